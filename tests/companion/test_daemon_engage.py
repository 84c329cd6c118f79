"""Who engages OFFBOARD, end to end: the daemon on the test's event loop with six pty cameras, the
pymavlink PX4 emulator behind MAVSDK on loopback UDP, a real TorchScript policy, and the real
control socket (`companion engage|disengage|status`).

The emulator behaves like PX4 here (checked against PX4 SITL, tests/px4): it refuses OFFBOARD
without fresh setpoints, goes back to OFFBOARD by itself when setpoints return after its
offboard-loss failsafe (the intended mode stays OFFBOARD), reports that intended mode in
CURRENT_MODE within a loop period of any change, and says MAV_STATE_CRITICAL during a failsafe.
Times asserted are the daemon's own transition stamps (its clock is the test's), with margins
far above the emulator's 20 ms loop; every other wait is a liveness bound.
"""

from __future__ import annotations

import asyncio
import os
import stat
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from pymavlink import mavutil

from companion.control_channel import send_command
from companion.health import HealthState
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.px4_logic import Px4Mode

from .daemon_rig import DO_SET_MODE, GUARD_S, until

BODY_CMD_FLU = (1.0, 0.0, 0.0)


def entered(daemon: Any, state: HealthState, since: int) -> bool:
    """Whether the daemon's health entered `state` after its first `since` transitions. For a
    state that may last a single tick (PILOT, when "operator" streams again right after a
    takeover), which polling the current state can miss on a busy machine."""
    return any(t.target is state for t in list(daemon.health.history)[since:])


def fly(daemon: Any, scenario: Callable[[], Awaitable[None]]) -> None:
    """Run the daemon on a fresh event loop while `scenario` plays; stop it afterwards."""

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            await scenario()
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    asyncio.run(body())


async def control(path: str, command: str) -> dict[str, Any]:
    """`companion engage|disengage|status`, from a thread (the daemon runs on this loop)."""
    return await asyncio.to_thread(send_command, path, command)


def set_modes(px4: AutopilotEmulator, since: int = 0) -> list[Any]:
    return [c for c in px4.commands()[since:] if c.command == DO_SET_MODE]


def test_operator_mode_streams_and_only_the_pilots_switch_engages(
    engage_rig: Any, control_socket_path: str
) -> None:
    rig = engage_rig()
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="operator")

    async def scenario() -> None:
        # Healthy: hover setpoints stream, the vehicle stays with the pilot.
        await until(lambda: len(px4.setpoints()) >= 20, GUARD_S, "a setpoint stream")
        assert px4.mode is Px4Mode.POSCTL and not set_modes(px4)
        assert all(abs(s.vx_mps) + abs(s.vy_mps) + abs(s.vz_mps) < 1e-6 for s in px4.setpoints())
        assert daemon.health.state is HealthState.STARTING
        assert "ready" in daemon.health.reason
        refused = await control(control_socket_path, "engage")
        assert not refused["ok"] and "switching the vehicle to OFFBOARD" in refused["message"]

        # The pilot switches to OFFBOARD: engaged, the policy flies.
        assert px4.pilot_switch_mode(Px4Mode.OFFBOARD).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        await until(lambda: px4.setpoints()[-1].vx_mps > 0.5, GUARD_S, "flying north")
        status = await control(control_socket_path, "status")
        assert status["state"] == "active" and status["offboard"] == "active"

        # The pilot takes over; the daemon stops, then streams again; the pilot re-engages.
        seen = len(daemon.health.history)
        assert px4.pilot_switch_mode(Px4Mode.POSCTL).name == "ACCEPTED"
        await until(lambda: entered(daemon, HealthState.PILOT, seen), GUARD_S, "PILOT")
        await until(lambda: daemon.health.state is HealthState.STARTING, GUARD_S, "STARTING")
        count = len(px4.setpoints())
        await until(lambda: len(px4.setpoints()) >= count + 10, GUARD_S, "streaming again")
        assert px4.mode is Px4Mode.POSCTL and not set_modes(px4)
        assert px4.pilot_switch_mode(Px4Mode.OFFBOARD).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "re-engaged")

        # The ground station's `companion disengage`: zero velocity, then Hold.
        reply = await control(control_socket_path, "disengage")
        assert reply["ok"]
        await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "HOLD")
        await until(lambda: daemon.health.state is HealthState.STARTING, GUARD_S, "waiting")

    fly(daemon, scenario)
    assert not Path(control_socket_path).exists()  # removed on exit


def test_a_restarted_daemon_does_not_take_back_px4s_offboard(
    engage_rig: Any, control_socket_path: str
) -> None:
    """PX4 left OFFBOARD by its offboard-loss failsafe (the companion died) and would go back to
    OFFBOARD on the first setpoint: the new daemon re-asserts PX4's mode before streaming."""
    rig = engage_rig(offboard_loss_mode=Px4Mode.HOLD)
    px4 = rig.px4
    # The crashed companion: setpoints, the pilot's switch, then silence.
    old = mavutil.mavlink_connection(f"udpout:127.0.0.1:{px4.local_port}", source_system=1)
    deadline = time.monotonic() + GUARD_S
    while px4.mode is not Px4Mode.OFFBOARD and time.monotonic() < deadline:
        old.mav.set_position_target_local_ned_send(
            0, 1, 1, 1, 0b0000101111000111, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
        )
        px4.pilot_switch_mode(Px4Mode.OFFBOARD)
        time.sleep(0.05)
    assert px4.mode is Px4Mode.OFFBOARD
    old.close()
    deadline = time.monotonic() + GUARD_S
    while px4.mode is Px4Mode.OFFBOARD and time.monotonic() < deadline:
        time.sleep(0.05)
    assert px4.mode is Px4Mode.HOLD  # PX4's failsafe, OFFBOARD still intended

    daemon = rig.daemon(control_socket_path, engage="operator")
    changes = len(px4.mode_changes())
    streamed = len(px4.setpoints())

    async def scenario() -> None:
        await until(
            lambda: len(px4.setpoints()) >= streamed + 30, GUARD_S, "the new daemon's stream"
        )
        await asyncio.sleep(1.0)
        assert px4.mode is Px4Mode.HOLD  # not resumed
        assert not px4.mode_changes()[changes:]
        reassert = set_modes(px4)
        assert len(reassert) == 1 and reassert[0].params[1:3] == (4.0, 3.0)  # AUTO LOITER
        assert px4.pilot_switch_mode(Px4Mode.OFFBOARD).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "engaged")

    fly(daemon, scenario)


def test_ground_mode_engages_only_on_companion_engage(
    engage_rig: Any, control_socket_path: str
) -> None:
    rig = engage_rig()
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="ground")

    async def scenario() -> None:
        await until(lambda: daemon.ready, GUARD_S, "a healthy pipeline")
        await asyncio.sleep(1.0)
        assert not px4.setpoints() and px4.mode is Px4Mode.POSCTL
        assert "companion engage" in daemon.health.reason
        assert stat.S_IMODE(os.stat(control_socket_path).st_mode) == 0o660  # root + service user
        # The operator's command line, as the ground station runs it over SSH.
        argv = [
            sys.executable,
            "-m",
            "companion.cli",
            "engage",
            "--socket",
            control_socket_path,
        ]
        done = await asyncio.to_thread(subprocess.run, argv, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        assert "engage requested" in done.stdout
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        assert px4.mode is Px4Mode.OFFBOARD

        assert (await control(control_socket_path, "disengage"))["ok"]
        await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "HOLD")
        await until(lambda: daemon.health.state is HealthState.STARTING, GUARD_S, "waiting")
        await asyncio.sleep(1.0)  # the engagement ended with the disengage: no new one
        assert px4.mode is Px4Mode.HOLD and daemon.health.state is HealthState.STARTING
        assert (await control(control_socket_path, "engage"))["ok"]
        await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "OFFBOARD again")

    fly(daemon, scenario)


def test_no_engagement_during_a_px4_failsafe(engage_rig: Any, control_socket_path: str) -> None:
    """A geofence breach or low battery: PX4 says CRITICAL, the daemon waits it out."""
    rig = engage_rig()
    px4 = rig.px4
    px4.set_failsafe(True)
    daemon = rig.daemon(control_socket_path, engage="auto")

    async def scenario() -> None:
        await until(lambda: "failsafe" in daemon.health.reason, GUARD_S, "the failsafe seen")
        await asyncio.sleep(1.5)
        assert not px4.setpoints() and not set_modes(px4) and px4.mode is Px4Mode.POSCTL
        assert daemon.health.state is HealthState.STARTING
        px4.set_failsafe(False)
        await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "engaged after it")

    fly(daemon, scenario)


def test_a_lost_heartbeat_hovers_then_fails_safe(engage_rig: Any, control_socket_path: str) -> None:
    """Telemetry flows but no HEARTBEAT: the mode is unknown, so the daemon stops flying."""
    rig = engage_rig()
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="auto", failsafe_after_s=1.0)

    async def scenario() -> None:
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        seen = len(daemon.health.history)
        lost_s = time.monotonic()
        px4.set_heartbeat_alive(False)
        await until(lambda: daemon.health.state is HealthState.FAILSAFE, GUARD_S, "FAILSAFE")
        after = list(daemon.health.history)[seen:]
        hover = next(t for t in after if t.target is HealthState.HOVER)
        assert "heartbeat lost" in hover.reason
        # heartbeat_timeout_s (3 s) after the last heartbeat (at most 1 s before the cut)
        assert 2.0 - 0.1 <= hover.t_s - lost_s <= 3.0 + 1.0
        await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "HOLD")

    fly(daemon, scenario)


def test_a_pilot_switch_is_seen_before_the_next_heartbeat(
    engage_rig: Any, control_socket_path: str
) -> None:
    """PX4's CURRENT_MODE arrives within ~0.1 s of the switch; the heartbeat up to 1 s later."""
    rig = engage_rig()
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="auto")

    async def scenario() -> None:
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        autopilot = daemon._commander.autopilot if daemon._commander else None
        assert autopilot is not None

        def heartbeat_s() -> float:
            status = autopilot.telemetry().status
            return -1.0 if status is None else status.t_s

        last = heartbeat_s()
        await until(lambda: heartbeat_s() != last, GUARD_S, "a heartbeat")
        seen = len(daemon.health.history)
        switched_s = time.monotonic()  # just after a heartbeat: the next is ~1 s away
        assert px4.pilot_switch_mode(Px4Mode.POSCTL).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.PILOT, GUARD_S, "PILOT")
        pilot = next(t for t in list(daemon.health.history)[seen:] if t.target is HealthState.PILOT)
        assert pilot.t_s - switched_s < 0.6

    fly(daemon, scenario)


def test_a_link_drop_longer_than_the_failsafe_ends_in_hold_until_the_pilot_engages(
    engage_rig: Any, control_socket_path: str
) -> None:
    """The radio link drops while flying: PX4's offboard-loss failsafe holds, the daemon hovers
    and runs its own failsafe once the link is back (PX4 may have resumed OFFBOARD on MAVSDK's
    re-sent setpoint meanwhile). It ends in Hold, streaming, until the pilot switches again."""
    rig = engage_rig(offboard_loss_mode=Px4Mode.HOLD)
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="operator", failsafe_after_s=1.0)

    async def scenario() -> None:
        await until(lambda: len(px4.setpoints()) >= 10, GUARD_S, "a setpoint stream")
        assert px4.pilot_switch_mode(Px4Mode.OFFBOARD).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")
        px4.set_link_alive(False)
        await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "PX4's loss failsafe")
        await until(lambda: daemon.health.state is HealthState.FAILSAFE, GUARD_S, "FAILSAFE")
        await asyncio.sleep(1.0)
        px4.set_link_alive(True)
        await until(lambda: daemon.health.state is HealthState.STARTING, GUARD_S, "waiting")
        await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "HOLD")
        changes = len(px4.mode_changes())
        await asyncio.sleep(3.0)  # the daemon streams again: PX4 must stay in HOLD
        assert not px4.mode_changes()[changes:]
        assert px4.pilot_switch_mode(Px4Mode.OFFBOARD).name == "ACCEPTED"
        await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "re-engaged")

    fly(daemon, scenario)


def test_a_vehicle_in_offboard_on_stale_setpoints_is_put_in_hold_not_adopted(
    engage_rig: Any,
) -> None:
    """PX4 is in OFFBOARD while this daemon is not commanding (it resumed on setpoints MAVSDK
    re-sent after the daemon had released it): getting ready for the pilot ends that in Hold."""
    from companion.autopilot import AutopilotConfig, MavsdkAutopilot
    from companion.errors import AutopilotError

    rig = engage_rig()
    px4 = rig.px4
    stale = mavutil.mavlink_connection(f"udpout:127.0.0.1:{px4.local_port}", source_system=1)

    async def body() -> None:
        config = AutopilotConfig(url=f"udpin://127.0.0.1:{px4.config.client_port}")
        async with MavsdkAutopilot(config) as autopilot:
            deadline = time.monotonic() + GUARD_S
            while autopilot.telemetry().flight_mode is None or (
                autopilot.telemetry().flight_mode.value.name != "OFFBOARD"
            ):
                assert time.monotonic() < deadline, "OFFBOARD never seen"
                stale.mav.set_position_target_local_ned_send(
                    0, 1, 1, 1, 0b0000101111000111, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0
                )
                px4.pilot_switch_mode(Px4Mode.OFFBOARD)
                await asyncio.sleep(0.05)
            with pytest.raises(AutopilotError, match="stale setpoints"):
                await autopilot.prepare_offboard()
            assert px4.mode is Px4Mode.HOLD

    try:
        asyncio.run(body())
    finally:
        stale.close()
