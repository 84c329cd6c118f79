"""Frame conventions, written once.

- **World (simulation):** ENU — x east, y north, z up. Yaw 0 faces east, positive counter-clockwise.
- **PX4 / MAVSDK local frame:** NED — x north, y east, z down. Yaw 0 faces north, clockwise.
- **Body frame of the CNN targets:** FLU — x forward, y left, z up. It is the body frame that goes
  with ENU (at zero roll, pitch and yaw it coincides with the world axes). PX4's body frame is FRD;
  convert explicitly with `flu_to_frd` / `frd_to_flu` at the autopilot boundary.

Quaternions are Hamilton, scalar first (`q_wxyz`), unit norm. `q_world_body` (and the rotation
matrix `R_world_body`, columns = body axes in world coordinates) maps body vectors into the world:
`v_world = R_world_body @ v_body`. All functions are vectorized over leading dimensions.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

WORLD_FRAME = "ENU"
AUTOPILOT_FRAME = "NED"
BODY_FRAME = "FLU"

# Rotation taking ENU coordinates to NED coordinates (a proper rotation; it is its own inverse).
R_NED_ENU: FloatArray = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# Rotation taking FRD coordinates to FLU coordinates (180 deg about x; its own inverse).
R_FLU_FRD: FloatArray = np.diag([1.0, -1.0, -1.0])

_EPS = 1e-12


def _as_float(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=np.float64)


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Wrap angles to [-pi, pi)."""
    a = _as_float(angle_rad)
    wrapped = (a + np.pi) % (2.0 * np.pi) - np.pi
    # The modulo of a tiny negative number can round up to exactly 2 pi, giving +pi.
    return np.asarray(np.where(wrapped >= np.pi, wrapped - 2.0 * np.pi, wrapped), dtype=np.float64)


def quat_normalize(q_wxyz: ArrayLike) -> FloatArray:
    """Unit quaternion(s) with a non-negative scalar part. Shape (..., 4)."""
    q = _as_float(q_wxyz)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(norm < _EPS):
        raise ValueError("cannot normalize a zero quaternion")
    q = q / norm
    return np.asarray(np.where(q[..., :1] < 0.0, -q, q), dtype=np.float64)


def quat_conjugate(q_wxyz: ArrayLike) -> FloatArray:
    """Conjugate (the inverse of a unit quaternion). Shape (..., 4)."""
    q = _as_float(q_wxyz)
    return np.asarray(q * np.array([1.0, -1.0, -1.0, -1.0]), dtype=np.float64)


def quat_multiply(a_wxyz: ArrayLike, b_wxyz: ArrayLike) -> FloatArray:
    """Hamilton product a * b (apply b first, then a). Shapes broadcast over (..., 4)."""
    a = _as_float(a_wxyz)
    b = _as_float(b_wxyz)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_to_rotmat(q_wxyz: ArrayLike) -> FloatArray:
    """Rotation matrix R (..., 3, 3) of unit quaternion(s) q (..., 4): v' = R @ v."""
    q = _as_float(q_wxyz)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    r = np.empty((*q.shape[:-1], 3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def rotmat_to_quat(rotmat: ArrayLike) -> FloatArray:
    """Unit quaternion(s) (..., 4), scalar part >= 0, of rotation matrices (..., 3, 3).

    Uses the numerically stable branch (largest of w, x, y, z) per matrix.
    """
    r = _as_float(rotmat)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate 4*component^2 values; pick the largest per matrix.
    cand = np.stack([1 + trace, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22])
    best = np.argmax(cand, axis=0)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, best[None], axis=0)[0], _EPS))
    d21 = r[..., 2, 1] - r[..., 1, 2]
    d02 = r[..., 0, 2] - r[..., 2, 0]
    d10 = r[..., 1, 0] - r[..., 0, 1]
    s01 = r[..., 0, 1] + r[..., 1, 0]
    s02 = r[..., 0, 2] + r[..., 2, 0]
    s12 = r[..., 1, 2] + r[..., 2, 1]
    options = np.stack(
        [
            np.stack([s / 4, d21 / s, d02 / s, d10 / s], axis=-1),
            np.stack([d21 / s, s / 4, s01 / s, s02 / s], axis=-1),
            np.stack([d02 / s, s01 / s, s / 4, s12 / s], axis=-1),
            np.stack([d10 / s, s02 / s, s12 / s, s / 4], axis=-1),
        ]
    )
    q = np.take_along_axis(options, best[None, ..., None], axis=0)[0]
    return quat_normalize(q)


def quat_from_euler_zyx(
    roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike
) -> FloatArray:
    """Quaternion of intrinsic Z-Y-X (yaw, then pitch, then roll) Euler angles."""
    r, p, y = np.broadcast_arrays(_as_float(roll_rad), _as_float(pitch_rad), _as_float(yaw_rad))
    cr, sr = np.cos(r / 2), np.sin(r / 2)
    cp, sp = np.cos(p / 2), np.sin(p / 2)
    cy, sy = np.cos(y / 2), np.sin(y / 2)
    q = np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )
    return quat_normalize(q)


def euler_zyx_from_quat(q_wxyz: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(roll, pitch, yaw) in radians of unit quaternion(s), intrinsic Z-Y-X."""
    q = quat_normalize(q_wxyz)
    w, x, y, z = np.moveaxis(q, -1, 0)
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def quat_from_yaw(yaw_rad: ArrayLike) -> FloatArray:
    """Quaternion of a pure rotation about the vertical axis."""
    y = _as_float(yaw_rad)
    return np.stack([np.cos(y / 2), np.zeros_like(y), np.zeros_like(y), np.sin(y / 2)], axis=-1)


def yaw_from_velocity(
    vel_world_enu: ArrayLike, fallback_yaw_rad: ArrayLike, min_speed_mps: float = 0.1
) -> FloatArray:
    """ENU yaw that faces the horizontal velocity; `fallback_yaw_rad` where it is slower.

    Shapes: velocity (..., 3), fallback broadcastable to (...). Returns (...).
    """
    v = _as_float(vel_world_enu)
    speed_xy = np.hypot(v[..., 0], v[..., 1])
    yaw = np.arctan2(v[..., 1], v[..., 0])
    return np.where(speed_xy >= min_speed_mps, yaw, _as_float(fallback_yaw_rad))


def rotmat_from_z_axis_and_yaw(z_axis_world: ArrayLike, yaw_rad: ArrayLike) -> FloatArray:
    """Attitude whose body z axis is `z_axis_world` and whose heading is `yaw_rad` (ENU).

    This is how a multicopter's attitude follows from its thrust direction: the body x axis is the
    heading direction projected onto the plane normal to the thrust. Shapes (..., 3), (...) ->
    (..., 3, 3), columns = body x, y, z in world coordinates.
    """
    z = _as_float(z_axis_world)
    z = z / np.maximum(np.linalg.norm(z, axis=-1, keepdims=True), _EPS)
    yaw = _as_float(yaw_rad)
    heading = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=-1)
    heading = np.broadcast_to(heading, z.shape)
    y = np.cross(z, heading)
    y_norm = np.linalg.norm(y, axis=-1, keepdims=True)
    # Thrust exactly horizontal along the heading: fall back to the world's up for the side axis.
    fallback = np.cross(z, np.broadcast_to(np.array([0.0, 0.0, 1.0]), z.shape))
    y = np.where(y_norm > 1e-9, y / np.maximum(y_norm, _EPS), fallback)
    y = y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), _EPS)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=-1)


def body_to_world(vec_body: ArrayLike, rot_world_body: ArrayLike) -> FloatArray:
    """Rotate body-frame vectors (..., 3) into the world with R_world_body (..., 3, 3)."""
    out = np.einsum("...ij,...j->...i", _as_float(rot_world_body), _as_float(vec_body))
    return np.asarray(out, dtype=np.float64)


def world_to_body(vec_world: ArrayLike, rot_world_body: ArrayLike) -> FloatArray:
    """Rotate world-frame vectors (..., 3) into the body frame: R_world_body^T v."""
    out = np.einsum("...ji,...j->...i", _as_float(rot_world_body), _as_float(vec_world))
    return np.asarray(out, dtype=np.float64)


def enu_to_ned(vec_enu: ArrayLike) -> FloatArray:
    """(east, north, up) -> (north, east, down). Shape (..., 3)."""
    v = _as_float(vec_enu)
    return np.stack([v[..., 1], v[..., 0], -v[..., 2]], axis=-1)


def ned_to_enu(vec_ned: ArrayLike) -> FloatArray:
    """(north, east, down) -> (east, north, up). Shape (..., 3)."""
    return enu_to_ned(vec_ned)  # the permutation is its own inverse


def flu_to_frd(vec_flu: ArrayLike) -> FloatArray:
    """(forward, left, up) -> (forward, right, down). Shape (..., 3)."""
    v = _as_float(vec_flu)
    return np.stack([v[..., 0], -v[..., 1], -v[..., 2]], axis=-1)


def frd_to_flu(vec_frd: ArrayLike) -> FloatArray:
    """(forward, right, down) -> (forward, left, up). Shape (..., 3)."""
    return flu_to_frd(vec_frd)


def yaw_enu_to_ned(yaw_enu_rad: ArrayLike) -> FloatArray:
    """ENU yaw (0 = east, counter-clockwise) -> NED yaw (0 = north, clockwise), wrapped."""
    return wrap_angle(np.pi / 2 - _as_float(yaw_enu_rad))


def yaw_ned_to_enu(yaw_ned_rad: ArrayLike) -> FloatArray:
    """NED yaw -> ENU yaw, wrapped (same formula: the map is an involution)."""
    return yaw_enu_to_ned(yaw_ned_rad)


_Q_NED_ENU = rotmat_to_quat(R_NED_ENU)
_Q_FLU_FRD = rotmat_to_quat(R_FLU_FRD)


def quat_enu_flu_to_ned_frd(q_enu_flu: ArrayLike) -> FloatArray:
    """Attitude as world-ENU<-body-FLU -> the same attitude as PX4's NED<-FRD quaternion."""
    return quat_normalize(quat_multiply(quat_multiply(_Q_NED_ENU, q_enu_flu), _Q_FLU_FRD))


def quat_ned_frd_to_enu_flu(q_ned_frd: ArrayLike) -> FloatArray:
    """PX4's NED<-FRD attitude quaternion -> world-ENU<-body-FLU quaternion."""
    q_enu_ned = quat_conjugate(_Q_NED_ENU)
    q_frd_flu = quat_conjugate(_Q_FLU_FRD)
    return quat_normalize(quat_multiply(quat_multiply(q_enu_ned, q_ned_frd), q_frd_flu))
