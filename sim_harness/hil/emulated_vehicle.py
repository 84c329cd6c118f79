"""The vehicle behind the autopilot emulator: a small interface and a first-order kinematic model.

Everything here is in PX4's frames: positions and velocities in local NED (x north, y east,
z down, metres from the home point), attitude as the NED <- FRD body quaternion (w, x, y, z),
yaw in radians, 0 = north, clockwise positive. The ground is the plane z = 0 (altitude >= 0).

`VehicleBackend` is what the emulator drives; `FirstOrderVehicle` is the default. A pybullet
vehicle can replace it by implementing the same two members.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.frames import quat_from_euler_zyx
from companion.validation import require_non_negative, require_positive, require_vector3

FloatArray = NDArray[np.float64]

GRAVITY_NED_MPS2 = np.array([0.0, 0.0, 9.81])


def _wrap(angle_rad: float) -> float:
    """Wrap to [-pi, pi) (scalar; this runs at the physics rate)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def attitude_from_thrust(body_z_ned: FloatArray, yaw_ned_rad: float) -> FloatArray:
    """q NED <- FRD (w, x, y, z) with body z along `body_z_ned` and Euler yaw `yaw_ned_rad`.

    PX4's construction: roll and pitch tilt the body z axis, and the body x axis stays in the
    vertical plane of the heading (Z-Y-X Euler angles with the given yaw).
    """
    zn, ze, zd = (float(c) for c in body_z_ned / np.linalg.norm(body_z_ned))
    cy, sy = math.cos(yaw_ned_rad), math.sin(yaw_ned_rad)
    forward, right = cy * zn + sy * ze, -sy * zn + cy * ze  # body z in the heading frame
    roll = -math.asin(max(-1.0, min(1.0, right)))
    pitch = math.atan2(forward, zd)
    q = quat_from_euler_zyx(roll, pitch, yaw_ned_rad)
    return q if q[0] >= 0.0 else -q


@dataclass(frozen=True)
class VelocityCommand:
    """What the flight controller asks the vehicle to fly.

    `vel_ned_mps` (3,) m/s; `yaw_ned_rad` the heading to turn to, or None; `yaw_rate_rad_s` the
    turn rate when no heading is given (None or 0: keep the heading).
    """

    vel_ned_mps: FloatArray
    yaw_ned_rad: float | None = None
    yaw_rate_rad_s: float | None = None


@dataclass(frozen=True)
class VehicleStateNed:
    """Position (3,) m, velocity (3,) m/s, attitude q NED <- FRD (4,), body rates (3,) rad/s."""

    pos_ned_m: FloatArray
    vel_ned_mps: FloatArray
    q_ned_frd_wxyz: FloatArray
    rates_frd_rad_s: FloatArray = field(default_factory=lambda: np.zeros(3))

    @property
    def altitude_m(self) -> float:
        """Height above the home plane (m, up positive)."""
        return float(-self.pos_ned_m[2])

    @property
    def yaw_ned_rad(self) -> float:
        """Heading of the body x axis (rad, 0 = north, clockwise)."""
        w, x, y, z = (float(c) for c in self.q_ned_frd_wxyz)
        return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class VehicleBackend(Protocol):
    """A vehicle the emulator can fly. Called from the emulator's thread only."""

    def state(self) -> VehicleStateNed:
        """The current state (a snapshot the caller may keep)."""
        ...

    def step(self, dt_s: float, command: VelocityCommand | None) -> VehicleStateNed:
        """Advance by `dt_s` seconds. `command` None means motors off (disarmed)."""
        ...


@dataclass(frozen=True)
class FirstOrderParams:
    """Response of `FirstOrderVehicle`.

    vel_tau_s: time constant of the velocity response (s); yaw_tau_s: time constant of the yaw
    response (s); yaw_rate_max_rad_s: turn-rate limit; fall_speed_mps: descent speed with the
    motors off.
    """

    vel_tau_s: float = 0.3
    yaw_tau_s: float = 0.3
    yaw_rate_max_rad_s: float = math.radians(90.0)
    fall_speed_mps: float = 3.0

    def __post_init__(self) -> None:
        require_positive("first_order.vel_tau_s", self.vel_tau_s)
        require_positive("first_order.yaw_tau_s", self.yaw_tau_s)
        require_positive("first_order.yaw_rate_max_rad_s", self.yaw_rate_max_rad_s)
        require_non_negative("first_order.fall_speed_mps", self.fall_speed_mps)


class FirstOrderVehicle:
    """Velocity follows the command with a first-order lag; yaw slews to its setpoint.

    The attitude is the one a multicopter would need for the acceleration it is flying: body z
    (down) opposite the thrust, heading = yaw. The vehicle never goes below the ground plane.
    """

    def __init__(
        self,
        pos_ned_m: ArrayLike = (0.0, 0.0, 0.0),
        yaw_ned_rad: float = 0.0,
        params: FirstOrderParams | None = None,
    ) -> None:
        self.params = params if params is not None else FirstOrderParams()
        pos = np.array(require_vector3("vehicle.pos_ned_m", np.asarray(pos_ned_m).tolist()))
        pos[2] = min(pos[2], 0.0)
        self._pos_ned_m = pos
        self._vel_ned_mps = np.zeros(3)
        self._acc_ned_mps2 = np.zeros(3)
        self._yaw_ned_rad = _wrap(float(yaw_ned_rad))
        self._yaw_rate_rad_s = 0.0

    def state(self) -> VehicleStateNed:
        """The current state; attitude from the acceleration being flown and the yaw."""
        thrust_ned = self._acc_ned_mps2 - GRAVITY_NED_MPS2  # specific force, points "up"
        body_z_ned = -thrust_ned
        return VehicleStateNed(
            pos_ned_m=self._pos_ned_m.copy(),
            vel_ned_mps=self._vel_ned_mps.copy(),
            q_ned_frd_wxyz=attitude_from_thrust(body_z_ned, self._yaw_ned_rad),
            rates_frd_rad_s=np.array([0.0, 0.0, self._yaw_rate_rad_s]),
        )

    def step(self, dt_s: float, command: VelocityCommand | None) -> VehicleStateNed:
        """Advance by `dt_s` (s) towards `command` (None: motors off, fall to the ground)."""
        if dt_s <= 0.0:
            return self.state()
        p = self.params
        if command is None:
            target = np.array([0.0, 0.0, p.fall_speed_mps if self._pos_ned_m[2] < 0.0 else 0.0])
        else:
            target = np.asarray(command.vel_ned_mps, dtype=np.float64)
            if target.shape != (3,) or not np.all(np.isfinite(target)):
                target = np.zeros(3)
        blend = 1.0 - math.exp(-dt_s / p.vel_tau_s)
        vel_old = self._vel_ned_mps
        vel_new = vel_old + (target - vel_old) * blend
        pos_new = self._pos_ned_m + 0.5 * (vel_old + vel_new) * dt_s
        if pos_new[2] >= 0.0:  # on the ground: no further descent
            pos_new[2] = 0.0
            vel_new[2] = min(vel_new[2], 0.0)
        self._acc_ned_mps2 = (vel_new - vel_old) / dt_s
        self._vel_ned_mps = vel_new
        self._pos_ned_m = pos_new
        turn_rad = self._yaw_turn(command, dt_s)
        self._yaw_rate_rad_s = turn_rad / dt_s
        self._yaw_ned_rad = _wrap(self._yaw_ned_rad + turn_rad)
        return self.state()

    def _yaw_turn(self, command: VelocityCommand | None, dt_s: float) -> float:
        """Heading change (rad) over `dt_s`: first-order towards the yaw setpoint, rate-limited."""
        p = self.params
        if command is None:
            return 0.0
        if command.yaw_ned_rad is not None and math.isfinite(command.yaw_ned_rad):
            error = _wrap(command.yaw_ned_rad - self._yaw_ned_rad)
            turn = error * (1.0 - math.exp(-dt_s / p.yaw_tau_s))
        elif command.yaw_rate_rad_s is not None and math.isfinite(command.yaw_rate_rad_s):
            turn = command.yaw_rate_rad_s * dt_s
        else:
            turn = 0.0
        max_turn = p.yaw_rate_max_rad_s * dt_s
        return max(-max_turn, min(max_turn, turn))
