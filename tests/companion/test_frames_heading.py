"""Frame conventions: heading from velocity, attitude from a thrust direction, angle wrapping."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from companion.frames import (
    euler_zyx_from_quat,
    quat_from_yaw,
    rotmat_from_z_axis_and_yaw,
    rotmat_to_quat,
    wrap_angle,
    yaw_from_velocity,
)

from .frame_strategies import PROPERTY, TOL, angle_diff, rot, vector

# --------------------------------------------------------------------------------------------
# Heading from velocity, attitude from thrust
# --------------------------------------------------------------------------------------------


def test_yaw_from_velocity_faces_the_velocity() -> None:
    assert float(yaw_from_velocity([1.0, 0.0, 0.0], 0.7)) == pytest.approx(0.0)
    assert float(yaw_from_velocity([0.0, 2.0, -1.0], 0.7)) == pytest.approx(math.pi / 2)
    assert float(yaw_from_velocity([-1.0, -1.0, 3.0], 0.7)) == pytest.approx(-3 * math.pi / 4)


def test_yaw_from_velocity_falls_back_when_slow() -> None:
    # Horizontal speed 0.05 < 0.1 (default): keep the fallback; vertical speed does not count.
    assert float(yaw_from_velocity([0.05, 0.0, 0.0], 0.7)) == 0.7
    assert float(yaw_from_velocity([0.0, 0.0, 5.0], -1.2)) == -1.2
    assert float(yaw_from_velocity([0.0, 0.0, 0.0], 0.3)) == 0.3
    # A custom threshold.
    assert float(yaw_from_velocity([0.5, 0.0, 0.0], 0.7, min_speed_mps=1.0)) == 0.7
    assert float(yaw_from_velocity([0.0, 1.5, 0.0], 0.7, min_speed_mps=1.0)) == pytest.approx(
        math.pi / 2
    )


def test_yaw_from_velocity_vectorized_with_per_agent_fallback() -> None:
    v = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    fallback = np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(yaw_from_velocity(v, fallback), [math.pi / 2, 0.2, math.pi])


def assert_orthonormal(r: np.ndarray, tol: float = 1e-9) -> None:
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(np.swapaxes(r, -1, -2) @ r, eye, atol=tol)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=tol)


@PROPERTY
@given(z=vector, yaw=st.floats(-10.0, 10.0))
def test_rotmat_from_z_axis_and_yaw(z: np.ndarray, yaw: float) -> None:
    assume(np.linalg.norm(z) > 1e-3)
    z_unit = z / np.linalg.norm(z)
    heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    assume(np.linalg.norm(np.cross(z_unit, heading)) > 1e-3)  # not along the heading
    r = rotmat_from_z_axis_and_yaw(z, yaw)
    assert_orthonormal(r)
    np.testing.assert_allclose(r[:, 2], z_unit, atol=1e-9)
    # Body x is the heading projected onto the plane normal to the thrust.
    proj = heading - (heading @ z_unit) * z_unit
    np.testing.assert_allclose(r[:, 0], proj / np.linalg.norm(proj), atol=1e-7)


@PROPERTY
@given(yaw=st.floats(-3.1, 3.1))
def test_vertical_thrust_gives_level_attitude_with_requested_heading(yaw: float) -> None:
    r = rotmat_from_z_axis_and_yaw([0.0, 0.0, 9.81], yaw)
    assert_orthonormal(r)
    np.testing.assert_allclose(r, rot(quat_from_yaw(yaw)), atol=1e-12)
    roll, pitch, yaw_out = euler_zyx_from_quat(rotmat_to_quat(r))
    assert abs(float(roll)) < 1e-9
    assert abs(float(pitch)) < 1e-9
    assert abs(float(angle_diff(yaw_out, yaw))) < 1e-9


def test_thrust_tilted_forward_gives_positive_pitch_nose_down() -> None:
    a = math.radians(20.0)
    r = rotmat_from_z_axis_and_yaw([math.sin(a), 0.0, math.cos(a)], 0.0)
    roll, pitch, yaw = euler_zyx_from_quat(rotmat_to_quat(r))
    assert float(pitch) == pytest.approx(a, abs=1e-9)
    assert float(roll) == pytest.approx(0.0, abs=1e-9)
    assert float(yaw) == pytest.approx(0.0, abs=1e-9)
    assert r[2, 0] < 0.0  # nose below the horizon


def test_thrust_tilted_left_rolls_the_right_side_down() -> None:
    # Thrust leaning towards +y (north = body left at yaw 0): the drone banks left,
    # i.e. its left side goes down: negative roll in FLU.
    a = math.radians(15.0)
    r = rotmat_from_z_axis_and_yaw([0.0, math.sin(a), math.cos(a)], 0.0)
    roll, pitch, _ = euler_zyx_from_quat(rotmat_to_quat(r))
    assert float(roll) == pytest.approx(-a, abs=1e-9)
    assert float(pitch) == pytest.approx(0.0, abs=1e-9)


def test_rotmat_from_z_axis_and_yaw_thrust_along_heading_is_finite() -> None:
    r = rotmat_from_z_axis_and_yaw([1.0, 0.0, 0.0], 0.0)
    assert np.all(np.isfinite(r))
    assert_orthonormal(r)
    np.testing.assert_allclose(r[:, 2], [1.0, 0.0, 0.0], atol=TOL)


def test_rotmat_from_z_axis_and_yaw_is_vectorized() -> None:
    z = np.array([[0.0, 0.0, 1.0], [0.3, -0.2, 1.0], [0.0, 0.5, 0.5]])
    yaw = np.array([0.0, 1.0, -2.0])
    r = rotmat_from_z_axis_and_yaw(z, yaw)
    assert r.shape == (3, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(r[k], rotmat_from_z_axis_and_yaw(z[k], yaw[k]), atol=1e-12)
    assert_orthonormal(r)


# --------------------------------------------------------------------------------------------
# wrap_angle
# --------------------------------------------------------------------------------------------


def test_wrap_angle_known_values() -> None:
    assert float(wrap_angle(0.0)) == 0.0
    assert float(wrap_angle(3 * math.pi / 2)) == pytest.approx(-math.pi / 2)
    assert float(wrap_angle(-3 * math.pi / 2)) == pytest.approx(math.pi / 2)
    assert float(wrap_angle(math.pi)) == pytest.approx(-math.pi)  # half-open: +pi -> -pi
    assert float(wrap_angle(7.0)) == pytest.approx(7.0 - 2 * math.pi)
    np.testing.assert_allclose(wrap_angle([0.5, 2 * math.pi + 0.5]), [0.5, 0.5])


@PROPERTY
@given(a=st.floats(-1000.0, 1000.0, allow_subnormal=False))
def test_wrap_angle_range_and_equivalence(a: float) -> None:
    w = float(wrap_angle(a))
    assert -math.pi <= w < math.pi
    turns = (a - w) / (2 * math.pi)
    assert abs(turns - round(turns)) < 1e-9


def test_wrap_angle_just_below_minus_pi_stays_half_open() -> None:
    a = float(np.nextafter(-math.pi, -10.0))
    assert float(wrap_angle(a)) < math.pi
