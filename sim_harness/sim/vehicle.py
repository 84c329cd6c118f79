"""A multicopter that flies like PX4's velocity control, vectorized over N vehicles.

Per vehicle, each physics step:

1. The world-ENU velocity setpoint is clamped like PX4 (MPC_XY_VEL_MAX, MPC_Z_VEL_MAX_UP/DN).
2. A PID on the velocity error gives an acceleration setpoint (MPC_XY_VEL_{P,I,D}_ACC,
   MPC_Z_VEL_{P,I}_ACC), with anti-windup: the integrator freezes while the output saturates.
3. Limits: vertical acceleration within [-MPC_ACC_DOWN_MAX, MPC_ACC_UP_MAX]; horizontal within
   MPC_ACC_HOR_MAX and within the tilt limit MPC_TILTMAX_AIR (|a_xy| <= (g + a_z) tan(tilt_max)).
4. The thrust acceleration follows the setpoint with a first-order lag (`attitude_tau_s`), which
   stands in for the attitude and thrust loops; linear rotor drag (`drag_per_s`) opposes the
   velocity, so in cruise the integrator holds a forward tilt as on a real quadrotor.
5. The body attitude is the one that produces that thrust: body z (FLU) along the thrust
   direction a_thrust + g*z_up, heading towards the yaw, so the cameras roll and pitch like a real
   quadrotor's. The yaw turns towards the setpoint velocity at most MPC_YAWRAUTO_MAX, and is held
   while the setpoint is slower than `yaw_hold_speed_mps`.
6. Semi-implicit Euler integration; the ground (z = `ground_clearance_m`) stops descent.

Translational dynamics are integrated here (numpy, deterministic); pybullet holds the bodies for
contacts and rendering (see `world.py`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.frames import (
    quat_from_yaw,
    rotmat_from_z_axis_and_yaw,
    rotmat_to_quat,
    wrap_angle,
    yaw_from_velocity,
)
from companion.validation import require_non_negative, require_positive, require_range

FloatArray = NDArray[np.float64]

GRAVITY_MPS2 = 9.81


@dataclass(frozen=True)
class VehicleParams:
    """PX4 multicopter defaults (parameter names in the comments)."""

    mass_kg: float = 1.5
    vel_p_xy: float = 1.8  # MPC_XY_VEL_P_ACC (1/s)
    vel_i_xy: float = 0.4  # MPC_XY_VEL_I_ACC (1/s^2)
    vel_d_xy: float = 0.2  # MPC_XY_VEL_D_ACC (-)
    vel_p_z: float = 4.0  # MPC_Z_VEL_P_ACC (1/s)
    vel_i_z: float = 2.0  # MPC_Z_VEL_I_ACC (1/s^2)
    acc_xy_max_mps2: float = 5.0  # MPC_ACC_HOR_MAX
    acc_up_max_mps2: float = 4.0  # MPC_ACC_UP_MAX
    acc_down_max_mps2: float = 3.0  # MPC_ACC_DOWN_MAX
    tilt_max_deg: float = 45.0  # MPC_TILTMAX_AIR
    vel_xy_max_mps: float = 12.0  # MPC_XY_VEL_MAX
    vel_up_max_mps: float = 3.0  # MPC_Z_VEL_MAX_UP
    vel_down_max_mps: float = 1.5  # MPC_Z_VEL_MAX_DN
    yaw_rate_max_deg_s: float = 45.0  # MPC_YAWRAUTO_MAX
    yaw_hold_speed_mps: float = 0.2  # below this setpoint speed the heading is held
    attitude_tau_s: float = 0.1  # lag of the produced acceleration behind its setpoint
    drag_per_s: float = 0.25  # linear rotor drag: a_drag = -drag_per_s * v (0.5 m/s^2 at 2 m/s)
    ground_clearance_m: float = 0.05  # lowest body-centre altitude (resting on the ground)

    def __post_init__(self) -> None:
        require_positive("vehicle.mass_kg", self.mass_kg)
        for name in ("vel_p_xy", "vel_p_z"):
            require_positive(f"vehicle.{name}", getattr(self, name))
        for name in (
            "vel_i_xy",
            "vel_d_xy",
            "vel_i_z",
            "yaw_hold_speed_mps",
            "ground_clearance_m",
            "drag_per_s",
        ):
            require_non_negative(f"vehicle.{name}", getattr(self, name))
        for name in (
            "acc_xy_max_mps2",
            "acc_up_max_mps2",
            "vel_xy_max_mps",
            "vel_up_max_mps",
            "vel_down_max_mps",
            "yaw_rate_max_deg_s",
            "attitude_tau_s",
        ):
            require_positive(f"vehicle.{name}", getattr(self, name))
        # Descending faster than free fall would need negative thrust.
        require_range(
            "vehicle.acc_down_max_mps2",
            self.acc_down_max_mps2,
            0.0,
            GRAVITY_MPS2,
            low_inclusive=False,
            high_inclusive=False,
        )
        require_range(
            "vehicle.tilt_max_deg",
            self.tilt_max_deg,
            0.0,
            90.0,
            low_inclusive=False,
            high_inclusive=False,
        )


@dataclass
class VehicleState:
    """State of N vehicles; every array's first axis is the agent."""

    pos_world_enu: FloatArray  # (N, 3) m
    vel_world_enu: FloatArray  # (N, 3) m/s
    acc_world_enu: FloatArray  # (N, 3) m/s^2, thrust acceleration minus gravity (lagged)
    yaw_rad: FloatArray  # (N,) ENU heading
    vel_error_integral: FloatArray = field(repr=False)  # (N, 3) m

    @property
    def n_agents(self) -> int:
        return int(self.pos_world_enu.shape[0])


class VehicleModel:
    """N velocity-controlled multicopters; call `step` at the physics rate."""

    def __init__(
        self,
        params: VehicleParams,
        initial_pos_world_enu: ArrayLike,
        initial_yaw_rad: ArrayLike | None = None,
    ) -> None:
        pos = np.array(initial_pos_world_enu, dtype=np.float64)
        if pos.ndim != 2 or pos.shape[1] != 3:
            raise ValueError(f"initial positions must have shape (N, 3), got {pos.shape}")
        n = pos.shape[0]
        yaw = (
            np.zeros(n)
            if initial_yaw_rad is None
            else np.broadcast_to(np.asarray(initial_yaw_rad, dtype=np.float64), (n,)).copy()
        )
        self.params = params
        self._tan_tilt_max = math.tan(math.radians(params.tilt_max_deg))
        self.state = VehicleState(
            pos_world_enu=pos,
            vel_world_enu=np.zeros((n, 3)),
            acc_world_enu=np.zeros((n, 3)),
            yaw_rad=yaw,
            vel_error_integral=np.zeros((n, 3)),
        )
        self._q_world_body: FloatArray | None = quat_from_yaw(yaw)

    @property
    def q_world_body(self) -> FloatArray:
        """Attitudes (N, 4) wxyz, body FLU -> world ENU: thrust along body z, heading = yaw.

        Computed on demand (and cached until the next step): the physics loop itself never
        needs it, only contacts, cameras and logs do.
        """
        if self._q_world_body is None:
            s = self.state
            thrust_dir = s.acc_world_enu + np.array([0.0, 0.0, GRAVITY_MPS2])
            self._q_world_body = rotmat_to_quat(rotmat_from_z_axis_and_yaw(thrust_dir, s.yaw_rad))
        return self._q_world_body

    def clamp_setpoint(self, vel_sp_world_enu: FloatArray) -> FloatArray:
        """Velocity setpoint limited like PX4 (horizontal norm, climb and descent rates)."""
        p = self.params
        sp = np.array(vel_sp_world_enu, dtype=np.float64)
        speed_xy = np.hypot(sp[:, 0], sp[:, 1])
        scale = np.divide(
            p.vel_xy_max_mps,
            speed_xy,
            out=np.ones_like(speed_xy),
            where=speed_xy > p.vel_xy_max_mps,
        )
        sp[:, :2] *= scale[:, None]
        sp[:, 2] = np.clip(sp[:, 2], -p.vel_down_max_mps, p.vel_up_max_mps)
        return sp

    def _acceleration_setpoint(self, vel_sp: FloatArray, dt_s: float) -> FloatArray:
        p, s = self.params, self.state
        err = vel_sp - s.vel_world_enu
        gains_p = np.array([p.vel_p_xy, p.vel_p_xy, p.vel_p_z])
        gains_i = np.array([p.vel_i_xy, p.vel_i_xy, p.vel_i_z])
        gains_d = np.array([p.vel_d_xy, p.vel_d_xy, 0.0])
        # D acts on the measured acceleration (the setpoint is piecewise constant).
        raw = gains_p * err + gains_i * s.vel_error_integral - gains_d * s.acc_world_enu
        acc = self._limit_acceleration(raw)
        # Anti-windup: integrate only the axes whose output is not being limited.
        unsaturated = np.isclose(acc, raw, rtol=1e-9, atol=1e-9)
        s.vel_error_integral += np.where(unsaturated, err * dt_s, 0.0)
        return acc

    def _limit_acceleration(self, acc: FloatArray) -> FloatArray:
        p = self.params
        out = acc.copy()
        out[:, 2] = np.clip(out[:, 2], -p.acc_down_max_mps2, p.acc_up_max_mps2)
        acc_xy_max = np.minimum(p.acc_xy_max_mps2, (GRAVITY_MPS2 + out[:, 2]) * self._tan_tilt_max)
        norm_xy = np.hypot(out[:, 0], out[:, 1])
        scale = np.divide(
            acc_xy_max, norm_xy, out=np.ones_like(norm_xy), where=norm_xy > acc_xy_max
        )
        out[:, :2] *= scale[:, None]
        return out

    def step(
        self, vel_sp_world_enu: ArrayLike, dt_s: float, yaw_sp_rad: ArrayLike | None = None
    ) -> None:
        """Advance all vehicles by `dt_s` towards the (N, 3) world-ENU velocity setpoints.

        `yaw_sp_rad` (N,) ENU: heading setpoints (an offboard yaw, as PX4 tracks it); NaN or None:
        the heading follows the setpoint's direction (held below `yaw_hold_speed_mps`).
        """
        p, s = self.params, self.state
        sp = np.asarray(vel_sp_world_enu, dtype=np.float64)
        if sp.shape != s.pos_world_enu.shape:
            raise ValueError(f"setpoints must have shape {s.pos_world_enu.shape}, got {sp.shape}")
        if not np.all(np.isfinite(sp)):
            raise ValueError("velocity setpoints must be finite")
        sp = self.clamp_setpoint(sp)
        acc_sp = self._acceleration_setpoint(sp, dt_s)
        blend = 1.0 - math.exp(-dt_s / p.attitude_tau_s)
        s.acc_world_enu += (acc_sp - s.acc_world_enu) * blend

        s.vel_world_enu += (s.acc_world_enu - p.drag_per_s * s.vel_world_enu) * dt_s
        s.pos_world_enu += s.vel_world_enu * dt_s
        grounded = s.pos_world_enu[:, 2] < p.ground_clearance_m
        if np.any(grounded):
            s.pos_world_enu[grounded, 2] = p.ground_clearance_m
            s.vel_world_enu[grounded, 2] = np.maximum(s.vel_world_enu[grounded, 2], 0.0)

        yaw_target = yaw_from_velocity(sp, s.yaw_rad, p.yaw_hold_speed_mps)
        if yaw_sp_rad is not None:
            given = np.asarray(yaw_sp_rad, dtype=np.float64)
            yaw_target = np.where(np.isfinite(given), given, yaw_target)
        max_turn = math.radians(p.yaw_rate_max_deg_s) * dt_s
        s.yaw_rad = wrap_angle(
            s.yaw_rad + np.clip(wrap_angle(yaw_target - s.yaw_rad), -max_turn, max_turn)
        )
        self._q_world_body = None
