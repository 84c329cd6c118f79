"""The MAVSDK adapter against the PX4 emulator, over real MAVLink on loopback UDP."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Coroutine, Iterator
from typing import Any

import mavsdk
import numpy as np
import pytest

from companion.autopilot import (
    AutopilotConfig,
    FlightMode,
    MavsdkAutopilot,
    OffboardState,
    forward_mavsdk_logs,
)
from companion.errors import AutopilotError, ConfigError, OffboardLostError
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
from sim_harness.hil.px4_logic import Px4LogicConfig, Px4Mode

DO_SET_MODE = 176
HEARTBEAT_HZ = 20.0  # PX4 sends 1 Hz; faster here so mode changes show up quickly
# Offboard loss to Hold, as with the shipped parameter file (PX4's default is Position mode).
FAST_PX4 = Px4LogicConfig(
    takeoff_altitude_m=2.0,
    takeoff_speed_mps=4.0,
    land_speed_mps=3.0,
    offboard_loss_mode=Px4Mode.HOLD,
)

Sim = Callable[..., tuple[AutopilotEmulator, AutopilotConfig]]


@pytest.fixture
def sim() -> Iterator[Sim]:
    """Makes an emulator on a free port and an adapter config pointing at it."""
    emulators: list[AutopilotEmulator] = []

    def make(
        hovering: bool = False, altitude_m: float = 5.0, adapter: dict[str, Any] | None = None
    ) -> tuple[AutopilotEmulator, AutopilotConfig]:
        port = free_udp_port()
        kwargs: dict[str, Any] = {"heartbeat_rate_hz": HEARTBEAT_HZ, "px4": FAST_PX4}
        if hovering:
            emulator_config = EmulatorConfig.hovering(port, altitude_m, **kwargs)
        else:
            emulator_config = EmulatorConfig(port, **kwargs)
        emulators.append(AutopilotEmulator(emulator_config).start())
        config = AutopilotConfig(
            url=f"udpin://127.0.0.1:{port}",
            discovery_timeout_s=5.0,
            health_timeout_s=5.0,
            offboard_prestream_s=0.05,
            **(adapter or {}),
        )
        return emulators[-1], config

    yield make
    for emulator in emulators:
        emulator.stop()


def run(coro: Coroutine[Any, Any, None]) -> None:
    """Run one test body; `asyncio.run` returning at all shows nothing was left hanging."""
    asyncio.run(coro)


async def until(condition: Callable[[], bool], timeout_s: float = 15.0) -> None:
    """Wait for `condition` (a hang guard, not a timing check: generous for a loaded machine;
    it returns as soon as the condition holds)."""
    async with asyncio.timeout(timeout_s):
        while not condition():
            await asyncio.sleep(0.02)


def mode_of(autopilot: MavsdkAutopilot) -> FlightMode | None:
    mode = autopilot.telemetry().flight_mode
    return None if mode is None else mode.value


# -- configuration ----------------------------------------------------------------------------


def test_config_defaults_and_from_dict() -> None:
    config = AutopilotConfig.from_dict({"url": "serial:///dev/ttyS1:921600", "arm": True})
    assert config.url == "serial:///dev/ttyS1:921600" and config.arm
    assert AutopilotConfig().url == "udpin://127.0.0.1:14540"
    assert AutopilotConfig().command_timeout_s == 2.0
    with pytest.raises(ConfigError, match="unknown key.*'speed'"):
        AutopilotConfig.from_dict({"speed": 3})


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"setpoint_rate_hz": 5.0}, r"autopilot\.setpoint_rate_hz: 5 is outside .*\[10, 100\]"),
        ({"command_timeout_s": 0.0}, r"autopilot\.command_timeout_s"),
        ({"failsafe_action": "rtl"}, r"autopilot\.failsafe_action: 'rtl' must be one of hold"),
        ({"url": "http://x"}, r"autopilot\.url"),
        ({"takeoff": True}, r"autopilot\.takeoff: needs autopilot\.arm"),
        ({"arm": 1}, r"autopilot\.arm"),
    ],
)
def test_config_errors_name_the_field(fields: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        AutopilotConfig.from_dict(fields)


# -- connection and telemetry -------------------------------------------------------------------


def test_connect_fills_telemetry_stamped_with_the_injected_clock(sim: Sim) -> None:
    emulator, config = sim(hovering=True, altitude_m=5.0)

    def clock() -> float:
        return time.monotonic() + 1000.0

    async def body() -> None:
        async with MavsdkAutopilot(config, clock=clock) as autopilot:
            telemetry = autopilot.telemetry
            await until(lambda: None not in vars(telemetry()).values())
            tel = telemetry()
            assert tel.position_ned_m is not None and tel.q_ned_frd_wxyz is not None
            np.testing.assert_allclose(tel.position_ned_m.value, [0.0, 0.0, -5.0], atol=0.05)
            np.testing.assert_allclose(tel.q_ned_frd_wxyz.value, [1.0, 0.0, 0.0, 0.0], atol=1e-3)
            assert mode_of(autopilot) is FlightMode.POSCTL
            assert tel.armed is not None and tel.armed.value
            assert tel.in_air is not None and tel.in_air.value
            assert all(slot.t_s > 1000.0 for slot in vars(tel).values())
            assert autopilot.offboard_state is OffboardState.INACTIVE
            await autopilot.takeoff()  # already flying: nothing to do

    run(body())
    assert emulator.mode is Px4Mode.POSCTL  # connecting changed nothing
    # Only REQUEST_MESSAGE / SET_MESSAGE_INTERVAL: no takeoff, no arming, no mode change.
    assert {c.command for c in emulator.commands()} <= {511, 512}


def test_no_autopilot_fails_discovery_with_a_clear_error() -> None:
    config = AutopilotConfig(url=f"udpin://127.0.0.1:{free_udp_port()}", discovery_timeout_s=0.3)

    async def body() -> None:
        autopilot = MavsdkAutopilot(config)
        with pytest.raises(AutopilotError, match="no autopilot on udpin://127.0.0.1"):
            await autopilot.connect()
        await autopilot.close()  # already released: a no-op

    run(body())


# -- offboard ---------------------------------------------------------------------------------


def test_arm_takeoff_offboard_velocity_and_stop(sim: Sim) -> None:
    emulator, config = sim(adapter={"arm": True, "takeoff": True})

    async def body() -> None:
        async with MavsdkAutopilot(config) as autopilot:
            assert emulator.armed and emulator.mode is Px4Mode.HOLD
            assert emulator.vehicle_state().altitude_m == pytest.approx(2.0, abs=0.3)
            with pytest.raises(AutopilotError, match="start_offboard"):
                await autopilot.set_velocity_ned([1.0, 0.0, 0.0], 0.0)

            await autopilot.start_offboard()
            assert emulator.mode is Px4Mode.OFFBOARD
            assert autopilot.offboard_state is OffboardState.ACTIVE
            for _ in range(20):  # 2 s at the daemon's 10 Hz
                await autopilot.set_velocity_ned(np.array([1.0, 0.5, -0.2]), math.radians(90.0))
                await asyncio.sleep(0.1)

            last = emulator.setpoints()[-1]
            assert last.frame == 1  # MAV_FRAME_LOCAL_NED
            assert last.uses_velocity and last.uses_yaw and not last.uses_yaw_rate
            np.testing.assert_allclose([last.vx_mps, last.vy_mps, last.vz_mps], [1.0, 0.5, -0.2])
            assert last.yaw_rad == pytest.approx(math.pi / 2)
            state = emulator.vehicle_state()
            np.testing.assert_allclose(state.vel_ned_mps, [1.0, 0.5, -0.2], atol=0.05)
            assert state.yaw_ned_rad == pytest.approx(math.pi / 2, abs=0.02)
            assert state.pos_ned_m[0] > 1.0 and state.pos_ned_m[1] > 0.5
            velocity = autopilot.telemetry().velocity_ned_mps
            assert velocity is not None
            np.testing.assert_allclose(velocity.value, [1.0, 0.5, -0.2], atol=0.05)

            await autopilot.stop_offboard()
            assert emulator.mode is Px4Mode.HOLD
            assert autopilot.offboard_state is OffboardState.INACTIVE
            await until(lambda: mode_of(autopilot) is FlightMode.HOLD)
            assert autopilot.offboard_state is OffboardState.INACTIVE  # our own switch: no loss

    run(body())


def test_pilot_switch_is_detected_and_commanding_stops(sim: Sim) -> None:
    emulator, config = sim(hovering=True)

    async def body() -> None:
        async with MavsdkAutopilot(config) as autopilot:
            await autopilot.start_offboard()
            await autopilot.set_velocity_ned([0.5, 0.0, 0.0], 0.0)
            assert emulator.pilot_switch_mode(Px4Mode.POSCTL).name == "ACCEPTED"
            await until(lambda: autopilot.offboard_state is OffboardState.LOST)
            assert "POSCTL" in (autopilot.offboard_lost_reason or "")
            with pytest.raises(OffboardLostError, match="POSCTL"):
                await autopilot.set_velocity_ned([0.5, 0.0, 0.0], 0.0)
            mode_commands = sum(c.command == DO_SET_MODE for c in emulator.commands())
            await autopilot.stop_offboard()  # the pilot has control: no mode change
            assert autopilot.offboard_state is OffboardState.INACTIVE
            assert sum(c.command == DO_SET_MODE for c in emulator.commands()) == mode_commands
            assert emulator.mode is Px4Mode.POSCTL
            await autopilot.hold()
            assert emulator.mode is Px4Mode.HOLD

    run(body())


def test_a_link_pause_holds_and_the_returning_stream_resumes_offboard(sim: Sim) -> None:
    """PX4 (SITL) does this: Hold after COM_OF_LOSS_T, and OFFBOARD again, with no request, as
    soon as MAVSDK's re-sent setpoints get through; the adapter need not notice either."""
    emulator, config = sim(hovering=True)

    async def body() -> None:
        async with MavsdkAutopilot(config) as autopilot:
            await autopilot.start_offboard()
            requests = sum(c.command == DO_SET_MODE for c in emulator.commands())
            emulator.set_link_alive(False)  # MAVSDK's 20 Hz stream no longer arrives
            await until(lambda: emulator.mode is Px4Mode.HOLD)
            assert emulator.mode_changes()[-1].reason == "offboard setpoints lost"
            emulator.set_link_alive(True)
            await until(lambda: emulator.mode is Px4Mode.OFFBOARD)
            assert emulator.mode_changes()[-1].reason == "offboard setpoints regained"
            assert sum(c.command == DO_SET_MODE for c in emulator.commands()) == requests

    run(body())


def test_failsafe_land_lands_and_disarms(sim: Sim) -> None:
    emulator, config = sim(hovering=True, altitude_m=1.0, adapter={"failsafe_action": "land"})

    async def body() -> None:
        async with MavsdkAutopilot(config) as autopilot:
            await autopilot.start_offboard()
            await autopilot.failsafe()
            assert emulator.mode is Px4Mode.LAND
            await until(lambda: not emulator.armed)
            assert emulator.vehicle_state().altitude_m == 0.0
            await until(lambda: mode_of(autopilot) is FlightMode.LAND)
            assert autopilot.offboard_state is OffboardState.INACTIVE  # not mistaken for a loss
            await until(lambda: (a := autopilot.telemetry().armed) is not None and not a.value)

    run(body())


def test_setpoints_are_validated(sim: Sim) -> None:
    _, config = sim(hovering=True)

    async def body() -> None:
        async with MavsdkAutopilot(config) as autopilot:
            await autopilot.start_offboard()
            for vel, yaw in (([math.nan, 0, 0], 0.0), ([1.0, 0.0], 0.0), ([0, 0, 0], math.inf)):
                with pytest.raises(AutopilotError, match="finite"):
                    await autopilot.set_velocity_ned(vel, yaw)

    run(body())


# -- shutting down ------------------------------------------------------------------------------


def test_close_while_commanding_runs_the_failsafe(sim: Sim) -> None:
    emulator, config = sim(hovering=True)

    async def body() -> None:
        autopilot = MavsdkAutopilot(config)
        await autopilot.connect()
        await autopilot.start_offboard()
        await asyncio.wait_for(autopilot.close(), timeout=10.0)

    run(body())
    assert emulator.mode is Px4Mode.HOLD
    assert emulator.mode_changes()[-1].reason == "DO_SET_MODE"


@pytest.mark.parametrize("command_in_flight", [False, True])
def test_close_returns_when_the_emulator_is_gone(
    sim: Sim, caplog: pytest.LogCaptureFixture, command_in_flight: bool
) -> None:
    emulator, config = sim(hovering=True)

    async def body() -> None:
        autopilot = MavsdkAutopilot(config)
        await autopilot.connect()
        await autopilot.start_offboard()
        emulator.stop()  # link lost for good: the failsafe on close times out
        stuck = asyncio.ensure_future(autopilot.land()) if command_in_flight else None
        await asyncio.sleep(0.05)
        await asyncio.wait_for(autopilot.close(), timeout=10.0)
        if stuck is not None:
            with pytest.raises(AutopilotError):
                await stuck

    with caplog.at_level(logging.WARNING, logger="companion.autopilot"):
        run(body())
    # Every MAVSDK call had ended by itself, so MAVSDK was destroyed, not leaked.
    assert not any("still in flight" in r.getMessage() for r in caplog.records)


def test_mavsdk_log_lines_go_to_python_logging(sim: Sim, caplog: pytest.LogCaptureFixture) -> None:
    _, config = sim()
    forward_mavsdk_logs(logging.getLogger("test.mavsdk"))

    async def body() -> None:
        async with MavsdkAutopilot(config):
            pass

    try:
        with caplog.at_level(logging.DEBUG, logger="test.mavsdk"):
            run(body())
    finally:
        mavsdk.log_unsubscribe()
    assert any("MAVSDK version" in r.getMessage() for r in caplog.records)


# -- battery and GPS ------------------------------------------------------------------------------


def test_battery_and_gps_fix_arrive_stamped_in_px4_units(sim: Sim) -> None:
    """SYS_STATUS (80 %, 16.2 V) and GPS_RAW_INT (3-D fix, 12 satellites) from the emulator,
    through MAVSDK: the percentage stays a percentage (MAVSDK 4 reports 0..100, not 0..1)."""
    from companion.autopilot_types import GpsFixType
    from companion.daemon_reports import power_and_gps_payload
    from sim_harness.hil import px4_messages

    _, config = sim(hovering=True)

    def clock() -> float:
        return time.monotonic() + 1000.0

    async def body() -> None:
        async with MavsdkAutopilot(config, clock=clock) as autopilot:
            await until(lambda: autopilot.telemetry().battery is not None)
            await until(lambda: autopilot.telemetry().gps is not None)
            tel = autopilot.telemetry()
            assert tel.battery is not None and tel.gps is not None
            assert tel.battery.value.remaining_pct == pytest.approx(80.0)
            assert tel.battery.value.voltage_v == pytest.approx(16.2, abs=1e-3)
            assert tel.gps.value.fix_type is GpsFixType.FIX_3D
            assert tel.gps.value.satellites == px4_messages.GPS_SATELLITES == 12
            assert tel.battery.t_s > 1000.0 and tel.gps.t_s > 1000.0
            payload = power_and_gps_payload(tel, clock())
            assert payload["battery"] == {"remaining_pct": 80.0, "voltage_v": 16.2}
            assert payload["gps"] == {"fix_type": "fix_3d", "satellites": 12}
            assert 0.0 <= payload["battery_age_s"] < 15.0

    run(body())


def test_battery_and_gps_not_reported_yet_are_null() -> None:
    from companion.autopilot_types import AutopilotTelemetry
    from companion.daemon_reports import power_and_gps_payload

    assert power_and_gps_payload(AutopilotTelemetry(), 5.0) == {
        "battery": {"remaining_pct": None, "voltage_v": None},
        "battery_age_s": None,
        "gps": {"fix_type": None, "satellites": None},
        "gps_age_s": None,
    }
