"""The vehicle model tracks velocity setpoints like PX4 and tilts by the acceleration it makes."""

import math

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.frames import euler_zyx_from_quat, quat_to_rotmat
from sim_harness.sim.vehicle import GRAVITY_MPS2, VehicleModel, VehicleParams

DT = 0.01


def fly_for(model: VehicleModel, setpoint, seconds: float) -> None:
    sp = np.broadcast_to(np.asarray(setpoint, dtype=float), model.state.pos_world_enu.shape)
    for _ in range(round(seconds / DT)):
        model.step(sp, DT)


def test_tracks_a_horizontal_velocity_setpoint() -> None:
    model = VehicleModel(VehicleParams(), [[0.0, 0.0, 5.0]])
    fly_for(model, [2.0, 0.0, 0.0], 15.0)
    np.testing.assert_allclose(model.state.vel_world_enu[0], [2.0, 0.0, 0.0], atol=0.05)
    assert model.state.pos_world_enu[0, 2] == pytest.approx(5.0, abs=0.05)


def test_tracks_climb_and_caps_it_at_the_px4_limit() -> None:
    params = VehicleParams()
    model = VehicleModel(params, [[0.0, 0.0, 5.0]])
    fly_for(model, [0.0, 0.0, 10.0], 10.0)
    assert model.state.vel_world_enu[0, 2] == pytest.approx(params.vel_up_max_mps, abs=0.05)


def test_acceleration_and_tilt_stay_within_limits() -> None:
    params = VehicleParams()
    model = VehicleModel(params, [[0.0, 0.0, 5.0]])
    max_tilt = 0.0
    for _ in range(300):
        model.step([[12.0, 0.0, 0.0]], DT)
        acc = model.state.acc_world_enu[0]
        assert np.hypot(acc[0], acc[1]) <= params.acc_xy_max_mps2 + 1e-9
        body_z = quat_to_rotmat(model.q_world_body[0])[:, 2]
        max_tilt = max(max_tilt, math.degrees(math.acos(np.clip(body_z[2], -1, 1))))
    assert max_tilt <= params.tilt_max_deg
    # A hard acceleration really does tilt the body (5 m/s^2 forward is about 27 deg).
    assert max_tilt > 20.0


def test_body_tilts_towards_the_acceleration() -> None:
    model = VehicleModel(VehicleParams(), [[0.0, 0.0, 5.0]], initial_yaw_rad=0.0)
    fly_for(model, [2.0, 0.0, 0.0], 0.3)  # accelerating east, heading east
    roll, pitch, _ = euler_zyx_from_quat(model.q_world_body[0])
    assert pitch > math.radians(5)  # FLU: positive pitch = nose down
    assert abs(roll) < 1e-6
    body_z = quat_to_rotmat(model.q_world_body[0])[:, 2]
    thrust = model.state.acc_world_enu[0] + [0.0, 0.0, GRAVITY_MPS2]
    np.testing.assert_allclose(body_z, thrust / np.linalg.norm(thrust), atol=1e-9)


def test_heading_turns_towards_velocity_at_the_yaw_rate_limit() -> None:
    params = VehicleParams()
    model = VehicleModel(params, [[0.0, 0.0, 5.0]], initial_yaw_rad=0.0)
    fly_for(model, [0.0, 1.0, 0.0], 1.0)  # north: a 90 deg turn at 45 deg/s takes 2 s
    assert math.degrees(model.state.yaw_rad[0]) == pytest.approx(params.yaw_rate_max_deg_s, abs=1)
    fly_for(model, [0.0, 1.0, 0.0], 2.0)
    assert math.degrees(model.state.yaw_rad[0]) == pytest.approx(90.0, abs=1e-6)
    _, _, yaw = euler_zyx_from_quat(model.q_world_body[0])
    assert math.degrees(yaw) == pytest.approx(90.0, abs=0.5)


def test_heading_is_held_when_the_setpoint_is_slow() -> None:
    model = VehicleModel(VehicleParams(), [[0.0, 0.0, 5.0]], initial_yaw_rad=1.0)
    fly_for(model, [0.0, -0.05, 0.0], 2.0)
    assert model.state.yaw_rad[0] == pytest.approx(1.0)


def test_a_yaw_setpoint_overrides_the_heading_rule_and_nan_falls_back_to_it() -> None:
    """As PX4 tracks an offboard yaw: drone 0 flies east facing north; drone 1 has no yaw."""
    params = VehicleParams()
    model = VehicleModel(params, [[0.0, 0.0, 5.0], [5.0, 0.0, 5.0]], initial_yaw_rad=0.0)
    for _ in range(round(3.0 / DT)):
        model.step([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], DT, [math.pi / 2, math.nan])
    assert model.state.yaw_rad == pytest.approx([math.pi / 2, math.pi / 2], abs=1e-6)
    assert model.state.vel_world_enu[0, 0] == pytest.approx(1.0, abs=0.05)


def test_ground_stops_descent() -> None:
    params = VehicleParams()
    model = VehicleModel(params, [[0.0, 0.0, 1.0]])
    fly_for(model, [0.0, 0.0, -1.5], 5.0)
    assert model.state.pos_world_enu[0, 2] == pytest.approx(params.ground_clearance_m)
    assert model.state.vel_world_enu[0, 2] >= 0.0


def test_vehicles_are_independent() -> None:
    model = VehicleModel(VehicleParams(), [[0.0, 0.0, 5.0], [10.0, 0.0, 5.0]])
    fly_for(model, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], 5.0)
    assert model.state.vel_world_enu[0, 0] > 0.9
    np.testing.assert_allclose(model.state.pos_world_enu[1], [10.0, 0.0, 5.0], atol=1e-9)


def test_rejects_bad_setpoints_and_params() -> None:
    model = VehicleModel(VehicleParams(), [[0.0, 0.0, 5.0]])
    with pytest.raises(ValueError, match="finite"):
        model.step([[np.nan, 0.0, 0.0]], DT)
    with pytest.raises(ValueError, match="shape"):
        model.step([[1.0, 0.0]], DT)
    with pytest.raises(ConfigError, match="vehicle.tilt_max_deg"):
        VehicleParams(tilt_max_deg=95.0)
    with pytest.raises(ConfigError, match="vehicle.vel_p_xy"):
        VehicleParams(vel_p_xy=-1.0)
