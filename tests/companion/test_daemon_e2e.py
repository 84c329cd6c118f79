"""The daemon end to end with real parts: six pty cameras playing recorded frames, the pymavlink
PX4 emulator over loopback UDP (MAVSDK in between), a TorchScript policy, an MCAP log, Zenoh.

In-process tests drive the `Daemon` on the test's event loop (the policy's `_run_model` wrapped to
return NaN or to hang on demand); the SIGTERM test runs `companion run --config FILE` as a child
process with a systemd notify socket. How times are judged on a loaded machine: `daemon_rig`.
Start-up refusals are in `test_daemon_startup.py`, PX4's home frame in `test_daemon_home.py`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from companion.config import config_from_dict
from companion.daemon import Daemon
from companion.flight_log import TOPIC_HEALTH, TOPIC_SETPOINT, LogReader
from companion.health import HealthState
from companion.policy import Policy
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.drone import toml_text
from sim_harness.hil.px4_logic import Px4Mode

from .daemon_rig import (
    BODY_CMD_FLU,
    DO_SET_MODE,
    GUARD_S,
    REPO,
    ModelHook,
    Subscriber,
    daemon_log,
    document,
    flying_expected,
    free_tcp_port,
    hovering_east,
    is_zero,
    last_setpoint,
    quiet,
    until,
)


@pytest.fixture
def px4() -> Iterator[AutopilotEmulator]:
    """PX4 armed and hovering at 5 m in POSCTL, facing east; heartbeats at 20 Hz."""
    with hovering_east() as emulator:
        yield emulator


def test_flies_hovers_recovers_and_yields_to_the_pilot(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    port = free_tcp_port()
    config = config_from_dict(
        document(tmp_path, cameras, px4, make_policy_file("constant", BODY_CMD_FLU), port)
    )
    policy = Policy.load(config.policy)
    hook = ModelHook(policy)
    # The daemon's clock is the test's: its health transitions can be timed against a trigger.
    daemon = Daemon(config, policy=policy, handle_signals=False, clock=time.monotonic)
    monitor = Subscriber(port)

    async def hover_within(trigger: Callable[[], None], bar_s: float = 0.5) -> None:
        """The daemon decides to hover within `bar_s` of the trigger, and the vehicle gets it.

        Timed from the trigger to the ACTIVE -> HOVER transition the daemon stamped on the tick
        that sent the zero setpoint: the daemon's reaction, not the test's polling delay. (A
        tick already running when the trigger came may stamp a time just before it.)
        """
        await until(lambda: flying_expected(last_setpoint(px4)), GUARD_S, "flying again")
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        seen = len(daemon.health.history)  # no await since the check: still ACTIVE
        triggered_s = time.monotonic()
        trigger()
        await until(lambda: is_zero(last_setpoint(px4)), GUARD_S, "a zero-velocity setpoint")
        assert daemon.health.state is HealthState.HOVER
        after = list(daemon.health.history)[seen:]
        hover = next(t for t in after if t.target is HealthState.HOVER)
        assert hover.source is HealthState.ACTIVE
        assert hover.t_s - triggered_s <= bar_s

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "OFFBOARD")
            await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
            assert daemon.ready
            # Setpoints flow in OFFBOARD: NED velocity frame, the policy's command rotated into
            # NED with the attitude (exactly EXPECTED_NED once the vehicle stops accelerating).
            # The five are judged as one snapshot: the emulator's thread keeps appending.
            recent: list[Any] = []

            def steady() -> bool:
                recent[:] = px4.setpoints()[-5:]
                return len(recent) == 5 and all(flying_expected(s) for s in recent)

            await until(steady, GUARD_S, "five consecutive expected NED setpoints")
            assert all(s.frame == 1 and s.uses_velocity and s.uses_yaw for s in recent)
            assert px4.mode is Px4Mode.OFFBOARD

            # Telemetry reached a real subscriber on loopback.
            await until(
                lambda: monitor.latest("swarm/d1/setpoint") is not None, GUARD_S, "telemetry"
            )
            state = monitor.latest("swarm/d1/state")
            assert state is not None and state["data"]["health"] == "active"
            assert state["data"]["flight_mode"] == "offboard"
            assert "d1" in monitor.table.render() and "offboard" in monitor.table.render()

            # One camera stops: hover within 0.5 s; it comes back: flying again.
            await hover_within(lambda: cameras.stall("left"))
            # The stalled face is named: skewed (its last frame older than the newest face's by
            # more than the skew limit) or stale (older than the freshness limit), whichever the
            # first tick after the stall sees; on a loaded machine that can be either.
            reason = daemon.health.reason
            assert "left: stale" in reason or "left: skewed" in reason, reason
            cameras.resume("left")

            # NaN model output: hover at once.
            await hover_within(lambda: setattr(hook, "mode", "nan"))
            assert "non-finite" in daemon.health.reason
            hook.mode = "normal"

            # The model hangs: hover within 0.5 s, and flying again once it returns.
            hook.release.clear()
            await hover_within(lambda: setattr(hook, "mode", "hang"))
            assert "no fresh inference" in daemon.health.reason
            hook.mode = "normal"
            hook.release.set()
            await until(lambda: flying_expected(last_setpoint(px4)), GUARD_S, "flying after hang")

            # The pilot flips the mode switch: the daemon stops commanding, never fights back.
            commands_before = len(px4.commands())
            assert px4.pilot_switch_mode(Px4Mode.POSCTL).name == "ACCEPTED"
            await until(lambda: daemon.health.state is HealthState.PILOT, GUARD_S, "PILOT")
            # MAVSDK re-sends the last setpoint by itself for ~2 s after the vehicle left
            # OFFBOARD (PX4 ignores them outside OFFBOARD), then stops.
            await until(quiet(px4, 0.5), GUARD_S, "MAVSDK to stop re-sending")
            assert px4.mode is Px4Mode.POSCTL
            assert not [c for c in px4.commands()[commands_before:] if c.command == DO_SET_MODE]
        finally:
            hook.release.set()
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)
        assert px4.mode is Px4Mode.POSCTL  # shutdown does not take the vehicle from the pilot

    try:
        asyncio.run(body())
    finally:
        monitor.close()
    messages = list(LogReader(daemon_log(tmp_path)).messages())
    events = [m.json()["event"] for m in messages if m.topic == TOPIC_HEALTH]
    loaded = next(m.json() for m in messages if m.json().get("event") == "policy loaded")
    assert loaded["detail"]["sha256"] == policy.sha256
    assert loaded["detail"]["fused"] is policy.fused and loaded["detail"]["warmup_ms"] > 0
    assert "active -> hover" in events and "hover -> active" in events
    assert "active -> pilot" in events and events[-1] == "stopped"
    released = next(
        m.log_time_ns
        for m in messages
        if m.topic == TOPIC_HEALTH and m.json()["event"] == "active -> pilot"
    )
    sent_after = [
        m
        for m in messages
        if m.topic == TOPIC_SETPOINT and m.log_time_ns > released and m.json()["sent"]
    ]
    assert not sent_after  # not one setpoint from the daemon once the pilot had the vehicle


@pytest.mark.parametrize(("action", "mode"), [("hold", Px4Mode.HOLD), ("land", Px4Mode.LAND)])
def test_a_long_hover_escalates_to_the_failsafe_and_stays_there(
    tmp_path: Path,
    cameras: CameraEmulator,
    px4: AutopilotEmulator,
    make_policy_file: Any,
    action: str,
    mode: Px4Mode,
) -> None:
    doc = document(
        tmp_path, cameras, px4, make_policy_file("constant", BODY_CMD_FLU), free_tcp_port()
    )
    doc["daemon"]["failsafe_after_s"] = 0.6
    doc["autopilot"]["failsafe_action"] = action
    daemon = Daemon(config_from_dict(doc), handle_signals=False)

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
            cameras.stall("down")
            await until(lambda: daemon.health.state is HealthState.HOVER, GUARD_S, "HOVER")
            await until(lambda: px4.mode is mode, GUARD_S, f"{mode.name} after the failsafe")
            assert daemon.health.state is HealthState.FAILSAFE
            cameras.resume("down")  # fresh images again: the daemon must not re-engage
            modes = len(px4.mode_changes())
            await asyncio.sleep(1.0)
            assert px4.mode is mode and len(px4.mode_changes()) == modes
            assert daemon.health.state is HealthState.FAILSAFE
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    asyncio.run(body())


def test_sigterm_holds_exits_0_and_leaves_a_readable_log(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    """`companion run` under a systemd-like manager: READY, WATCHDOG, then SIGTERM."""
    doc = document(
        tmp_path, cameras, px4, make_policy_file("constant", BODY_CMD_FLU), free_tcp_port()
    )
    config_path = tmp_path / "companion.toml"
    config_path.write_text(toml_text(doc))
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"vision-swarm-test-{os.getpid()}-{time.monotonic_ns()}"
    notify.bind("\0" + name)  # abstract namespace, as NOTIFY_SOCKET="@name"
    notify.settimeout(0.2)
    env = {**os.environ, "NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "400000"}
    env.pop("WATCHDOG_PID", None)
    child = subprocess.Popen(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(config_path)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    received: list[str] = []

    def receive_until(predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > deadline or child.poll() is not None:
                pytest.fail(f"no {what}: got {received}, child {child.poll()}")
            with contextlib.suppress(TimeoutError):
                received.extend(notify.recv(4096).decode().splitlines())

    at_sigterm: list[Any] = []

    def flying_the_policy_now() -> bool:
        """OFFBOARD, and the latest setpoint is the policy's eastward command (not the zero
        prestream nor a hover): judged on one snapshot, the one the SIGTERM then follows."""
        at_sigterm[:] = px4.setpoints()
        return px4.mode is Px4Mode.OFFBOARD and bool(at_sigterm) and at_sigterm[-1].vy_mps > 0.9

    try:
        receive_until(lambda: "READY=1" in received, 60.0, "READY=1")
        ready_at = received.index("READY=1")
        receive_until(lambda: received[ready_at:].count("WATCHDOG=1") >= 3, GUARD_S, "WATCHDOG=1")
        receive_until(flying_the_policy_now, GUARD_S, "the policy's setpoints in OFFBOARD")
        child.send_signal(signal.SIGTERM)
        output, _ = child.communicate(timeout=20.0)
        notify.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while True:
                received.extend(notify.recv(4096).decode().splitlines())
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        notify.close()
    text = output.decode(errors="replace")
    assert child.returncode == 0, text
    assert px4.mode is Px4Mode.HOLD, text
    # The daemon's own switch to HOLD, after the SIGTERM; the last velocity it streamed before
    # that switch (emulator timestamps, not the order the test saw them in) was zero.
    offboard_end = px4.mode_changes()[-1]
    assert (offboard_end.old, offboard_end.new) == (Px4Mode.OFFBOARD, Px4Mode.HOLD)
    assert offboard_end.reason == "DO_SET_MODE"
    after_sigterm = px4.setpoints()[len(at_sigterm) :]
    before_hold = [s for s in after_sigterm if s.t_s <= offboard_end.t_s]
    assert before_hold and is_zero(before_hold[-1]), text
    assert all(is_zero(s) for s in after_sigterm if s.t_s > offboard_end.t_s)
    assert "STOPPING=1" in received

    log = daemon_log(tmp_path)
    summary = subprocess.run(
        [sys.executable, "-m", "companion.cli", "log", "summary", str(log)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert summary.returncode == 0, summary.stderr
    assert ": complete" in summary.stdout
    for topic in ("/camera/stitched", "/policy/output", TOPIC_SETPOINT, "/autopilot/telemetry"):
        assert topic in summary.stdout
    assert "offboard stopped" in summary.stdout and "stopped: SIGTERM" in summary.stdout
    setpoints = [m.json() for m in LogReader(log).messages() if m.topic == TOPIC_SETPOINT]
    flown = [s for s in setpoints if s["action"] == "fly" and s["tick_latency_s"] is not None]
    assert flown and all(0.0 < s["tick_latency_s"] < 0.1 for s in flown)
