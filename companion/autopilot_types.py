"""The autopilot contract: what the daemon needs from PX4 (`Autopilot`), its data and its config.

Frames and units: PX4's local NED (x north, y east, z down; m, m/s), attitude as the NED <- FRD
quaternion (w, x, y, z), yaw in radians NED (0 = north, clockwise). Receive times are seconds on
the adapter's monotonic clock. The MAVSDK implementation is `companion.autopilot.MavsdkAutopilot`
(which also re-exports everything here).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.errors import ConfigError
from companion.geo import HomePosition
from companion.sections import require_bool, section_from_dict
from companion.validation import require_range

if TYPE_CHECKING:
    from companion.autopilot_mavlink import ModeReport, VehicleStatus

FloatArray = NDArray[np.float64]
T = TypeVar("T")
SECTION = "autopilot"
URL_SCHEMES = ("udpin://", "udpout://", "udp://", "tcpin://", "tcpout://", "tcp://", "serial://")
FAILSAFE_ACTIONS = ("hold", "land")


class FlightMode(enum.Enum):
    """The vehicle's flight mode as MAVSDK decodes it from the heartbeat."""

    UNKNOWN = "unknown"
    READY = "ready"
    TAKEOFF = "takeoff"
    HOLD = "hold"
    MISSION = "mission"
    RETURN_TO_LAUNCH = "return_to_launch"
    LAND = "land"
    OFFBOARD = "offboard"
    FOLLOW_ME = "follow_me"
    MANUAL = "manual"
    ALTCTL = "altctl"
    POSCTL = "posctl"
    ACRO = "acro"
    STABILIZED = "stabilized"
    RATTITUDE = "rattitude"


class OffboardState(enum.Enum):
    """INACTIVE: not commanding. READY: streaming hover setpoints so that the pilot or ground
    station can switch to OFFBOARD ("operator" engagement; the switch makes it ACTIVE).
    ACTIVE: commanding, vehicle seen in OFFBOARD. LOST: it left."""

    INACTIVE = "inactive"
    ACTIVE = "active"
    LOST = "lost"
    READY = "ready"


@dataclass(frozen=True)
class Stamped(Generic[T]):
    """A value and when it was received (s, the adapter's monotonic clock)."""

    value: T
    t_s: float


class GpsFixType(enum.Enum):
    """GPS fix type as MAVSDK decodes it from GPS_RAW_INT."""

    NO_GPS = "no_gps"
    NO_FIX = "no_fix"
    FIX_2D = "fix_2d"
    FIX_3D = "fix_3d"
    FIX_DGPS = "fix_dgps"
    RTK_FLOAT = "rtk_float"
    RTK_FIXED = "rtk_fixed"


@dataclass(frozen=True)
class BatteryState:
    """The flight battery as PX4 reports it (SYS_STATUS / BATTERY_STATUS); None: not measured."""

    remaining_pct: float | None  # state of charge, 0..100 %
    voltage_v: float | None  # pack voltage, V


@dataclass(frozen=True)
class GpsState:
    """The GPS receiver's fix (GPS_RAW_INT)."""

    fix_type: GpsFixType
    satellites: int  # satellites used


@dataclass(frozen=True)
class AutopilotTelemetry:
    """Latest telemetry, each value with its receive time; None until the first one arrives.

    Position, velocity and attitude arrive at the autopilot's stream rates, flight mode and armed
    with every heartbeat (1 Hz on PX4), in_air only when it changes: judge the link's freshness
    by the position stamp, not by in_air's.
    """

    position_ned_m: Stamped[FloatArray] | None = None  # (3,)
    velocity_ned_mps: Stamped[FloatArray] | None = None  # (3,)
    q_ned_frd_wxyz: Stamped[FloatArray] | None = None  # (4,), body FRD -> NED
    flight_mode: Stamped[FlightMode] | None = None
    armed: Stamped[bool] | None = None
    in_air: Stamped[bool] | None = None
    home: Stamped[HomePosition] | None = None  # PX4's HOME_POSITION (set on arming)
    battery: Stamped[BatteryState] | None = None  # at PX4's SYS_STATUS/BATTERY_STATUS rate
    gps: Stamped[GpsState] | None = None  # at PX4's GPS_RAW_INT rate
    status: Stamped[VehicleStatus] | None = None  # every autopilot HEARTBEAT: failsafe, liveness
    mode_report: Stamped[ModeReport] | None = None  # CURRENT_MODE: the intended mode (PX4 >= 1.15)


@dataclass(frozen=True)
class AutopilotConfig:
    """The `[autopilot]` section. Times in seconds.

    `arm` / `takeoff`: `connect()` also arms (and takes off to PX4's MIS_TAKEOFF_ALT).
    `offboard_prestream_s`: how long the first setpoint streams before OFFBOARD is requested
    (PX4 wants > 1 s). `setpoint_rate_hz`: the rate the daemon sends setpoints at (PX4 needs
    > 2 Hz; MAVSDK re-sends the last one at 20 Hz regardless). `failsafe_action`: what
    `failsafe()` (and `close()` while commanding) switches to. `heartbeat_timeout_s`: no
    HEARTBEAT from the autopilot for this long means the link to it (or PX4 itself) is gone: the
    flight mode is unknown, so the daemon hovers and then runs its failsafe (PX4 sends 1 Hz).
    """

    url: str = "udpin://127.0.0.1:14540"
    discovery_timeout_s: float = 10.0
    health_timeout_s: float = 30.0
    command_timeout_s: float = 2.0
    arm: bool = False
    takeoff: bool = False
    takeoff_timeout_s: float = 30.0
    offboard_prestream_s: float = 1.0
    offboard_confirm_timeout_s: float = 3.0
    failsafe_action: str = "hold"
    setpoint_rate_hz: float = 10.0
    close_timeout_s: float = 2.5
    heartbeat_timeout_s: float = 3.0

    def __post_init__(self) -> None:
        s = SECTION
        if not isinstance(self.url, str) or not self.url.startswith(URL_SCHEMES):
            raise ConfigError(
                f"{s}.url: {self.url!r} must start with one of {', '.join(URL_SCHEMES)}"
            )
        require_range(
            f"{s}.discovery_timeout_s", self.discovery_timeout_s, 0.0, 600.0, low_inclusive=False
        )
        require_range(
            f"{s}.health_timeout_s", self.health_timeout_s, 0.0, 600.0, low_inclusive=False
        )
        require_range(
            f"{s}.command_timeout_s", self.command_timeout_s, 0.0, 30.0, low_inclusive=False
        )
        require_bool(f"{s}.arm", self.arm)
        require_bool(f"{s}.takeoff", self.takeoff)
        if self.takeoff and not self.arm:
            raise ConfigError(f"{s}.takeoff: needs {s}.arm = true")
        require_range(
            f"{s}.takeoff_timeout_s", self.takeoff_timeout_s, 0.0, 300.0, low_inclusive=False
        )
        require_range(f"{s}.offboard_prestream_s", self.offboard_prestream_s, 0.0, 10.0)
        require_range(
            f"{s}.offboard_confirm_timeout_s",
            self.offboard_confirm_timeout_s,
            0.0,
            30.0,
            low_inclusive=False,
        )
        if self.failsafe_action not in FAILSAFE_ACTIONS:
            raise ConfigError(
                f"{s}.failsafe_action: {self.failsafe_action!r} must be one of "
                + ", ".join(FAILSAFE_ACTIONS)
            )
        require_range(f"{s}.setpoint_rate_hz", self.setpoint_rate_hz, 10.0, 100.0)
        require_range(f"{s}.close_timeout_s", self.close_timeout_s, 0.0, 30.0)
        require_range(
            f"{s}.heartbeat_timeout_s", self.heartbeat_timeout_s, 1.5, 60.0, low_inclusive=True
        )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AutopilotConfig:
        """From the parsed `[autopilot]` table; unknown keys are refused, naming them."""
        return section_from_dict(cls, SECTION, data)


class Autopilot(Protocol):
    """What the daemon needs from the flight controller. Every call is bounded in time."""

    async def connect(self) -> None:
        """Link, discovery, health (local position, home); then arm / take off if configured."""

    async def arm(self) -> None:
        """Arm the motors."""

    async def takeoff(self) -> None:
        """Take off and return once the climb is over (no-op when already flying)."""

    async def start_offboard(self, yaw_ned_rad: float | None = None) -> None:
        """Stream a zero-velocity setpoint, switch to OFFBOARD, return once the vehicle shows it.

        After a LOST offboard this takes the vehicle back from the pilot: call it only when the
        operator asks for it.
        """

    async def prepare_offboard(self) -> None:
        """Get ready for the pilot's switch to OFFBOARD ("operator" engagement): state READY.

        If PX4 would resume OFFBOARD by itself on the first setpoint (left by a failsafe with
        OFFBOARD still intended), re-assert the mode it is in first, so that only the pilot's or
        ground station's switch engages. Raises `AutopilotError` if that is refused.
        """

    async def stream_velocity_ned(self, vel_ned_mps: ArrayLike, yaw_ned_rad: float) -> None:
        """While READY: send one setpoint (no re-sending: stop calling and the stream stops)."""

    async def set_velocity_ned(self, vel_ned_mps: ArrayLike, yaw_ned_rad: float) -> None:
        """Command a NED velocity (3,) m/s and a NED yaw (rad) while offboard is ACTIVE."""

    async def stop_offboard(self) -> None:
        """Leave OFFBOARD to HOLD (no mode change if the pilot has already taken over)."""

    async def hold(self) -> None:
        """Switch to HOLD (position hold)."""

    async def land(self) -> None:
        """Land where the vehicle is."""

    async def failsafe(self) -> None:
        """The configured failsafe action (hold or land)."""

    def telemetry(self) -> AutopilotTelemetry:
        """The latest telemetry values with their receive times (never blocks)."""

    @property
    def offboard_state(self) -> OffboardState:
        """Whether we are commanding, and whether the vehicle is still following."""

    @property
    def offboard_lost_reason(self) -> str | None:
        """Why offboard was lost (None unless `offboard_state` is LOST)."""

    async def close(self) -> None:
        """Release the link; never hangs. Runs the failsafe first if still commanding."""
