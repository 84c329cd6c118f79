"""The daemon in PX4's frames, end to end (pty cameras, the PX4 emulator over MAVSDK): a global
migration point converted with PX4's home, and the altitude floor kept above that home when the
EKF's origin is elsewhere."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.daemon import Daemon
from companion.flight_log import TOPIC_HEALTH, LogReader
from sim_harness.hil import px4_messages as msgs
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.px4_logic import Px4Mode

from .daemon_rig import (
    GUARD_S,
    daemon_log,
    document,
    free_tcp_port,
    hovering_east,
    is_zero,
    last_setpoint,
    until,
)


@pytest.fixture
def px4() -> Iterator[AutopilotEmulator]:
    """PX4 armed and hovering at 5 m in POSCTL, facing east; heartbeats at 20 Hz."""
    with hovering_east() as emulator:
        yield emulator


def test_a_global_migration_point_is_converted_with_px4s_home(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    """`migration_point_global` 100 m north of PX4's home at the hover altitude: the daemon adds
    a northward migration of k_mig = 1 m/s to the policy's eastward command, once PX4 has sent
    its home, and logs the converted point."""
    home = px4.config.home
    north_deg = math.degrees(100.0 / 6_378_137.0)
    doc = document(
        tmp_path, cameras, px4, make_policy_file("constant", (1.0, 0.0, 0.0)), free_tcp_port()
    )
    doc["control"] = {"migration_point_global": [home.lat_deg + north_deg, home.lon_deg, 493.0]}
    daemon = Daemon(config_from_dict(doc), handle_signals=False)

    def migrating(setpoint: Any) -> bool:  # NED: north 1 (migration), east 1 (policy)
        return abs(setpoint.vx_mps - 1.0) < 0.1 and abs(setpoint.vy_mps - 1.0) < 0.1

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "OFFBOARD")
            await until(
                lambda: bool(px4.setpoints()) and migrating(last_setpoint(px4)),
                GUARD_S,
                "the policy's command plus the migration towards the global point",
            )
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    asyncio.run(body())
    events = [
        m.json() for m in LogReader(daemon_log(tmp_path)).messages() if m.topic == TOPIC_HEALTH
    ]
    (converted,) = [e for e in events if e.get("event") == "migration point"]
    np.testing.assert_allclose(converted["detail"]["migration_point_enu"], [0, 100, 5], atol=0.01)


def test_the_altitude_floor_is_kept_above_px4s_home(
    tmp_path: Path, cameras: CameraEmulator, make_policy_file: Any
) -> None:
    """PX4's EKF origin need not be at its home (real PX4 starts it where its first estimate
    was). Here home is 4.5 m above the origin and the vehicle hovers 5 m above the origin: 0.5 m
    above home, under the 1 m floor. A policy asking to descend at 0.5 m/s is never flown down;
    the daemon pushes the vehicle up instead (at 1 m/s per metre under the floor)."""
    home = msgs.Home(47.397742, 8.545594, 488.0, local_ned_m=(0.0, 0.0, -4.5))
    with hovering_east(home=home) as px4:
        doc = document(
            tmp_path, cameras, px4, make_policy_file("constant", (0.0, 0.0, -0.5)), free_tcp_port()
        )
        daemon = Daemon(config_from_dict(doc), handle_signals=False)

        def flown() -> list[Any]:
            return [s for s in px4.setpoints() if not is_zero(s)]

        async def body() -> None:
            run = asyncio.create_task(daemon.run())
            try:
                await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "OFFBOARD")
                await until(lambda: len(flown()) >= 20, GUARD_S, "20 setpoints flown")
            finally:
                daemon.request_stop("test over")
                await asyncio.wait_for(run, 15.0)

        asyncio.run(body())
        ups = [-s.vz_mps for s in flown()]  # NED down -> up
    assert min(ups) > -0.05, "a descent below the floor above home was flown"
    assert max(ups) > 0.3  # pushed up: 0.5 m under the floor, 0.5 m/s
