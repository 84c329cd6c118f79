"""The onboard daemon: six cameras -> policy -> control law -> PX4 offboard setpoints, supervised.

One asyncio program (`Daemon.run`), tasks under a TaskGroup:

- the six camera links (`companion.camera.serial_link`), each filling a latest-frame slot;
- the Zenoh telemetry publisher (5 Hz, latest values only);
- an attitude sampler (50 Hz) that keeps the autopilot's recent attitudes, so each policy output
  is rotated with the attitude at its image's capture time;
- the control loop: a tick on each fresh six-frame set, `rate_hz` the floor (or a fixed grid;
  `companion.daemon_loop`). One tick:

  1. rig snapshot; if all six faces are fresh and it is a new image, start the inference (on the
     policy's worker thread) and wait for it at most `inference_budget_s` (a slower result is used
     by a later tick);
  2. control law on the latest valid policy output (attitude at capture, current position);
     steps 1 and 2 are `companion.daemon_pilot`;
  3. `HealthMonitor.step` (companion.health) decides: fly, hover, engage or stream (who may
     engage and when: `companion.daemon_engage`), failsafe, release;
  4. the setpoint goes to the autopilot; then the side outputs (MCAP record, telemetry, sd_notify).

systemd: READY=1 the first time the pipeline is healthy; WATCHDOG=1 from the loop itself, only
after a tick that started on time (`watchdog_max_late_s`), so a stuck event loop or a dead control
loop stops the pings and systemd restarts the service. A stale camera or model is not a reason to
restart: the health state machine hovers, then fails safe (Hold/Land).

SIGTERM/SIGINT: stop the loop, zero velocity, offboard stop (Hold), close the logs and the links,
return normally (exit 0). Every shutdown step is bounded by `shutdown_timeout_s`.

The control socket (`companion.control_channel`) takes `companion engage|disengage|status`. A
missing autopilot heartbeat (`[autopilot] heartbeat_timeout_s`) is a hover, then the failsafe:
without it the vehicle's mode is unknown.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import signal
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any, TypeVar

from companion import daemon_reports as reports
from companion import frames
from companion.autopilot_types import Autopilot, OffboardState
from companion.camera.rig import Rig
from companion.camera.serial_link import SerialCameraLink, links_from_config, run_links
from companion.camera.slot import FrameSource
from companion.config import CompanionConfig
from companion.control import ControlOutput
from companion.control_channel import ControlChannel, ControlError
from companion.daemon_commands import Commander
from companion.daemon_engage import Engagement
from companion.daemon_loop import fixed_rate, frame_locked
from companion.daemon_outputs import Outputs, TickTimes
from companion.daemon_pilot import Pilot
from companion.errors import CompanionError, ModelError
from companion.health import (
    Action,
    HealthConfig,
    HealthDecision,
    HealthInputs,
    HealthMonitor,
    HealthState,
)
from companion.policy import Policy
from companion.pose_history import pose_enu
from companion.recorder import TOPIC_POLICY, FlightRecorder
from companion.sdnotify import SdNotifier
from companion.telemetry import TelemetryPublisher

log = logging.getLogger(__name__)
T = TypeVar("T")
ATTITUDE_SAMPLE_S = 0.02


class _StopRequested(Exception):
    """A stop arrived while starting up."""


class Daemon:
    """The supervised pipeline. `await run()` until `request_stop()` or SIGTERM/SIGINT.

    Parts are built from `config` unless given: `policy` (else `Policy.load`), `autopilot` (else
    `MavsdkAutopilot`), `frame_sources` (else serial links from `[cameras]`), `notifier` (else
    from `$NOTIFY_SOCKET`). `clock`: monotonic seconds, shared with the links and the adapter.
    """

    def __init__(
        self,
        config: CompanionConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.time_ns,
        policy: Policy | None = None,
        autopilot: Autopilot | None = None,
        frame_sources: Mapping[str, FrameSource] | None = None,
        notifier: SdNotifier | None = None,
        handle_signals: bool = True,
    ) -> None:
        self.config = config
        d = config.daemon
        self._clock = clock
        self._policy = policy
        self._autopilot = autopilot
        self._commander: Commander | None = None
        self._handle_signals = handle_signals
        self._links: dict[str, SerialCameraLink] = {}
        if frame_sources is None:
            self._links = links_from_config(config.cameras, clock=clock)
            frame_sources = self._links
        self._rig = Rig(config.cameras, frame_sources)
        health_config = HealthConfig(d.stale_hover_after_s, d.failsafe_after_s)
        self.health = HealthMonitor(health_config, start_s=clock())
        recorder = FlightRecorder(
            config.recorder,
            drone_id=config.drone.id,
            metadata={"config": str(config.source or "")},
            clock_ns=clock_ns,
            monotonic=clock,
        )
        telemetry = TelemetryPublisher(config.telemetry, clock=clock, clock_ns=clock_ns)
        wall_offset_ns = clock_ns() - int(clock() * 1e9)
        self.outputs = Outputs(
            recorder,
            telemetry,
            notifier if notifier is not None else SdNotifier(),
            self._links,
            wall_ns_of=lambda t_s: int(t_s * 1e9) + wall_offset_ns,
            watchdog_max_late_s=d.watchdog_max_late_s,
        )
        self._stop = asyncio.Event()
        self._stop_reason = ""
        self._pilot = Pilot(config, self.outputs.event)
        self.engagement = Engagement(
            d.engage,
            requires_airborne=d.engage_requires_airborne,
            heartbeat_timeout_s=config.autopilot.heartbeat_timeout_s,
            events=self.outputs.event,
        )
        self._control_channel: ControlChannel | None = None
        if d.control_socket:
            self._control_channel = ControlChannel(d.control_socket, self._on_control)
        self.ticks = 0
        self.skipped_ticks = 0

    @property
    def ready(self) -> bool:
        """READY=1 was sent: the pipeline has been healthy at least once."""
        return self.outputs.ready_sent

    # -- lifecycle -------------------------------------------------------------------------

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the daemon to stop (call from the event loop's thread; signals do)."""
        if not self._stop.is_set():
            log.info("stopping: %s", reason)
            self._stop_reason = reason
            self._stop.set()

    async def run(self) -> None:
        """Start everything, fly until stopped, shut down safely. Raises `CompanionError` when
        a part cannot start (model refused, autopilot not found, recorder directory unusable)."""
        loop = asyncio.get_running_loop()
        if self._handle_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, self.request_stop, sig.name)
        keepalive = asyncio.create_task(self._startup_keepalive(), name="watchdog-startup")
        try:
            self.outputs.recorder.start()
            self.outputs.event("starting", "info", {"drone_id": self.config.drone.id})
            await self.outputs.telemetry.open()
            await self._open_control_channel()
            if self._policy is None:
                load = asyncio.to_thread(Policy.load, self.config.policy, clock=self._clock)
                try:
                    self._policy = await self._until_stopped(load)
                except ModelError as exc:  # the log says why the daemon stopped
                    self.outputs.event("policy refused", "error", str(exc))
                    self._stop_reason = f"policy refused: {exc}"
                    raise
            self.outputs.event(
                "policy loaded",
                "info",
                {
                    "sha256": self._policy.sha256,
                    "fused": self._policy.fused,
                    "warmup_ms": 1e3 * (self._policy.warmup_latency_s or 0.0),
                    "reference_error_mps": self._policy.reference_error_mps,  # None: no check
                },
            )
            await self._supervise(keepalive)
        except _StopRequested:
            log.info("stopped while starting up")
        finally:
            keepalive.cancel()
            await self._shutdown()
            if self._handle_signals:
                for sig in (signal.SIGTERM, signal.SIGINT):
                    loop.remove_signal_handler(sig)

    async def _open_control_channel(self) -> None:
        """The control socket is for the operator; without it the drone is never engaged in
        "ground" mode, which is safe: log why and fly on."""
        channel = self._control_channel
        if channel is None:
            return
        try:
            await channel.open()
        except ControlError as exc:
            self._control_channel = None
            log.warning("%s", exc)
            self.outputs.event("control socket unavailable", "warning", str(exc))

    def _on_control(self, command: str) -> dict[str, Any]:
        commander = self._commander
        offboard = commander.offboard_state if commander is not None else OffboardState.INACTIVE
        state, reason = self.health.state, self.health.reason
        return self.engagement.command(command, state, reason, offboard)

    async def _supervise(self, keepalive: asyncio.Task[None]) -> None:
        try:
            async with asyncio.TaskGroup() as group:
                background = [
                    group.create_task(self.outputs.telemetry.run(), name="telemetry"),
                    group.create_task(self._sample_attitude(), name="attitude-sampler"),
                ]
                if self._links:
                    links = run_links(self._links)
                    background.append(group.create_task(links, name="camera-links"))
                group.create_task(self._main(background, keepalive), name="control")
        except BaseExceptionGroup as group:
            first = group.exceptions[0]
            if len(group.exceptions) == 1 and isinstance(first, CompanionError | _StopRequested):
                raise first from None  # one clear error for the CLI (e.g. no autopilot found)
            raise

    async def _main(
        self, background: list[asyncio.Task[Any]], keepalive: asyncio.Task[None]
    ) -> None:
        try:
            if self._autopilot is None:
                from companion.autopilot import MavsdkAutopilot  # MAVSDK only where it is used

                self._autopilot = MavsdkAutopilot(self.config.autopilot, clock=self._clock)
            self._commander = Commander(
                self._autopilot,
                clock=self._clock,
                events=self.outputs.event,
                timeout_s=self.config.daemon.shutdown_timeout_s,
                engage_retry_s=self.config.daemon.engage_retry_s,
                failsafe_action=self.config.autopilot.failsafe_action,
            )
            await self._until_stopped(self._autopilot.connect())
            keepalive.cancel()
            await self._loop()
        finally:
            for task in background:
                task.cancel()

    async def _until_stopped(self, work: Awaitable[T]) -> T:
        """`await work`, or cancel it and raise `_StopRequested` when a stop comes first."""
        task = asyncio.ensure_future(work)
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop.cancel()
        if task.done():
            return task.result()
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, TimeoutError, CompanionError):
            await asyncio.wait_for(task, self.config.daemon.shutdown_timeout_s)
        raise _StopRequested

    async def _startup_keepalive(self) -> None:
        """WATCHDOG=1 while starting: each start-up step is bounded by its own timeout."""
        interval = self.outputs.notifier.watchdog_interval_s
        while interval is not None:
            self.outputs.notifier.watchdog()
            await asyncio.sleep(interval)

    async def _sample_attitude(self) -> None:
        while True:
            if self._autopilot is not None:
                self._pilot.attitudes.add_from(self._autopilot.telemetry())
            await asyncio.sleep(ATTITUDE_SAMPLE_S)

    # -- the loop --------------------------------------------------------------------------

    async def _loop(self) -> None:
        d = self.config.daemon
        log.info(
            "control loop: %s, at least %g Hz",
            "ticks on each fresh six-frame set" if d.tick_on_frames else "fixed rate",
            d.rate_hz,
        )
        if d.tick_on_frames:
            await frame_locked(self._tick, self._rig, self._stop, self._clock, d.period_s)
        else:
            await fixed_rate(self._tick, self._stop, self._clock, d.period_s, self._skipped)

    def _skipped(self, missed: int) -> None:
        self.skipped_ticks += missed

    async def _tick(self, now_s: float, late_s: float) -> None:
        commander, policy = self._commander, self._policy
        assert commander is not None and policy is not None
        self.ticks += 1
        snapshot = self._rig.snapshot(now_s)
        new_image, collected = await self._pilot.infer(snapshot, policy)
        fresh = collected[1] if collected is not None and collected[1] is new_image else None

        telemetry = commander.autopilot.telemetry()
        self._pilot.attitudes.add_from(telemetry)
        pos_enu, yaw_enu = pose_enu(telemetry, now_s, self.config.daemon.telemetry_max_age_s)
        control, output_ok, problem = self._pilot.control(
            now_s, snapshot, telemetry, pos_enu, yaw_enu, policy
        )
        heartbeat = self.engagement.heartbeat_problem(telemetry, now_s)
        if heartbeat and self.health.state is not HealthState.STARTING:
            control, output_ok, problem = None, False, heartbeat  # mode unknown: hover, failsafe
        hover = lambda: self._pilot.law.hover(yaw_enu, "disengage")  # noqa: E731
        gate = await self.engagement.before_step(commander, hover, telemetry, now_s, self.health)
        decision = self.health.step(
            HealthInputs(
                now_s=now_s,
                output_time_s=self._pilot.output_time_s,
                output_ok=output_ok,
                problem=problem,
                offboard=commander.offboard_state,
                engage_allowed=gate.engage_allowed,
                stream_allowed=gate.stream_allowed,
                waiting=gate.waiting,
                reengage_allowed=self.engagement.reengage_allowed and commander.idle,
            )
        )
        self.engagement.after_step(decision, commander)
        command, sent = await self._act(decision, control, yaw_enu)
        times = TickTimes(now_s, late_s, self._clock(), new_image, fresh)
        if collected is not None:
            payload = reports.policy_payload(*collected)
            self.outputs.recorder.record(TOPIC_POLICY, payload)
        counters = {
            "in_state_s": round(now_s - self.health.since_s, 3),
            "ticks": self.ticks,
            "skipped_ticks": self.skipped_ticks,
            "setpoint_errors": commander.setpoint_errors,
        }
        self.outputs.tick(
            decision, command, sent, times, telemetry, commander.offboard_state, counters
        )

    async def _act(
        self, decision: HealthDecision, control: ControlOutput | None, yaw_enu_rad: float
    ) -> tuple[ControlOutput | None, bool]:
        """Carry out the decision; (the command sent or meant to be, whether it was sent)."""
        commander = self._commander
        assert commander is not None
        action = decision.action
        if action is Action.FLY and control is not None:
            return control, await commander.send(control)
        if action in (Action.HOVER, Action.FLY):
            command = self._pilot.law.hover(yaw_enu_rad, decision.reason)
            return command, await commander.send(command)
        if action is Action.STREAM:
            command = self._pilot.law.hover(yaw_enu_rad, decision.reason)
            return command, await commander.stream(command)
        if action is Action.ENGAGE:
            finite = math.isfinite(yaw_enu_rad)
            commander.engage(float(frames.yaw_enu_to_ned(yaw_enu_rad)) if finite else None)
        elif action is Action.FAILSAFE or decision.state is HealthState.FAILSAFE:
            commander.failsafe()  # no-op once done; retried after a refusal
        elif action is Action.RELEASE:
            await commander.release()
        return None, False

    # -- shutdown --------------------------------------------------------------------------

    async def _shutdown(self) -> None:
        """Zero velocity and Hold if commanding, then close everything; each step bounded."""
        timeout_s = self.config.daemon.shutdown_timeout_s
        reason = self._stop_reason or "daemon ending"
        self.outputs.notifier.stopping(f"stopping: {reason}")
        stop = HealthInputs(self._clock(), None, False, reason, stop_requested=True)
        self.outputs.transition(self.health.step(stop))
        commander = self._commander
        if commander is not None:
            max_age_s = self.config.daemon.telemetry_max_age_s
            _, yaw_enu = pose_enu(commander.autopilot.telemetry(), self._clock(), max_age_s)
            await commander.safe_stop(self._pilot.law.hover(yaw_enu, "shutdown"))
        self._pilot.cancel()  # the model thread itself is abandoned by policy.close
        self.outputs.event("stopped", "info", reason)
        if self._control_channel is not None:
            await self._control_channel.close()
        if commander is not None:
            await commander.guarded("telemetry close", self.outputs.telemetry.close())
            await commander.guarded("autopilot close", commander.autopilot.close())
        else:
            await self.outputs.telemetry.close()
        if self._policy is not None:
            await asyncio.to_thread(self._policy.close, min(timeout_s, 2.0))
        await asyncio.to_thread(self.outputs.recorder.close, timeout_s)
        self.outputs.notifier.close()
        log.info("stopped")
