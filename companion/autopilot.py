"""The MAVSDK autopilot adapter (`MavsdkAutopilot`); the contract lives in `autopilot_types`.

Frames and units: PX4's local NED (x north, y east, z down; m, m/s), attitude as the NED <- FRD
quaternion (w, x, y, z), yaw in radians NED (0 = north, clockwise). MAVSDK wants the yaw setpoint
in degrees: `MavsdkAutopilot` converts at the call, nowhere else.

Facts the adapter is built around (see FACTS.md):

- MAVSDK re-sends the last offboard setpoint at 20 Hz by itself; freshness is the daemon's job.
- `Offboard.is_active()` means "MAVSDK is streaming", not "the vehicle is in OFFBOARD": the mode
  comes from the heartbeat (1 Hz on PX4) and, sooner, from PX4's CURRENT_MODE (sent within ~0.1 s
  of a change; read through MavlinkDirect, `companion.autopilot_direct`). The adapter watches both:
  once the vehicle has been seen in OFFBOARD, any other mode means the pilot (or a PX4 failsafe)
  took over, `offboard_state` becomes LOST, and `set_velocity_ned` refuses to send
  (`OffboardLostError`). READY (operator engagement) streams one raw setpoint per call, so the
  stream stops when the daemon stops; the pilot's switch to OFFBOARD makes it ACTIVE.
- A MAVSDK command blocks an executor thread for up to ~2 s (its own timeout), and destroying
  MAVSDK under a blocked call can hang the interpreter. So calls are awaited with a timeout but
  never cancelled (`_call`), and `close()` lets them finish (at most `close_timeout_s`) before
  destroying; if one is still stuck it leaves MAVSDK alive rather than hang.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Coroutine
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
from mavsdk import log_subscribe
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk, MavsdkError
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync
from numpy.typing import ArrayLike, NDArray

from companion import autopilot_mavlink as mav
from companion.autopilot_direct import DirectLink
from companion.autopilot_feed import TelemetryFeed
from companion.autopilot_types import (
    Autopilot,
    AutopilotConfig,
    AutopilotTelemetry,
    FlightMode,
    OffboardState,
    Stamped,
)
from companion.errors import AutopilotError, OffboardLostError

__all__ = [
    "Autopilot",
    "AutopilotConfig",
    "AutopilotTelemetry",
    "FlightMode",
    "MavsdkAutopilot",
    "OffboardState",
    "Stamped",
    "forward_mavsdk_logs",
]

FloatArray = NDArray[np.float64]
T = TypeVar("T")
_POLL_S = 0.02  # how often waits re-check telemetry
logger = logging.getLogger(__name__)


def forward_mavsdk_logs(target: logging.Logger | None = None) -> None:
    """Send MAVSDK's own log lines (process-wide) to `target` instead of stdout."""
    out = target if target is not None else logging.getLogger("mavsdk")
    levels = (logging.DEBUG, logging.INFO, logging.WARNING, logging.ERROR)

    def on_log(level: Any, message: str, file: str | None, line: int) -> bool:
        out.log(levels[min(int(level), 3)], "%s (%s:%d)", message, file or "?", line)
        return True

    log_subscribe(on_log)


class MavsdkAutopilot:
    """`Autopilot` on MAVSDK 4 (`mavsdk.asyncio`). Use `async with` or connect()/close()."""

    def __init__(
        self, config: AutopilotConfig, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.config = config
        self._clock = clock
        self._mavsdk: Any = None
        self._action: Any = None
        self._offboard: Any = None
        self._telemetry_api: Any = None
        self._telemetry_task: asyncio.Task[None] | None = None
        self._direct: DirectLink | None = None
        self._in_flight: set[asyncio.Future[Any]] = set()
        self._feed = TelemetryFeed(clock, on_mode=self._mode_seen)
        self._offboard_state = OffboardState.INACTIVE
        self._lost_reason: str | None = None
        self._closed = False

    async def __aenter__(self) -> MavsdkAutopilot:
        await self.connect()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # -- state -------------------------------------------------------------------------------

    def telemetry(self) -> AutopilotTelemetry:
        return self._feed.value

    @property
    def offboard_state(self) -> OffboardState:
        return self._offboard_state

    @property
    def offboard_lost_reason(self) -> str | None:
        return self._lost_reason

    # -- commands ----------------------------------------------------------------------------

    async def connect(self) -> None:
        cfg = self.config
        if self._mavsdk is not None or self._closed:
            raise AutopilotError("connect() may be called once per MavsdkAutopilot")
        self._mavsdk = Mavsdk(
            Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        )
        try:
            await self._call("add connection " + cfg.url, self._mavsdk.add_any_connection(cfg.url))
            system = await self._call(
                "discovery",
                self._mavsdk.first_autopilot(cfg.discovery_timeout_s),
                timeout_s=cfg.discovery_timeout_s + 1.0,
            )
            if system is None:
                raise AutopilotError(
                    f"no autopilot on {cfg.url} within {cfg.discovery_timeout_s:g} s"
                )
            self._action = ActionAsync(system)
            self._offboard = OffboardAsync(system)
            self._telemetry_api = TelemetryAsync(system)
            target = await self._call("system id", system.get_system_id())
            self._direct = DirectLink(system, own_system_id=1, target_system=int(target))
            self._telemetry_task = asyncio.create_task(
                self._feed.run(self._telemetry_api, self._direct), name="autopilot-telemetry"
            )
            await self._wait_until(
                lambda: self._feed.health_ok, cfg.health_timeout_s, "health checks"
            )
            logger.info("autopilot on %s: connected and healthy", cfg.url)
            if cfg.arm:
                await self.arm()
            if cfg.takeoff:
                await self.takeoff()
        except BaseException:
            await self.close()
            raise

    async def arm(self) -> None:
        await self._call("arm", self._require(self._action).arm())

    async def takeoff(self) -> None:
        has_landed_state = lambda: self._feed.value.in_air is not None  # noqa: E731
        await self._wait_until(has_landed_state, self.config.health_timeout_s, "landed state")
        in_air = self._feed.value.in_air
        if in_air is not None and in_air.value:
            logger.info("takeoff skipped: already in the air")
            return
        await self._call("takeoff", self._require(self._action).takeoff())
        seen_takeoff = False

        def climbed() -> bool:
            nonlocal seen_takeoff
            mode, flying = self._feed.value.flight_mode, self._feed.value.in_air
            if mode is not None and mode.value is FlightMode.TAKEOFF:
                seen_takeoff = True
                return False
            return seen_takeoff and flying is not None and flying.value

        await self._wait_until(climbed, self.config.takeoff_timeout_s, "takeoff")

    async def start_offboard(self, yaw_ned_rad: float | None = None) -> None:
        cfg = self.config
        offboard = self._require(self._offboard)
        if self._offboard_state is OffboardState.ACTIVE:
            return
        if yaw_ned_rad is None:
            yaw_ned_rad = self._current_yaw_ned_rad()
        await self._send_setpoint(np.zeros(3), yaw_ned_rad)
        if cfg.offboard_prestream_s > 0.0:
            await asyncio.sleep(cfg.offboard_prestream_s)
        t_request_s = self._clock()
        await self._call("offboard start", offboard.start())

        def in_offboard() -> bool:
            mode = self._feed.value.flight_mode
            return (
                mode is not None and mode.value is FlightMode.OFFBOARD and mode.t_s >= t_request_s
            )

        await self._wait_until(
            in_offboard, cfg.offboard_confirm_timeout_s, "OFFBOARD in the heartbeat"
        )
        self._offboard_state = OffboardState.ACTIVE
        self._lost_reason = None
        logger.info("offboard active")

    async def prepare_offboard(self) -> None:
        if self._offboard_state in (OffboardState.ACTIVE, OffboardState.READY):
            return
        mode = self._feed.value.flight_mode
        if mode is not None and mode.value is FlightMode.OFFBOARD:
            # Not commanded by this daemon, so following stale setpoints (MAVSDK's re-sends after
            # a link drop, on which PX4 resumed OFFBOARD): stop them and hold; an operator
            # engages again.
            logger.warning("the vehicle is in OFFBOARD without this daemon commanding: HOLD")
            await self._call("offboard stop (Hold)", self._require(self._offboard).stop())
            raise AutopilotError(
                "the vehicle was in OFFBOARD on stale setpoints: switched to HOLD; engage again"
            )
        report = self._feed.value.mode_report
        if report is not None and report.value.resumes_offboard:
            current = report.value
            logger.warning(
                "PX4 would resume OFFBOARD on our first setpoint (%s now, OFFBOARD intended): "
                "re-asserting %s",
                current.mode.name,
                current.mode.name,
            )
            direct = self._require(self._direct)
            result = await self._call("re-assert mode", direct.set_mode(current.custom_mode))
            if result != 0:
                raise AutopilotError(
                    f"PX4 refused to stay in {current.mode.name} (DO_SET_MODE result {result}): "
                    "it would resume OFFBOARD on our setpoints"
                )
            await self._wait_until(
                lambda: not self._resumes_offboard(), self.config.command_timeout_s, "CURRENT_MODE"
            )
        self._offboard_state = OffboardState.READY
        self._lost_reason = None

    def _resumes_offboard(self) -> bool:
        report = self._feed.value.mode_report
        return report is not None and report.value.resumes_offboard

    async def stream_velocity_ned(self, vel_ned_mps: ArrayLike, yaw_ned_rad: float) -> None:
        vel = self._checked(vel_ned_mps, yaw_ned_rad)
        if self._offboard_state is not OffboardState.READY:
            raise AutopilotError("not READY: call prepare_offboard() first")
        direct = self._require(self._direct)
        north, east, down = (float(v) for v in vel)
        t_ms = int(self._clock() * 1000.0)
        fields = mav.velocity_setpoint_fields(
            direct.target_system, t_ms, (north, east, down), yaw_ned_rad
        )
        await self._call("setpoint stream", direct.send_setpoint(fields))

    @staticmethod
    def _checked(vel_ned_mps: ArrayLike, yaw_ned_rad: float) -> FloatArray:
        vel = np.asarray(vel_ned_mps, dtype=np.float64)
        if vel.shape != (3,) or not np.all(np.isfinite(vel)) or not math.isfinite(yaw_ned_rad):
            raise AutopilotError(
                f"setpoint must be 3 finite m/s and a finite yaw, got {vel!r}, {yaw_ned_rad!r}"
            )
        return vel

    async def set_velocity_ned(self, vel_ned_mps: ArrayLike, yaw_ned_rad: float) -> None:
        vel = self._checked(vel_ned_mps, yaw_ned_rad)
        if self._offboard_state is OffboardState.LOST:
            raise OffboardLostError(f"offboard lost: {self._lost_reason}")
        if self._offboard_state is not OffboardState.ACTIVE:
            raise AutopilotError("offboard is not active: call start_offboard() first")
        await self._send_setpoint(vel, yaw_ned_rad)

    async def stop_offboard(self) -> None:
        previous = self._offboard_state
        self._offboard_state = OffboardState.INACTIVE
        if previous is OffboardState.READY:
            logger.info("setpoint stream stopped (the vehicle was never switched to OFFBOARD)")
        if previous is OffboardState.LOST:
            logger.info("offboard stopped; the pilot has control, no mode change")
        if previous is OffboardState.ACTIVE:
            await self._leaving_offboard(
                previous, "offboard stop", self._require(self._offboard).stop()
            )

    async def hold(self) -> None:
        if self._offboard_state is OffboardState.ACTIVE:
            await self.stop_offboard()  # MAVSDK's offboard stop is a switch to HOLD
        else:
            await self._leaving_offboard(
                self._offboard_state, "hold", self._require(self._action).hold()
            )

    async def land(self) -> None:
        await self._leaving_offboard(
            self._offboard_state, "land", self._require(self._action).land()
        )

    async def failsafe(self) -> None:
        logger.warning("autopilot failsafe: %s", self.config.failsafe_action)
        await (self.land() if self.config.failsafe_action == "land" else self.hold())

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._offboard_state is OffboardState.ACTIVE:
                logger.warning("closing while commanding offboard: running the failsafe first")
                try:
                    await self.failsafe()
                except AutopilotError as exc:
                    logger.error("failsafe on close failed: %s", exc)
        finally:
            await self._release()

    # -- internals ---------------------------------------------------------------------------

    def _require(self, plugin: Any) -> Any:
        if plugin is None or self._mavsdk is None:
            raise AutopilotError("not connected: call connect() first")
        return plugin

    def _current_yaw_ned_rad(self) -> float:
        q = self._feed.value.q_ned_frd_wxyz
        if q is None or not np.all(np.isfinite(q.value)):
            return 0.0
        w, x, y, z = (float(c) for c in q.value)
        return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))

    async def _send_setpoint(self, vel_ned_mps: FloatArray, yaw_ned_rad: float) -> None:
        north, east, down = (float(v) for v in vel_ned_mps)
        setpoint = VelocityNedYaw(north, east, down, math.degrees(yaw_ned_rad))
        await self._call(
            "velocity setpoint", self._require(self._offboard).set_velocity_ned(setpoint)
        )

    async def _leaving_offboard(
        self, previous: OffboardState, what: str, call: Coroutine[Any, Any, Any]
    ) -> None:
        """Run a mode-changing call; mark offboard inactive first so the change is not a loss."""
        self._offboard_state = OffboardState.INACTIVE
        try:
            await self._call(what, call)
        except BaseException:
            if previous is OffboardState.ACTIVE:
                self._offboard_state = previous  # the vehicle may still be following us
            raise

    async def _call(
        self, what: str, call: Coroutine[Any, Any, T], timeout_s: float | None = None
    ) -> T:
        """Await a MAVSDK call for at most `timeout_s` without ever cancelling it.

        A cancelled wrapper leaves its executor thread blocked in C, untracked; instead the call
        stays in `_in_flight` until MAVSDK itself returns, and `close()` waits for it.
        """
        timeout = self.config.command_timeout_s if timeout_s is None else timeout_s
        task = asyncio.ensure_future(call)
        self._in_flight.add(task)
        task.add_done_callback(self._call_done)
        done, _ = await asyncio.wait({task}, timeout=timeout)
        if not done:
            raise AutopilotError(f"{what}: no answer within {timeout:g} s")
        try:
            return task.result()
        except MavsdkError as exc:
            raise AutopilotError(f"{what} failed: {exc}") from exc

    def _call_done(self, task: asyncio.Future[Any]) -> None:
        self._in_flight.discard(task)
        if not task.cancelled():
            task.exception()  # retrieved here so a late failure is not reported as unhandled

    async def _wait_until(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        try:
            async with asyncio.timeout(timeout_s):
                while not condition():
                    await asyncio.sleep(_POLL_S)
        except TimeoutError:
            raise AutopilotError(f"timed out after {timeout_s:g} s waiting for {what}") from None

    async def _release(self) -> None:
        task, self._telemetry_task = self._telemetry_task, None
        if task is not None:
            task.cancel()
            await asyncio.wait({task}, timeout=self.config.close_timeout_s)
        if self._in_flight:
            await asyncio.wait(set(self._in_flight), timeout=self.config.close_timeout_s)
        mavsdk, self._mavsdk = self._mavsdk, None
        self._action = self._offboard = self._telemetry_api = None
        direct, self._direct = self._direct, None
        if mavsdk is None:
            return
        if self._in_flight:
            logger.warning(
                "%d MAVSDK call(s) still in flight: not destroying MAVSDK", len(self._in_flight)
            )
            return
        if direct is not None:
            direct.destroy()
        mavsdk.destroy()

    def _mode_seen(self, mode: FlightMode, source: str) -> None:
        """The vehicle's mode, from a heartbeat or CURRENT_MODE: engaged, or taken over."""
        if self._offboard_state is OffboardState.READY and mode is FlightMode.OFFBOARD:
            self._offboard_state = OffboardState.ACTIVE
            logger.info("offboard active: the pilot or ground station switched to OFFBOARD")
        elif self._offboard_state is OffboardState.ACTIVE and mode is not FlightMode.OFFBOARD:
            self._offboard_state = OffboardState.LOST
            self._lost_reason = f"vehicle switched to {mode.name} (pilot or PX4 failsafe)"
            logger.warning("offboard lost (seen in %s): %s", source, self._lost_reason)


if TYPE_CHECKING:  # mypy checks that the adapter satisfies the contract
    _ADAPTER_IS_AN_AUTOPILOT: type[Autopilot] = MavsdkAutopilot
