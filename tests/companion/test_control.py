"""Control law: frames by hand, migration, speed cap, altitude band, yaw, filter, config."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.control import (
    ControlConfig,
    ControlLaw,
    LowPassFilter,
    altitude_guard,
    compose_velocity,
    to_px4_setpoint,
    yaw_setpoint,
)
from companion.errors import ConfigError
from companion.frames import quat_from_euler_zyx, quat_from_yaw

TOL = 1e-9
Q_LEVEL = np.array([1.0, 0.0, 0.0, 0.0])
ORIGIN = np.zeros(3)


def q_yaw_deg(deg: float) -> np.ndarray:
    return quat_from_yaw(math.radians(deg))


# --- compose_velocity and to_px4_setpoint: frames by hand -------------------------------------


def test_forward_while_facing_north_flies_north_and_is_ned_x() -> None:
    # Body +x (forward), drone yawed 90 deg in ENU (nose north): world +y; NED (1, 0, 0).
    vel_world = compose_velocity([1.0, 0.0, 0.0], q_yaw_deg(90.0), ORIGIN, None, 1.0, 10.0)
    np.testing.assert_allclose(vel_world, [0.0, 1.0, 0.0], atol=TOL)
    vel_ned, yaw_ned = to_px4_setpoint(vel_world, math.pi / 2)
    np.testing.assert_allclose(vel_ned, [1.0, 0.0, 0.0], atol=TOL)
    assert yaw_ned == pytest.approx(0.0, abs=TOL)  # NED yaw 0 = north


def test_left_while_facing_east_flies_north() -> None:
    # FLU: body +y is left; facing east (yaw 0), left is north.
    vel_world = compose_velocity([0.0, 1.5, 0.0], Q_LEVEL, ORIGIN, None, 1.0, 10.0)
    np.testing.assert_allclose(vel_world, [0.0, 1.5, 0.0], atol=TOL)


def test_body_up_with_roll_90_deg_points_south() -> None:
    # Rolling +90 deg about the forward (east) axis tips the body z axis to world -y (south).
    q = quat_from_euler_zyx(math.pi / 2, 0.0, 0.0)
    vel_world = compose_velocity([0.0, 0.0, 1.0], q, ORIGIN, None, 1.0, 10.0)
    np.testing.assert_allclose(vel_world, [0.0, -1.0, 0.0], atol=TOL)
    vel_ned, _ = to_px4_setpoint(vel_world, 0.0)
    np.testing.assert_allclose(vel_ned, [-1.0, 0.0, 0.0], atol=TOL)  # south = -north


def test_enu_to_ned_setpoint_components_and_yaw() -> None:
    vel_ned, yaw_ned = to_px4_setpoint([1.0, 2.0, 3.0], 0.0)
    np.testing.assert_allclose(vel_ned, [2.0, 1.0, -3.0])
    assert yaw_ned == pytest.approx(math.pi / 2)  # ENU yaw 0 faces east = NED yaw +90 deg
    _, yaw_west = to_px4_setpoint([0.0, 0.0, 0.0], math.pi)
    assert yaw_west == pytest.approx(-math.pi / 2)  # west, wrapped into [-pi, pi)


def test_migration_term_is_added_in_world_frame() -> None:
    # Hovering policy, migration point 10 m east, k_mig = 1: 1 m/s east = NED (0, 1, 0).
    vel_world = compose_velocity(np.zeros(3), q_yaw_deg(37.0), ORIGIN, [10.0, 0.0, 0.0], 1.0, 2.0)
    np.testing.assert_allclose(vel_world, [1.0, 0.0, 0.0], atol=TOL)
    np.testing.assert_allclose(to_px4_setpoint(vel_world, 0.0)[0], [0.0, 1.0, 0.0], atol=TOL)


def test_speed_cap_after_the_sum() -> None:
    # 3 m/s forward (east) + 1 m/s migration east = 4 m/s, capped to 2 m/s along the sum.
    vel_world = compose_velocity([3.0, 0.0, 0.0], Q_LEVEL, ORIGIN, [5.0, 0.0, 0.0], 1.0, 2.0)
    np.testing.assert_allclose(vel_world, [2.0, 0.0, 0.0], atol=TOL)
    # Policy north 1 m/s + migration east 1 m/s: (1, 1) (|v| = 1.41 < 2) is not scaled.
    v2 = compose_velocity([0.0, 1.0, 0.0], Q_LEVEL, ORIGIN, [5.0, 0.0, 0.0], 1.0, 2.0)
    np.testing.assert_allclose(v2, [1.0, 1.0, 0.0], atol=TOL)


def test_vectorized_over_agents_with_nan_migration_rows() -> None:
    vel_body = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    q = np.stack([Q_LEVEL, q_yaw_deg(90.0), q_yaw_deg(180.0)])
    pos = np.array([[0.0, 0.0, 5.0], [3.0, 0.0, 5.0], [0.0, 0.0, 5.0]])
    targets = np.array([[np.nan] * 3, [np.nan] * 3, [0.0, -4.0, 5.0]])
    out = compose_velocity(vel_body, q, pos, targets, 1.0, 2.0)
    expected = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    np.testing.assert_allclose(out, expected, atol=TOL)
    for i in range(3):
        row = compose_velocity(vel_body[i], q[i], pos[i], targets[i], 1.0, 2.0)
        np.testing.assert_allclose(out[i], row, atol=TOL)


def test_common_migration_point_broadcasts_to_all_agents() -> None:
    pos = np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    out = compose_velocity(np.zeros((2, 3)), np.stack([Q_LEVEL] * 2), pos, [0.0, 5.0, 0.0], 2.0, 5)
    np.testing.assert_allclose(out, [[0.0, 2.0, 0.0], [0.0, -2.0, 0.0]], atol=TOL)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-50, 50), min_size=3, max_size=3),
    st.floats(-math.pi, math.pi),
    st.floats(-1.5, 1.5),
    st.floats(0.1, 5.0),
)
def test_composed_speed_never_exceeds_the_cap(
    vel: list[float], yaw: float, pitch: float, v_max: float
) -> None:
    q = quat_from_euler_zyx(0.3, pitch, yaw)
    out = compose_velocity(vel, q, [1.0, 2.0, 3.0], [-7.0, 4.0, 3.0], 1.0, v_max)
    assert np.all(np.isfinite(out))
    assert np.linalg.norm(out) <= v_max * (1 + 1e-12)


# --- yaw, altitude guard ---------------------------------------------------------------------


def test_yaw_faces_velocity_and_is_held_when_slow() -> None:
    assert yaw_setpoint([0.0, 1.0, 0.0], 0.0, 0.3) == pytest.approx(math.pi / 2)
    assert yaw_setpoint([-1.0, 0.0, 0.5], 0.0, 0.3) == pytest.approx(-math.pi)
    # 0.2 m/s horizontal (a fast climb does not count) is below the limit: hold 1.0 rad.
    assert yaw_setpoint([0.2, 0.0, 2.0], 1.0, 0.3) == pytest.approx(1.0)
    out = yaw_setpoint([[1.0, 1.0, 0.0], [0.0, 0.0, 0.0]], [0.0, 2.5], 0.3)
    np.testing.assert_allclose(out, [math.pi / 4, 2.5])


def test_altitude_guard_floor_and_ceiling() -> None:
    v = np.array([[0.5, 0.0, -1.0], [0.5, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    z = np.array([5.0, 1.0, 0.2, 31.0])
    out = altitude_guard(v, z, floor_m=1.0, ceiling_m=30.0, push_gain_per_s=1.0, push_max_mps=0.5)
    np.testing.assert_allclose(out[0], [0.5, 0.0, -1.0])  # inside the band: unchanged
    np.testing.assert_allclose(out[1], [0.5, 0.0, 0.0])  # at the floor: no further descent
    np.testing.assert_allclose(out[2], [0.0, 0.0, 0.5])  # 0.8 m below: pushed up, capped at 0.5
    np.testing.assert_allclose(out[3], [0.0, 0.0, -0.5])  # 1 m above the ceiling: pushed down
    # Climbing away from the floor is allowed; no limits at all with None.
    np.testing.assert_allclose(altitude_guard([0, 0, 1.2], 0.5, 1.0, None), [0, 0, 1.2])
    np.testing.assert_allclose(altitude_guard([0, 0, -3.0], -9.0, None, None), [0, 0, -3.0])


# --- low-pass filter -------------------------------------------------------------------------


def test_low_pass_step_response_matches_first_order_formula() -> None:
    lpf = LowPassFilter(cutoff_hz=1.0, dt_s=0.1)
    alpha = 0.1 / (0.1 + 1.0 / (2.0 * math.pi))
    assert lpf.alpha() == pytest.approx(alpha)
    outputs = [lpf.step([1.0, -2.0, 0.0])[0] for _ in range(5)]
    expected = [1.0 - (1.0 - alpha) ** k for k in range(1, 6)]
    np.testing.assert_allclose(outputs, expected)
    lpf.reset()
    np.testing.assert_allclose(lpf.step([1.0, 0.0, 0.0]), [alpha, 0.0, 0.0])


def test_low_pass_off_passes_through_and_keeps_per_agent_state() -> None:
    off = LowPassFilter(None, 0.1)
    np.testing.assert_allclose(off.step([3.0, 2.0, 1.0]), [3.0, 2.0, 1.0])
    lpf = LowPassFilter(2.0, 0.1)
    lpf.step(np.ones((2, 3)))
    lpf.reset_rows([True, False])
    out = lpf.step(np.ones((2, 3)))
    assert out[0, 0] < out[1, 0]
    with pytest.raises(ValueError, match="shape"):
        lpf.step(np.ones((3, 3)))


# --- ControlLaw --------------------------------------------------------------------------------


def test_control_law_reports_every_intermediate() -> None:
    law = ControlLaw(ControlConfig(migration_point_enu=(0.0, 100.0, 5.0), altitude_floor_m=None))
    out = law.step([1.0, 0.0, 0.0], q_yaw_deg(90.0), [0.0, 0.0, 5.0], math.pi / 2)
    assert out.ok and out.reason == ""
    np.testing.assert_allclose(out.vel_body_filtered_flu, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(out.vel_world_enu, [0.0, 2.0, 0.0], atol=TOL)  # 1 + 1 north
    np.testing.assert_allclose(out.vel_final_enu, [0.0, 2.0, 0.0], atol=TOL)
    np.testing.assert_allclose(out.vel_ned, [2.0, 0.0, 0.0], atol=TOL)
    assert float(out.yaw_enu_rad) == pytest.approx(math.pi / 2)
    assert float(out.yaw_ned_rad) == pytest.approx(0.0, abs=TOL)
    record = out.as_dict()
    assert record["ok"] is True and record["vel_ned"] == pytest.approx([2.0, 0.0, 0.0])


def test_control_law_applies_altitude_guard_and_filter() -> None:
    cfg = ControlConfig(low_pass_cutoff_hz=1.0, altitude_floor_m=2.0, altitude_ceiling_m=10.0)
    law = ControlLaw(cfg, nominal_dt_s=0.1)
    out = law.step([0.0, 0.0, -1.0], Q_LEVEL, [0.0, 0.0, 1.0], 0.0)
    alpha = law.filter.alpha()
    np.testing.assert_allclose(out.vel_body_filtered_flu, [0.0, 0.0, -alpha])
    np.testing.assert_allclose(out.vel_final_enu, [0.0, 0.0, 0.5])  # 1 m below floor: push up


def test_control_law_measures_the_altitude_band_from_home() -> None:
    # 5 m above the frame's origin but only 0.5 m above a home 4.5 m up: under the 1 m floor.
    law = ControlLaw(ControlConfig(altitude_floor_m=1.0, altitude_ceiling_m=30.0))
    out = law.step([0.0, 0.0, -1.0], Q_LEVEL, [0.0, 0.0, 5.0], 0.0, home_z_enu_m=4.5)
    np.testing.assert_allclose(out.vel_final_enu, [0.0, 0.0, 0.5])  # pushed up, not down
    out = law.step([0.0, 0.0, -1.0], Q_LEVEL, [0.0, 0.0, 5.0], 0.0)  # from the origin: free
    np.testing.assert_allclose(out.vel_final_enu, [0.0, 0.0, -1.0])


def test_control_law_hovers_on_nan_attitude_and_holds_yaw() -> None:
    law = ControlLaw(ControlConfig(altitude_floor_m=None))
    first = law.step([1.0, 0.0, 0.0], q_yaw_deg(90.0), ORIGIN, math.pi / 2)
    assert first.ok
    bad = law.step([1.0, 0.0, 0.0], [np.nan] * 4, ORIGIN, math.pi / 2)
    assert not bad.ok and "attitude" in bad.reason
    np.testing.assert_allclose(bad.vel_final_enu, 0.0)
    np.testing.assert_allclose(bad.vel_ned, 0.0)
    # Slow command: yaw held at the last setpoint (north), not the measured 0.3 rad.
    slow = law.step([0.0, 0.0, 0.0], Q_LEVEL, ORIGIN, 0.3)
    assert slow.ok
    assert float(slow.yaw_enu_rad) == pytest.approx(0.3)  # held yaw was lost to the bad tick
    slow2 = law.step([0.05, 0.0, 0.0], Q_LEVEL, ORIGIN, 1.2)
    assert float(slow2.yaw_enu_rad) == pytest.approx(0.3)


def test_control_law_batched_rows_are_independent() -> None:
    law = ControlLaw(ControlConfig(altitude_floor_m=None), nominal_dt_s=0.1)
    v = np.array([[1.0, 0.0, 0.0], [np.inf, 0.0, 0.0]])
    q = np.stack([Q_LEVEL, Q_LEVEL])
    out = law.step(v, q, np.zeros((2, 3)), np.zeros(2))
    np.testing.assert_array_equal(out.valid, [True, False])
    np.testing.assert_allclose(out.vel_final_enu, [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert "velocity" in out.reason


def test_hover_is_immediate_and_resets_the_filter() -> None:
    law = ControlLaw(ControlConfig(low_pass_cutoff_hz=0.5), nominal_dt_s=0.1)
    law.step([2.0, 0.0, 0.0], Q_LEVEL, [0.0, 0.0, 5.0], 0.0)
    out = law.hover(0.7, "images stale")
    assert not out.ok and out.reason == "images stale"
    np.testing.assert_allclose(out.vel_ned, 0.0)
    # The heading the vehicle has at the switch (0.7), not the last commanded one (0): PX4 SITL
    # turned the vehicle by 8 deg at the switch when the hover held the commanded heading.
    assert float(out.yaw_enu_rad) == pytest.approx(0.7)
    still = law.hover(0.75, "images stale")  # the vehicle drifts: the hover keeps its heading
    assert float(still.yaw_enu_rad) == pytest.approx(0.7)
    after = law.step([1.0, 0.0, 0.0], Q_LEVEL, [0.0, 0.0, 5.0], 0.0)
    np.testing.assert_allclose(after.vel_body_filtered_flu, [law.filter.alpha(), 0.0, 0.0])


# --- config --------------------------------------------------------------------------------------


def test_config_defaults_are_the_papers() -> None:
    cfg = ControlConfig()
    assert (cfg.k_mig, cfg.v_max_mps, cfg.migration_point_enu) == (1.0, 2.0, None)
    assert cfg.low_pass_cutoff_hz is None


def test_config_from_dict_converts_and_refuses_unknown_keys() -> None:
    cfg = ControlConfig.from_dict({"migration_point_enu": [30, 0, 5], "v_max_mps": 4})
    assert cfg.migration_point_enu == (30.0, 0.0, 5.0) and cfg.v_max_mps == 4
    with pytest.raises(ConfigError, match=r"unknown key\(s\) 'vmax'"):
        ControlConfig.from_dict({"vmax": 3})
    with pytest.raises(ConfigError, match="control.v_max_mps.*allowed range"):
        ControlConfig.from_dict({"v_max_mps": 0})
    with pytest.raises(ConfigError, match="control.migration_point_enu"):
        ControlConfig.from_dict({"migration_point_enu": [1, 2]})
    with pytest.raises(ConfigError, match="control.altitude_ceiling_m.*above"):
        ControlConfig(altitude_floor_m=5.0, altitude_ceiling_m=5.0)
    with pytest.raises(ConfigError, match="control.low_pass_cutoff_hz"):
        ControlConfig(low_pass_cutoff_hz=-1.0)
    with pytest.raises(ConfigError, match="control: expected a table"):
        ControlConfig.from_dict([1, 2])  # type: ignore[arg-type]
