"""Frame conventions: quaternions, rotations, ENU/NED and FLU/FRD, yaw helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.frames import (
    R_FLU_FRD,
    R_NED_ENU,
    body_to_world,
    enu_to_ned,
    euler_zyx_from_quat,
    flu_to_frd,
    frd_to_flu,
    ned_to_enu,
    quat_conjugate,
    quat_enu_flu_to_ned_frd,
    quat_from_euler_zyx,
    quat_from_yaw,
    quat_multiply,
    quat_ned_frd_to_enu_flu,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
    world_to_body,
    yaw_enu_to_ned,
    yaw_ned_to_enu,
)

from .frame_strategies import (
    PROPERTY,
    TOL,
    angle_diff,
    quaternion_batches,
    quaternions,
    rot,
    same_rotation_quat,
    vector,
)

# --------------------------------------------------------------------------------------------
# Quaternions and rotation matrices
# --------------------------------------------------------------------------------------------


@PROPERTY
@given(q=quaternion_batches())
def test_rotation_matrix_is_orthonormal_and_proper(q: np.ndarray) -> None:
    r = quat_to_rotmat(q)
    assert r.shape == (q.shape[0], 3, 3)
    eye = np.broadcast_to(np.eye(3), r.shape)
    np.testing.assert_allclose(r @ np.swapaxes(r, -1, -2), eye, atol=TOL)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=TOL)


@PROPERTY
@given(q=quaternion_batches())
def test_quat_rotmat_round_trip(q: np.ndarray) -> None:
    back = rotmat_to_quat(quat_to_rotmat(q))
    assert back.shape == q.shape
    assert np.all(back[..., 0] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(back, axis=-1), 1.0, atol=TOL)
    for a, b in zip(back, q, strict=True):
        assert same_rotation_quat(a, b)
    # And the matrix survives the other way round.
    np.testing.assert_allclose(quat_to_rotmat(back), quat_to_rotmat(q), atol=TOL)


@PROPERTY
@given(q=quaternions())
def test_quat_normalize_gives_unit_norm_and_non_negative_scalar(q: np.ndarray) -> None:
    n = quat_normalize(3.7 * q)
    assert n[0] >= 0.0
    assert math.isclose(float(np.linalg.norm(n)), 1.0, abs_tol=TOL)
    assert same_rotation_quat(n, q)


def test_quat_normalize_rejects_zero() -> None:
    with pytest.raises(ValueError):
        quat_normalize([0.0, 0.0, 0.0, 0.0])


@PROPERTY
@given(a=quaternions(), b=quaternions())
def test_quat_multiply_matches_matrix_product(a: np.ndarray, b: np.ndarray) -> None:
    np.testing.assert_allclose(rot(quat_multiply(a, b)), rot(a) @ rot(b), atol=TOL)


@PROPERTY
@given(q=quaternions(), v=vector)
def test_quat_multiply_applies_b_first_then_a(q: np.ndarray, v: np.ndarray) -> None:
    # A rotation of 90 deg about z applied after q.
    qz = quat_from_yaw(math.pi / 2)
    expected = rot(qz) @ (rot(q) @ v)
    np.testing.assert_allclose(rot(quat_multiply(qz, q)) @ v, expected, atol=1e-7)


@PROPERTY
@given(q=quaternions())
def test_conjugate_is_inverse(q: np.ndarray) -> None:
    np.testing.assert_allclose(quat_multiply(q, quat_conjugate(q)), [1.0, 0.0, 0.0, 0.0], atol=TOL)
    np.testing.assert_allclose(rot(quat_conjugate(q)), rot(q).T, atol=TOL)


@PROPERTY
@given(
    roll=st.floats(-3.1, 3.1),
    pitch=st.floats(-1.4, 1.4),  # away from gimbal lock at +-pi/2
    yaw=st.floats(-3.1, 3.1),
)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    r, p, y = euler_zyx_from_quat(quat_from_euler_zyx(roll, pitch, yaw))
    assert abs(angle_diff(r, roll)) < 1e-9
    assert abs(p - pitch) < 1e-9
    assert abs(angle_diff(y, yaw)) < 1e-9


@PROPERTY
@given(roll=st.floats(-3.1, 3.1), pitch=st.floats(-1.4, 1.4), yaw=st.floats(-3.1, 3.1))
def test_euler_zyx_is_yaw_then_pitch_then_roll(roll: float, pitch: float, yaw: float) -> None:
    def rx(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(a: float) -> np.ndarray:
        c, s = math.cos(a), math.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    expected = rz(yaw) @ ry(pitch) @ rx(roll)
    np.testing.assert_allclose(rot(quat_from_euler_zyx(roll, pitch, yaw)), expected, atol=TOL)


def test_euler_vectorized() -> None:
    roll = np.array([0.1, -0.2, 0.0])
    pitch = np.array([0.0, 0.3, -0.4])
    yaw = np.array([1.0, 2.0, -3.0])
    q = quat_from_euler_zyx(roll, pitch, yaw)
    assert q.shape == (3, 4)
    r, p, y = euler_zyx_from_quat(q)
    np.testing.assert_allclose(r, roll, atol=TOL)
    np.testing.assert_allclose(p, pitch, atol=TOL)
    np.testing.assert_allclose(y, yaw, atol=TOL)


@PROPERTY
@given(q=quaternion_batches(), v=vector)
def test_world_to_body_inverts_body_to_world(q: np.ndarray, v: np.ndarray) -> None:
    r = quat_to_rotmat(q)
    vs = np.broadcast_to(v, (q.shape[0], 3))
    world = body_to_world(vs, r)
    np.testing.assert_allclose(world_to_body(world, r), vs, atol=1e-7)
    np.testing.assert_allclose(body_to_world(world_to_body(vs, r), r), vs, atol=1e-7)
    # Rotations keep lengths.
    np.testing.assert_allclose(np.linalg.norm(world, axis=-1), np.linalg.norm(vs, axis=-1))
    np.testing.assert_allclose(world[0], r[0] @ v, atol=1e-7)


# --------------------------------------------------------------------------------------------
# Known attitudes
# --------------------------------------------------------------------------------------------


def test_identity_attitude_keeps_axes() -> None:
    r = quat_to_rotmat([1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(r, np.eye(3), atol=TOL)


def test_yaw_90_deg_enu_faces_north() -> None:
    r = quat_to_rotmat(quat_from_yaw(math.pi / 2))
    # Body forward -> world north; body left -> world west; up stays up.
    np.testing.assert_allclose(body_to_world([1.0, 0.0, 0.0], r), [0.0, 1.0, 0.0], atol=TOL)
    np.testing.assert_allclose(body_to_world([0.0, 1.0, 0.0], r), [-1.0, 0.0, 0.0], atol=TOL)
    np.testing.assert_allclose(body_to_world([0.0, 0.0, 1.0], r), [0.0, 0.0, 1.0], atol=TOL)
    # A world velocity to the north is "forward" for this drone.
    np.testing.assert_allclose(world_to_body([0.0, 3.0, 0.0], r), [3.0, 0.0, 0.0], atol=TOL)
    # Same attitude through the Euler helper.
    np.testing.assert_allclose(rot(quat_from_euler_zyx(0.0, 0.0, math.pi / 2)), r, atol=TOL)


def test_positive_pitch_is_nose_down_in_flu() -> None:
    # FLU: y points left, so a right-handed rotation about +y takes x (forward) towards -z:
    # positive pitch = nose down. Forward becomes (cos 10deg, 0, -sin 10deg).
    a = math.radians(10.0)
    r = quat_to_rotmat(quat_from_euler_zyx(0.0, a, 0.0))
    forward = body_to_world([1.0, 0.0, 0.0], r)
    np.testing.assert_allclose(forward, [math.cos(a), 0.0, -math.sin(a)], atol=TOL)
    assert forward[2] < 0.0


def test_positive_roll_lifts_the_left_side_in_flu() -> None:
    # Right-handed rotation about +x (forward) takes y (left) towards +z: left side up.
    a = math.radians(15.0)
    r = quat_to_rotmat(quat_from_euler_zyx(a, 0.0, 0.0))
    left = body_to_world([0.0, 1.0, 0.0], r)
    np.testing.assert_allclose(left, [0.0, math.cos(a), math.sin(a)], atol=TOL)


# --------------------------------------------------------------------------------------------
# ENU <-> NED, FLU <-> FRD
# --------------------------------------------------------------------------------------------


def test_enu_to_ned_known_vector() -> None:
    # (east 1, north 2, up 3) -> (north 2, east 1, down -3)
    np.testing.assert_array_equal(enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_array_equal(ned_to_enu([2.0, 1.0, -3.0]), [1.0, 2.0, 3.0])


def test_flu_to_frd_known_vector() -> None:
    # (forward 1, left 2, up 3) -> (forward 1, right -2, down -3)
    np.testing.assert_array_equal(flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    np.testing.assert_array_equal(frd_to_flu([1.0, -2.0, -3.0]), [1.0, 2.0, 3.0])


@PROPERTY
@given(v=vector)
def test_frame_swaps_are_involutions_and_match_their_matrices(v: np.ndarray) -> None:
    np.testing.assert_array_equal(ned_to_enu(enu_to_ned(v)), v)
    np.testing.assert_array_equal(frd_to_flu(flu_to_frd(v)), v)
    np.testing.assert_array_equal(enu_to_ned(v), R_NED_ENU @ v)
    np.testing.assert_array_equal(frd_to_flu(v), R_FLU_FRD @ v)


def test_frame_swap_matrices_are_proper_rotations() -> None:
    for m in (R_NED_ENU, R_FLU_FRD):
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=TOL)
        assert np.linalg.det(m) == pytest.approx(1.0)


def test_frame_swaps_are_vectorized() -> None:
    v = np.arange(24.0).reshape(2, 4, 3)
    out = enu_to_ned(v)
    assert out.shape == (2, 4, 3)
    np.testing.assert_array_equal(out[1, 2], enu_to_ned(v[1, 2]))
    assert flu_to_frd(v).shape == (2, 4, 3)


def test_yaw_enu_to_ned_known_headings() -> None:
    # ENU yaw 0 faces east = NED yaw 90 deg; ENU 90 deg faces north = NED 0.
    assert float(yaw_enu_to_ned(0.0)) == pytest.approx(math.pi / 2, abs=TOL)
    assert float(yaw_enu_to_ned(math.pi / 2)) == pytest.approx(0.0, abs=TOL)
    # ENU 180 deg faces west = NED -90 deg.
    assert float(yaw_enu_to_ned(math.pi)) == pytest.approx(-math.pi / 2, abs=TOL)
    # ENU -90 deg faces south = NED 180 deg (reported as -pi in [-pi, pi)).
    assert abs(float(angle_diff(yaw_enu_to_ned(-math.pi / 2), math.pi))) < TOL
    # And back.
    assert float(yaw_ned_to_enu(0.0)) == pytest.approx(math.pi / 2, abs=TOL)
    assert float(yaw_ned_to_enu(math.pi / 2)) == pytest.approx(0.0, abs=TOL)


@PROPERTY
@given(yaw=st.floats(-10.0, 10.0))
def test_yaw_enu_ned_round_trip(yaw: float) -> None:
    back = yaw_ned_to_enu(yaw_enu_to_ned(yaw))
    assert abs(float(angle_diff(back, yaw))) < 1e-9


@PROPERTY
@given(yaw=st.floats(-3.1, 3.1))
def test_yaw_enu_to_ned_agrees_with_heading_vectors(yaw: float) -> None:
    heading_enu = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    yaw_ned = float(yaw_enu_to_ned(yaw))
    heading_ned = np.array([math.cos(yaw_ned), math.sin(yaw_ned), 0.0])
    np.testing.assert_allclose(enu_to_ned(heading_enu), heading_ned, atol=TOL)


# --------------------------------------------------------------------------------------------
# Attitude between the simulator (ENU/FLU) and PX4 (NED/FRD)
# --------------------------------------------------------------------------------------------


@PROPERTY
@given(q=quaternions(), v_frd=vector)
def test_ned_frd_attitude_maps_body_vectors_like_the_enu_flu_one(
    q: np.ndarray, v_frd: np.ndarray
) -> None:
    q_ned_frd = quat_enu_flu_to_ned_frd(q)
    lhs = rot(q_ned_frd) @ v_frd
    rhs = enu_to_ned(rot(q) @ frd_to_flu(v_frd))
    np.testing.assert_allclose(lhs, rhs, atol=1e-7)


@PROPERTY
@given(q=quaternion_batches())
def test_enu_flu_ned_frd_round_trip(q: np.ndarray) -> None:
    q_ned_frd = quat_enu_flu_to_ned_frd(q)
    assert q_ned_frd.shape == q.shape
    assert np.all(q_ned_frd[..., 0] >= 0.0)
    back = quat_ned_frd_to_enu_flu(q_ned_frd)
    for a, b in zip(back, q, strict=True):
        assert same_rotation_quat(a, b)


def test_identity_enu_attitude_faces_east_in_ned() -> None:
    q_ned = quat_enu_flu_to_ned_frd([1.0, 0.0, 0.0, 0.0])
    roll, pitch, yaw = euler_zyx_from_quat(q_ned)
    assert float(roll) == pytest.approx(0.0, abs=TOL)
    assert float(pitch) == pytest.approx(0.0, abs=TOL)
    assert float(yaw) == pytest.approx(math.pi / 2, abs=TOL)
    # Body forward is east, i.e. NED (0, 1, 0); body down is NED down.
    np.testing.assert_allclose(rot(q_ned) @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=TOL)
    np.testing.assert_allclose(rot(q_ned) @ [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], atol=TOL)


@PROPERTY
@given(roll=st.floats(-1.0, 1.0), pitch=st.floats(-1.0, 1.0), yaw=st.floats(-3.1, 3.1))
def test_euler_angles_in_ned_frd(roll: float, pitch: float, yaw: float) -> None:
    # Same physical attitude: roll is the same (right side down in both), pitch flips sign
    # (FLU positive = nose down, FRD positive = nose up), yaw maps with yaw_enu_to_ned.
    q_ned = quat_enu_flu_to_ned_frd(quat_from_euler_zyx(roll, pitch, yaw))
    r, p, y = euler_zyx_from_quat(q_ned)
    assert abs(float(angle_diff(r, roll))) < 1e-9
    assert abs(float(p) + pitch) < 1e-9
    assert abs(float(angle_diff(y, yaw_enu_to_ned(yaw)))) < 1e-9
