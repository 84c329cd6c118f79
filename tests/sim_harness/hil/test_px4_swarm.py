"""The real-PX4 HIL harness's frames, without PX4: the goal handed to each daemon as a global
point comes back, through the daemon's own conversion with its PX4's home, as the scenario's goal
in that drone's local frame; PX4's pose reported on the GCS link lands at the right world point
(its height above home, not above the estimator's origin)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from companion.frames import quat_enu_flu_to_ned_frd, quat_from_yaw
from companion.geo import GlobalPosition, HomePosition, global_to_local_enu
from companion.param_check import BOARD_ONLY
from sim_harness.hil.px4_drone import shipped_params
from sim_harness.hil.px4_gcs import PositionSample
from sim_harness.hil.px4_pose_station import TruthSample
from sim_harness.hil.px4_swarm import Px4Swarm
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN, home_of
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario


def swarm(tmp_path: Path, n: int = 3) -> Px4Swarm:
    scenario = build_scenario(ScenarioConfig(name="common", n_agents=n, seed=1011))
    return Px4Swarm(scenario, SHIPPED_MODEL_PATH, tmp_path)


def test_the_global_goal_is_each_drones_local_goal(tmp_path: Path) -> None:
    hil = swarm(tmp_path)
    for spec, setup in zip(hil._instances(), hil.setups, strict=True):
        home = HomePosition(GlobalPosition(spec.home_lat_deg, spec.home_lon_deg, spec.home_alt_m))
        point = hil._migration_global(setup.index)
        assert point is not None
        local = global_to_local_enu(GlobalPosition(*point), home)
        expected = hil.scenario.migration_points[setup.index] - setup.home_world_enu
        np.testing.assert_allclose(local, expected, atol=1e-3)
        assert spec.home_alt_m == DEFAULT_ORIGIN.alt_amsl_m  # SIH starts on the ground


def test_px4s_local_pose_is_placed_from_its_start_point(tmp_path: Path) -> None:
    hil = swarm(tmp_path, n=2)
    q_ned = quat_enu_flu_to_ned_frd(quat_from_yaw(0.3))
    for _ in range(2):
        gcs = SimpleNamespace(
            position=lambda: PositionSample(1.0, 2.0, -1.0, -5.0, 0.5, 0.0, -0.1),  # N, E, D
            attitude=(1.0, q_ned),
            truth=None,
            height_above_home_m=None,  # no GLOBAL_POSITION_INT yet
        )
        hil.drones.append(SimpleNamespace(gcs=gcs))  # type: ignore[arg-type]
    pos, vel, q = hil._poses(now=1.01)
    for i in range(2):
        np.testing.assert_allclose(pos[i], hil.homes[i] + [-1.0, 2.0, 5.0])
        np.testing.assert_allclose(vel[i], [0.0, 0.5, 0.1])
        np.testing.assert_allclose(q[i], quat_from_yaw(0.3), atol=1e-12)
    assert max(hil.pose_gap_max_s) <= 0.011


def test_px4s_estimate_is_placed_at_its_height_above_home_not_above_its_origin(
    tmp_path: Path,
) -> None:
    # Seen on a loaded machine: PX4's local frame started 0.74 m above the ground, so a drone
    # 4.59 m above home reported a local z of -3.85 m. The world must draw it at 4.59 m.
    hil = swarm(tmp_path, n=1)
    gcs = SimpleNamespace(
        position=lambda: PositionSample(1.0, 2.0, -1.0, -3.85, 0.0, 0.0, 0.0),
        attitude=None,
        truth=None,
        height_above_home_m=4.59,
    )
    hil.drones.append(SimpleNamespace(gcs=gcs))  # type: ignore[arg-type]
    pos, _, _ = hil._poses(now=1.01)
    np.testing.assert_allclose(pos[0], hil.homes[0] + [-1.0, 2.0, 4.59])


def test_the_shipped_parameters_go_to_px4_without_board_only_names() -> None:
    params = shipped_params()
    assert params and not set(params) & set(BOARD_ONLY)
    assert params["COM_OBL_RC_ACT"] == 5  # Hold on offboard loss, as the shipped file says


def test_sihs_vehicle_is_placed_where_it_is_and_the_estimate_error_kept(tmp_path: Path) -> None:
    hil = swarm(tmp_path, n=1)
    where = home_of(DEFAULT_ORIGIN, np.array([3.0, -2.0, 4.0]))
    q_ned = quat_enu_flu_to_ned_frd(quat_from_yaw(-0.5))
    truth = TruthSample(
        2.0,
        GlobalPosition(where.lat_deg, where.lon_deg, where.alt_amsl_m),
        np.array([1.0, 0.0, -0.5]),
        q_ned,
    )
    estimate = PositionSample(2.0, 0.0, 0.0, -3.0, 0.0, 0.0, 0.0)  # 3 m up at the start point
    gcs = SimpleNamespace(
        position=lambda: estimate, attitude=None, truth=truth, height_above_home_m=3.0
    )
    hil.drones.append(SimpleNamespace(gcs=gcs))  # type: ignore[arg-type]
    pos, vel, q = hil._poses(now=2.0)
    np.testing.assert_allclose(pos[0], [3.0, -2.0, 4.0], atol=0.01)
    np.testing.assert_allclose(vel[0], [0.0, 1.0, 0.5])
    np.testing.assert_allclose(q[0], quat_from_yaw(-0.5), atol=1e-12)
    start = hil.homes[0]
    assert hil.estimate_error_max_m[0] == pytest.approx(
        np.hypot(3.0 - start[0], -2.0 - start[1]), abs=0.01
    )
