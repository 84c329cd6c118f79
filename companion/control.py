"""The control law between the policy and the autopilot: filter, rotate, migrate, cap, guard, yaw.

One tick, for one drone or vectorized over N agents (the simulation's CNN controller):

    v_body  = policy output, body FLU (m/s)
    v_filt  = low-pass(v_body)                            (optional, first order, per agent)
    v_world = cap(R_world_body(q at capture) v_filt + v_mig, v_max)        world ENU
    v_final = cap(altitude_guard(v_world, z - z_home), v_max)      (the band is above home)
    yaw     = heading of v_final, held while |v_final,xy| < yaw_hold_speed
    PX4     = (enu_to_ned(v_final), yaw_enu_to_ned(yaw))                    NED, radians

The functions are pure (numpy in, numpy out; shapes (..., 3), quaternions (..., 4) scalar first,
body FLU -> world ENU); `ControlLaw` adds the only state: the filter and the held yaw.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion import frames
from companion.errors import ConfigError
from companion.flocking import cap_speed, migration_velocity
from companion.geo import require_global
from companion.sections import section_from_dict
from companion.validation import require_range, require_vector3

FloatArray = NDArray[np.float64]
SECTION = "control"


@dataclass(frozen=True)
class ControlConfig:
    """The `[control]` section. Speeds in m/s. Points in the world ENU frame (PX4's local frame,
    z = 0 at its EKF origin); the altitude band in m above PX4's home, as PX4's own geofence and
    take-off heights are (the EKF origin until PX4 reports a home: the two can differ by tenths of
    a metre or more, 0.74 m seen in SITL on a loaded machine)."""

    k_mig: float = 1.0  # migration speed (paper: 1)
    v_max_mps: float = 2.0  # speed cap of the final command (paper: 2)
    migration_point_enu: tuple[float, float, float] | None = None  # None: no migration
    # Or the point as [lat deg, lon deg, alt AMSL m]: converted with PX4's home (companion.geo).
    migration_point_global: tuple[float, float, float] | None = None
    low_pass_cutoff_hz: float | None = None  # None: filter off
    yaw_hold_speed_mps: float = 0.3  # below this horizontal speed the yaw setpoint is held
    altitude_floor_m: float | None = 1.0  # no descent below this (None: no floor)
    altitude_ceiling_m: float | None = 30.0  # no climb above this (None: no ceiling)
    altitude_push_gain_per_s: float = 1.0  # push back towards the band: gain * metres outside
    altitude_push_max_mps: float = 0.5  # and at most this fast

    def __post_init__(self) -> None:
        s = SECTION
        require_range(f"{s}.k_mig", self.k_mig, 0.0, 20.0)
        require_range(f"{s}.v_max_mps", self.v_max_mps, 0.0, 20.0, low_inclusive=False)
        if self.migration_point_enu is not None:
            point = require_vector3(f"{s}.migration_point_enu", self.migration_point_enu)
            object.__setattr__(self, "migration_point_enu", point)
        if self.migration_point_global is not None:
            field = f"{s}.migration_point_global"
            point = require_global(field, self.migration_point_global)
            object.__setattr__(self, "migration_point_global", point)
            if self.migration_point_enu is not None:
                raise ConfigError(
                    f"{field}: give the migration point once, either {field} "
                    f"([lat_deg, lon_deg, alt_amsl_m]) or {s}.migration_point_enu, not both"
                )
        if self.low_pass_cutoff_hz is not None:
            require_range(
                f"{s}.low_pass_cutoff_hz", self.low_pass_cutoff_hz, 0.0, 1000.0, low_inclusive=False
            )
        require_range(f"{s}.yaw_hold_speed_mps", self.yaw_hold_speed_mps, 0.0, 20.0)
        if self.altitude_floor_m is not None:
            require_range(f"{s}.altitude_floor_m", self.altitude_floor_m, -1000.0, 10000.0)
        if self.altitude_ceiling_m is not None:
            require_range(f"{s}.altitude_ceiling_m", self.altitude_ceiling_m, -1000.0, 10000.0)
        if (
            self.altitude_floor_m is not None
            and self.altitude_ceiling_m is not None
            and self.altitude_ceiling_m <= self.altitude_floor_m
        ):
            raise ConfigError(
                f"{s}.altitude_ceiling_m: {self.altitude_ceiling_m:g} must be above "
                f"{s}.altitude_floor_m ({self.altitude_floor_m:g})"
            )
        require_range(f"{s}.altitude_push_gain_per_s", self.altitude_push_gain_per_s, 0.0, 10.0)
        require_range(f"{s}.altitude_push_max_mps", self.altitude_push_max_mps, 0.0, 5.0)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ControlConfig:
        """From the parsed `[control]` table; unknown keys are refused, naming them."""
        overrides: dict[str, Any] = {}
        point = data.get("migration_point_enu") if isinstance(data, Mapping) else None
        if point is not None:
            field = f"{SECTION}.migration_point_enu"
            overrides["migration_point_enu"] = require_vector3(field, point)
        return section_from_dict(cls, SECTION, data, **overrides)


class LowPassFilter:
    """First-order low-pass y += alpha (x - y), alpha = dt / (dt + 1 / (2 pi f_c)), per agent.

    Off (`cutoff_hz=None`) it passes its input through. The state starts at zero (a drone at
    rest) and takes its shape, e.g. (3,) or (N, 3), from the first input; `reset()` returns it to
    zero (or to `value`).
    """

    def __init__(self, cutoff_hz: float | None, dt_s: float) -> None:
        if cutoff_hz is not None and not (math.isfinite(cutoff_hz) and cutoff_hz > 0.0):
            raise ValueError(f"cutoff_hz must be > 0 or None, got {cutoff_hz!r}")
        if not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        self.cutoff_hz = cutoff_hz
        self.dt_s = dt_s
        self._state: FloatArray | None = None

    @property
    def enabled(self) -> bool:
        return self.cutoff_hz is not None

    def alpha(self, dt_s: float | None = None) -> float:
        """Blend factor of one step of `dt_s` (default: the nominal period); 1 when off."""
        if self.cutoff_hz is None:
            return 1.0
        dt = self.dt_s if dt_s is None else dt_s
        tau_s = 1.0 / (2.0 * math.pi * self.cutoff_hz)
        return dt / (dt + tau_s)

    def step(self, x: ArrayLike, dt_s: float | None = None) -> FloatArray:
        """Filter one sample (any shape, fixed after the first call); returns the new output."""
        value = np.asarray(x, dtype=np.float64)
        if dt_s is not None and not (math.isfinite(dt_s) and dt_s > 0.0):
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        if self.cutoff_hz is None:
            return value.copy()
        if self._state is None:
            self._state = np.zeros_like(value)
        elif self._state.shape != value.shape:
            raise ValueError(f"filter state has shape {self._state.shape}, input {value.shape}")
        self._state = self._state + self.alpha(dt_s) * (value - self._state)
        return self._state.copy()

    def reset(self, value: ArrayLike | None = None) -> None:
        """Forget the state (next output starts from zero), or set it to `value`."""
        self._state = None if value is None else np.array(value, dtype=np.float64)

    def reset_rows(self, rows: ArrayLike) -> None:
        """Zero the state of the agents selected by the boolean mask `rows` (state shape[:-1])."""
        if self._state is not None:
            self._state[np.asarray(rows, dtype=bool)] = 0.0


def compose_velocity(
    vel_body_flu: ArrayLike,
    q_world_body_wxyz: ArrayLike,
    pos_world_enu: ArrayLike,
    migration_point_world_enu: ArrayLike | None,
    k_mig: float,
    v_max_mps: float,
) -> FloatArray:
    """cap(R_world_body v_body + v_mig, v_max): the world-ENU command (..., 3) in m/s.

    Shapes: velocity (..., 3) body FLU; attitude (..., 4) wxyz body FLU -> world ENU (use the
    attitude at image capture time); position (..., 3) m; migration point (..., 3) or (3,)
    (NaN rows: no point) or None.
    """
    v_body = np.asarray(vel_body_flu, dtype=np.float64)
    rot = frames.quat_to_rotmat(q_world_body_wxyz)
    v_world = frames.body_to_world(v_body, rot)
    pos = np.asarray(pos_world_enu, dtype=np.float64)
    lead = np.broadcast_shapes(v_world.shape, pos.shape)[:-1]
    pos_rows = np.broadcast_to(pos, (*lead, 3)).reshape(-1, 3)
    target: FloatArray | None = None
    if migration_point_world_enu is not None:
        target_full = np.broadcast_to(
            np.asarray(migration_point_world_enu, dtype=np.float64), (*lead, 3)
        )
        target = target_full.reshape(-1, 3)
    v_mig = migration_velocity(pos_rows, target, k_mig).reshape(*lead, 3)
    return cap_speed(v_world + v_mig, v_max_mps)


def yaw_setpoint(
    vel_world_enu: ArrayLike, hold_yaw_rad: ArrayLike, min_speed_mps: float
) -> FloatArray:
    """ENU yaw facing the horizontal velocity, `hold_yaw_rad` where it is slower than the limit.

    Shapes: (..., 3) and (...) -> (...), wrapped to [-pi, pi).
    """
    yaw = frames.yaw_from_velocity(vel_world_enu, hold_yaw_rad, min_speed_mps)
    return frames.wrap_angle(yaw)


def altitude_guard(
    vel_world_enu: ArrayLike,
    z_enu_m: ArrayLike,
    floor_m: float | None,
    ceiling_m: float | None,
    push_gain_per_s: float = 1.0,
    push_max_mps: float = 0.5,
) -> FloatArray:
    """Keep the altitude band: at or below the floor no descent, above the ceiling no climb.

    Outside the band the vertical speed is also pushed back towards it: at least
    min(gain * depth, push_max) upwards below the floor (at most that downwards above the
    ceiling). Inside the band the command is unchanged. Shapes (..., 3) and (...) -> (..., 3).
    """
    v = np.array(vel_world_enu, dtype=np.float64)
    z = np.asarray(z_enu_m, dtype=np.float64)
    vz = v[..., 2]
    if floor_m is not None:
        push_up = np.minimum(push_gain_per_s * np.maximum(floor_m - z, 0.0), push_max_mps)
        vz = np.where(z <= floor_m, np.maximum(vz, push_up), vz)
    if ceiling_m is not None:
        push_down = np.minimum(push_gain_per_s * np.maximum(z - ceiling_m, 0.0), push_max_mps)
        vz = np.where(z >= ceiling_m, np.minimum(vz, -push_down), vz)
    v[..., 2] = vz
    return v


def to_px4_setpoint(
    vel_world_enu: ArrayLike, yaw_enu_rad: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """World ENU velocity (..., 3) and ENU yaw (...) -> PX4 NED velocity (..., 3), NED yaw (...).

    NED yaw: 0 = north, clockwise, radians wrapped to [-pi, pi) (MAVSDK wants degrees: convert
    at the autopilot boundary).
    """
    return frames.enu_to_ned(vel_world_enu), frames.yaw_enu_to_ned(yaw_enu_rad)


@dataclass(frozen=True)
class ControlOutput:
    """Every intermediate of one tick; arrays (3,) for one drone or (N, 3) for N agents."""

    vel_body_flu: FloatArray  # policy output as given
    vel_body_filtered_flu: FloatArray  # after the low-pass (equal to the input when off)
    vel_world_enu: FloatArray  # rotated, + migration, capped (before the altitude guard)
    vel_final_enu: FloatArray  # after the altitude guard and the final cap: what is flown
    yaw_enu_rad: FloatArray  # () or (N,)
    vel_ned: FloatArray  # vel_final_enu in PX4's NED frame
    yaw_ned_rad: FloatArray
    valid: NDArray[np.bool_]  # () or (N,): False where inputs were invalid (command: hover)
    reason: str  # "" when every row is valid

    @property
    def ok(self) -> bool:
        return bool(np.all(self.valid))

    def as_dict(self) -> dict[str, Any]:
        """Plain lists and floats, for the flight log and telemetry."""
        return {
            "vel_body_flu": self.vel_body_flu.tolist(),
            "vel_body_filtered_flu": self.vel_body_filtered_flu.tolist(),
            "vel_world_enu": self.vel_world_enu.tolist(),
            "vel_final_enu": self.vel_final_enu.tolist(),
            "yaw_enu_rad": self.yaw_enu_rad.tolist(),
            "vel_ned": self.vel_ned.tolist(),
            "yaw_ned_rad": self.yaw_ned_rad.tolist(),
            "ok": self.ok,
            "reason": self.reason,
        }


class ControlLaw:
    """The stateful control law: low-pass filter and held yaw around the pure functions above.

    Invalid inputs (non-finite velocity, attitude, position or yaw; a zero quaternion) never reach
    the setpoint: that row is commanded to hover (zero velocity, yaw held) and `reason` says why.
    MAVSDK getters return NaN before the first telemetry arrives, so this happens in practice.
    """

    def __init__(self, config: ControlConfig, nominal_dt_s: float = 0.1) -> None:
        self.config = config
        self.filter = LowPassFilter(config.low_pass_cutoff_hz, nominal_dt_s)
        self._held_yaw_enu_rad: FloatArray | None = None
        self._hovering = False

    def reset(self) -> None:
        """Forget the filter state and the held yaw (e.g. after a pause of the pipeline)."""
        self.filter.reset()
        self._held_yaw_enu_rad = None
        self._hovering = False

    def _hold(self, yaw_enu_rad: FloatArray) -> FloatArray:
        if self._held_yaw_enu_rad is None or self._held_yaw_enu_rad.shape != yaw_enu_rad.shape:
            return yaw_enu_rad
        # Rows whose held yaw was lost to bad input take the measured one again.
        return np.where(np.isfinite(self._held_yaw_enu_rad), self._held_yaw_enu_rad, yaw_enu_rad)

    def step(
        self,
        vel_body_flu: ArrayLike,
        q_world_body_wxyz: ArrayLike,
        pos_world_enu: ArrayLike,
        yaw_enu_rad: ArrayLike,
        dt_s: float | None = None,
        migration_point_world_enu: ArrayLike | None = None,
        home_z_enu_m: ArrayLike = 0.0,
    ) -> ControlOutput:
        """One tick. Shapes (3,), (4,), (3,), () for one drone or (N, 3), (N, 4), (N, 3), (N,).

        `yaw_enu_rad` is the measured yaw, used to initialize the held yaw. The migration point
        defaults to the configured one; pass (N, 3) (NaN rows: none) for per-agent points.
        `home_z_enu_m`: the home's height in the world frame, from which the altitude band is
        measured (0: the frame's origin).
        """
        cfg = self.config
        v_body = np.asarray(vel_body_flu, dtype=np.float64)
        q = np.asarray(q_world_body_wxyz, dtype=np.float64)
        pos = np.asarray(pos_world_enu, dtype=np.float64)
        yaw_now = np.asarray(yaw_enu_rad, dtype=np.float64)
        if v_body.shape[-1:] != (3,) or q.shape[-1:] != (4,) or pos.shape[-1:] != (3,):
            raise ValueError(
                f"expected shapes (...,3), (...,4), (...,3); got {v_body.shape}, {q.shape}, "
                f"{pos.shape}"
            )
        checks = (
            ("velocity", np.all(np.isfinite(v_body), axis=-1)),
            ("attitude", np.all(np.isfinite(q), axis=-1) & (np.linalg.norm(q, axis=-1) > 0.5)),
            ("position", np.all(np.isfinite(pos), axis=-1)),
            ("yaw", np.isfinite(yaw_now)),
        )
        valid = np.ones(np.broadcast_shapes(*(c.shape for _, c in checks)), dtype=bool)
        bad = []
        for name, check in checks:
            valid &= check
            if not np.all(check):
                bad.append(name)
        reason = "" if not bad else f"invalid input ({', '.join(bad)}): hover"
        safe_v = np.where(valid[..., None], v_body, 0.0)
        safe_q = np.where(valid[..., None], q, np.array([1.0, 0.0, 0.0, 0.0]))
        safe_pos = np.where(valid[..., None], pos, 0.0)
        safe_yaw = np.where(valid, yaw_now, 0.0)
        migration = cfg.migration_point_enu
        target = migration_point_world_enu if migration_point_world_enu is not None else migration

        v_filt = self.filter.step(safe_v, dt_s)
        v_world = compose_velocity(v_filt, safe_q, safe_pos, target, cfg.k_mig, cfg.v_max_mps)
        v_guarded = altitude_guard(
            v_world,
            safe_pos[..., 2] - np.asarray(home_z_enu_m, dtype=np.float64),
            cfg.altitude_floor_m,
            cfg.altitude_ceiling_m,
            cfg.altitude_push_gain_per_s,
            cfg.altitude_push_max_mps,
        )
        v_final = np.where(valid[..., None], cap_speed(v_guarded, cfg.v_max_mps), 0.0)
        hold = self._hold(np.broadcast_to(safe_yaw, valid.shape).astype(np.float64))
        yaw = yaw_setpoint(v_final, hold, cfg.yaw_hold_speed_mps)
        self._held_yaw_enu_rad = np.where(valid, yaw, np.nan)
        self._hovering = False
        if not np.all(valid):
            # A hovering row restarts its filter from rest when its inputs come back.
            self.filter.reset_rows(~valid)
        vel_ned, yaw_ned = to_px4_setpoint(v_final, yaw)
        return ControlOutput(
            vel_body_flu=v_body.copy(),
            vel_body_filtered_flu=v_filt,
            vel_world_enu=v_world,
            vel_final_enu=v_final,
            yaw_enu_rad=yaw,
            vel_ned=vel_ned,
            yaw_ned_rad=yaw_ned,
            valid=valid,
            reason=reason,
        )

    def hover(self, yaw_enu_rad: float, reason: str) -> ControlOutput:
        """A one-drone hover command (zero velocity, the current heading held) and a filter reset.

        For ticks without a usable policy output (stale images, model failure): the stop is
        immediate, not filtered, and the filter restarts from rest.
        """
        self.filter.reset()
        measured = np.asarray(yaw_enu_rad, dtype=np.float64)
        # The first hover tick holds the heading the vehicle has now, later ones keep it: holding
        # the last commanded heading turned PX4 SITL's vehicle by 8 deg at the switch (issue 19).
        held = self._hold(measured) if self._hovering or not np.isfinite(measured) else measured
        self._hovering = True
        yaw = held if np.isfinite(held) else np.asarray(0.0)
        zero = np.zeros(3)
        vel_ned, yaw_ned = to_px4_setpoint(zero, yaw)
        self._held_yaw_enu_rad = np.asarray(yaw, dtype=np.float64)
        return ControlOutput(
            vel_body_flu=zero,
            vel_body_filtered_flu=zero.copy(),
            vel_world_enu=zero.copy(),
            vel_final_enu=zero.copy(),
            yaw_enu_rad=np.asarray(yaw, dtype=np.float64),
            vel_ned=vel_ned,
            yaw_ned_rad=yaw_ned,
            valid=np.asarray(False),
            reason=reason,
        )
