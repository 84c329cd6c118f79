"""PX4's flight-mode and arming rules, as far as an offboard companion can observe them.

Pure state machine, no I/O: the emulator feeds it commands, setpoints and the vehicle state, and
asks it which velocity command the vehicle should fly. Times are seconds on one monotonic clock.

Rules copied from PX4:

- OFFBOARD is refused unless a setpoint arrived within `offboard_entry_window_s`; in OFFBOARD,
  no setpoint for `offboard_loss_timeout_s` switches to `offboard_loss_mode` (COM_OF_LOSS_T,
  COM_OBL_RC_ACT; PX4's default 0 is Position mode).
- After that failsafe PX4 keeps OFFBOARD as the mode the user asked for: setpoints arriving again
  put the vehicle back into OFFBOARD by themselves, with no mode request (`offboard_resume`;
  measured on PX4 SITL: back in OFFBOARD within one heartbeat of the first setpoint, after 8 s in
  the failsafe). Only a mode change (pilot, ground station, takeoff, land, disarm) cancels that.
- Disarming is refused in the air unless forced (MAVLink magic 21196).

Where the emulator still differs from real PX4 (PX4 SITL + SIH, main 02e73e3b6f; the same MAVSDK
sequence against both: benchmarks/emulator_fidelity.py, docs/BENCHMARKS.md):

- Healthy/armable ~1 s after start (PX4: 3-6 s, EKF and pre-arm checks); takeoff to 2.5 m then
  Hold in 3 s (PX4: 7-8 s, spool-up and land detector); land to disarmed 5 s (PX4: 9-12 s), and
  PX4 shows HOLD again after it disarms (the emulator stays in LAND).
- The vehicle model reaches a 1.5 m/s command in ~1 s; PX4 flew 1.17-1.27 m/s after 3 s.
- ATTITUDE_QUATERNION at the telemetry rate, 30 Hz (PX4's onboard link: 50 Hz).
- Offboard loss: the emulator switches exactly COM_OF_LOSS_T after the last setpoint; PX4 said
  "Failsafe activated" ~1.09 s after a 1 s COM_OF_LOSS_T. Without an RC link PX4 degrades
  COM_OBL_RC_ACT 0 (Position) to Return; the emulator models a vehicle with RC: Position.
- Not emulated: COM_FAIL_ACT_T (PX4's Hold before a Return/Land failsafe action), the geofence
  (GF_*), velocity limits (MPC_*_VEL_MAX clip commands on PX4), COM_OBC_LOSS_T's "mission
  computer lost" message, failsafe flags in SYS_STATUS/HEARTBEAT, and every mode not listed.
- TAKEOFF climbs to the takeoff altitude then switches to HOLD; LAND descends and disarms on
  touchdown; HOLD and the manual modes hold zero velocity.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.validation import require_int_range, require_non_negative, require_positive
from sim_harness.hil.emulated_vehicle import VehicleStateNed, VelocityCommand

FORCE_DISARM_MAGIC = 21196


class Px4Mode(enum.Enum):
    """PX4 flight modes as (main mode, sub mode) of `px4_custom_mode`."""

    MANUAL = (1, 0)
    ALTCTL = (2, 0)
    POSCTL = (3, 0)
    READY = (4, 1)
    TAKEOFF = (4, 2)
    HOLD = (4, 3)  # AUTO_LOITER
    MISSION = (4, 4)
    RTL = (4, 5)
    LAND = (4, 6)
    ACRO = (5, 0)
    OFFBOARD = (6, 0)
    STABILIZED = (7, 0)

    @property
    def custom_mode(self) -> int:
        """The HEARTBEAT custom_mode word: main << 16 | sub << 24."""
        main, sub = self.value
        return (main << 16) | (sub << 24)

    @classmethod
    def from_main_sub(cls, main: int, sub: int) -> Px4Mode | None:
        """The mode for a (main, sub) pair, or None when PX4 has no such mode.

        Only the AUTO main mode (4) has sub modes that matter here; the others match on main.
        """
        for mode in cls:
            if mode.value == (main, sub) or (main != 4 and mode.value[0] == main):
                return mode
        return None

    @classmethod
    def from_custom_mode(cls, custom_mode: int) -> Px4Mode | None:
        """Decode a HEARTBEAT custom_mode word."""
        return cls.from_main_sub((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)


class LandedState(enum.IntEnum):
    """MAV_LANDED_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class MavResult(enum.IntEnum):
    """MAV_RESULT of a COMMAND_ACK."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


@dataclass(frozen=True)
class Px4LogicConfig:
    """Timeouts (s), speeds (m/s) and altitudes (m, above home) of the emulated PX4."""

    offboard_entry_window_s: float = 0.5
    offboard_loss_timeout_s: float = 0.5  # COM_OF_LOSS_T
    offboard_loss_mode: Px4Mode = Px4Mode.POSCTL  # COM_OBL_RC_ACT 0 (PX4's default)
    offboard_resume: bool = True  # setpoints back after the loss failsafe: OFFBOARD again
    takeoff_altitude_m: float = 2.5  # MIS_TAKEOFF_ALT
    takeoff_speed_mps: float = 1.0  # MPC_TKO_SPEED
    land_speed_mps: float = 0.7  # MPC_LAND_SPEED
    in_air_altitude_m: float = 0.1  # above this the vehicle counts as flying
    mode_log_capacity: int = 1000

    def __post_init__(self) -> None:
        require_positive("px4.offboard_entry_window_s", self.offboard_entry_window_s)
        require_positive("px4.offboard_loss_timeout_s", self.offboard_loss_timeout_s)
        require_positive("px4.takeoff_altitude_m", self.takeoff_altitude_m)
        require_positive("px4.takeoff_speed_mps", self.takeoff_speed_mps)
        require_positive("px4.land_speed_mps", self.land_speed_mps)
        require_non_negative("px4.in_air_altitude_m", self.in_air_altitude_m)
        require_int_range("px4.mode_log_capacity", self.mode_log_capacity, 1)


@dataclass(frozen=True)
class ModeChange:
    """One flight-mode transition: when (s), from, to, and why."""

    t_s: float
    old: Px4Mode
    new: Px4Mode
    reason: str


class Px4Logic:
    """Flight mode, arming and offboard rules. Not thread-safe: the emulator holds its lock."""

    def __init__(self, config: Px4LogicConfig, mode: Px4Mode, armed: bool) -> None:
        self.config = config
        self.mode = mode
        self.armed = armed
        self.mode_log: deque[ModeChange] = deque(maxlen=config.mode_log_capacity)
        self._setpoint: VelocityCommand | None = None
        self._setpoint_t_s: float | None = None
        self._takeoff_target_m = config.takeoff_altitude_m
        self.offboard_intended = False  # OFFBOARD left by the loss failsafe, not by a request

    # -- inputs ------------------------------------------------------------------------------

    def on_setpoint(self, t_s: float, command: VelocityCommand) -> None:
        """An offboard setpoint arrived."""
        self._setpoint = command
        self._setpoint_t_s = t_s

    def setpoint_fresh(self, t_s: float, window_s: float) -> bool:
        """Whether a setpoint arrived within the last `window_s` seconds."""
        return self._setpoint_t_s is not None and t_s - self._setpoint_t_s <= window_s

    def set_mode(self, t_s: float, mode: Px4Mode, reason: str) -> MavResult:
        """Switch mode (a DO_SET_MODE or the pilot's switch); OFFBOARD needs fresh setpoints."""
        if mode is Px4Mode.OFFBOARD and not self.setpoint_fresh(
            t_s, self.config.offboard_entry_window_s
        ):
            return MavResult.DENIED
        if mode in (Px4Mode.TAKEOFF, Px4Mode.LAND) and not self.armed:
            return MavResult.DENIED
        self.offboard_intended = False
        self._switch(t_s, mode, reason)
        return MavResult.ACCEPTED

    def arm(self, t_s: float, arm: bool, force: bool, state: VehicleStateNed) -> MavResult:
        """MAV_CMD_COMPONENT_ARM_DISARM; repeats of the same request are accepted."""
        if arm == self.armed:
            return MavResult.ACCEPTED
        if not arm and self.in_air(state) and not force:
            return MavResult.DENIED
        self.armed = arm
        self.offboard_intended = False
        return MavResult.ACCEPTED

    def takeoff(self, t_s: float, altitude_m: float | None) -> MavResult:
        """MAV_CMD_NAV_TAKEOFF: climb to `altitude_m` above home (None: the default)."""
        if not self.armed:
            return MavResult.DENIED
        if altitude_m is not None and math.isfinite(altitude_m) and altitude_m > 0.0:
            self._takeoff_target_m = altitude_m
        else:
            self._takeoff_target_m = self.config.takeoff_altitude_m
        self.offboard_intended = False
        self._switch(t_s, Px4Mode.TAKEOFF, "takeoff command")
        return MavResult.ACCEPTED

    def land(self, t_s: float) -> MavResult:
        """MAV_CMD_NAV_LAND at the current position."""
        return self.set_mode(t_s, Px4Mode.LAND, "land command")

    # -- outputs -----------------------------------------------------------------------------

    def in_air(self, state: VehicleStateNed) -> bool:
        """Whether the vehicle is off the ground."""
        return state.altitude_m > self.config.in_air_altitude_m

    def landed_state(self, state: VehicleStateNed) -> LandedState:
        """MAV_LANDED_STATE for EXTENDED_SYS_STATE."""
        if not self.in_air(state):
            return LandedState.TAKEOFF if self.mode is Px4Mode.TAKEOFF else LandedState.ON_GROUND
        if self.mode is Px4Mode.LAND:
            return LandedState.LANDING
        return LandedState.IN_AIR

    def update(self, t_s: float, state: VehicleStateNed) -> VelocityCommand | None:
        """Apply timeouts and mode completions, then return what the vehicle should fly.

        None means motors off (disarmed).
        """
        cfg = self.config
        if self.mode is Px4Mode.OFFBOARD and not self.setpoint_fresh(
            t_s, cfg.offboard_loss_timeout_s
        ):
            self._switch(t_s, cfg.offboard_loss_mode, "offboard setpoints lost")
            self.offboard_intended = cfg.offboard_resume
        elif self.offboard_intended and self.setpoint_fresh(t_s, cfg.offboard_entry_window_s):
            self.offboard_intended = False
            self._switch(t_s, Px4Mode.OFFBOARD, "offboard setpoints regained")
        if not self.armed:
            return None
        hold = VelocityCommand(vel_ned_mps=np.zeros(3))
        if self.mode is Px4Mode.OFFBOARD and self._setpoint is not None:
            return self._setpoint
        if self.mode is Px4Mode.TAKEOFF:
            if state.altitude_m >= self._takeoff_target_m:
                self._switch(t_s, Px4Mode.HOLD, "takeoff altitude reached")
                return hold
            return VelocityCommand(vel_ned_mps=np.array([0.0, 0.0, -cfg.takeoff_speed_mps]))
        if self.mode is Px4Mode.LAND:
            if state.altitude_m <= 0.0 and state.vel_ned_mps[2] >= -1e-3:
                self.armed = False  # auto-disarm on touchdown
                return None
            return VelocityCommand(vel_ned_mps=np.array([0.0, 0.0, cfg.land_speed_mps]))
        return hold

    def _switch(self, t_s: float, mode: Px4Mode, reason: str) -> None:
        if mode is not self.mode:
            self.mode_log.append(ModeChange(t_s, self.mode, mode, reason))
            self.mode = mode
