"""The MAVLink messages the adapter reads and writes itself (MAVSDK's MavlinkDirect), as pure code.

MAVSDK's telemetry plugin turns HEARTBEAT into a flight mode but hides what the daemon needs for
safe engagement; these messages carry it (PX4 behaviour checked against PX4 SITL, see FACTS.md):

- HEARTBEAT (1 Hz): `system_status` is MAV_STATE_CRITICAL (5) or EMERGENCY (6) while a PX4
  failsafe is active; its stamp tells whether the autopilot's heartbeat is still arriving.
- CURRENT_MODE (PX4 >= 1.15): sent within ~0.1 s of every mode change (the heartbeat shows it up to
  1 s later) and carries `intended_custom_mode`, the mode the user last asked for. After an
  offboard-loss failsafe it stays OFFBOARD: PX4 then goes back to OFFBOARD by itself as soon as
  setpoints arrive again, so a restarted companion would take the vehicle back with its first
  setpoint. A DO_SET_MODE to the current mode makes that mode the intended one and cancels it.
- SET_POSITION_TARGET_LOCAL_NED: the setpoints streamed before the pilot's switch to OFFBOARD
  ("operator" engagement), sent one per tick with no re-sending behind the daemon's back.

PX4's custom mode word: main mode in bits 16-23, sub mode in bits 24-31.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from companion.autopilot_types import FlightMode

MAV_STATE_CRITICAL = 5
MAV_STATE_EMERGENCY = 6
MAV_CMD_DO_SET_MODE = 176
MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_FRAME_LOCAL_NED = 1
AUTOPILOT_COMPONENT_ID = 1
# SET_POSITION_TARGET type mask: ignore position (1|2|4), acceleration (64|128|256), yaw rate
# (2048): velocity and yaw are used.
VELOCITY_YAW_TYPE_MASK = 1 | 2 | 4 | 64 | 128 | 256 | 2048

_MAIN_MODES = {
    1: FlightMode.MANUAL,
    2: FlightMode.ALTCTL,
    3: FlightMode.POSCTL,
    5: FlightMode.ACRO,
    6: FlightMode.OFFBOARD,
    7: FlightMode.STABILIZED,
    8: FlightMode.RATTITUDE,
}
_AUTO_SUB_MODES = {
    1: FlightMode.READY,
    2: FlightMode.TAKEOFF,
    3: FlightMode.HOLD,
    4: FlightMode.MISSION,
    5: FlightMode.RETURN_TO_LAUNCH,
    6: FlightMode.LAND,
    8: FlightMode.FOLLOW_ME,
}
_AUTO_MAIN = 4


def flight_mode_of(custom_mode: int) -> FlightMode:
    """The flight mode of a PX4 custom mode word (UNKNOWN for anything else)."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    if main == _AUTO_MAIN:
        return _AUTO_SUB_MODES.get(sub, FlightMode.UNKNOWN)
    return _MAIN_MODES.get(main, FlightMode.UNKNOWN)


@dataclass(frozen=True)
class VehicleStatus:
    """What the autopilot's HEARTBEAT says beyond the mode."""

    custom_mode: int
    system_status: int  # MAV_STATE

    @property
    def mode(self) -> FlightMode:
        return flight_mode_of(self.custom_mode)

    @property
    def failsafe(self) -> bool:
        """PX4 reports CRITICAL or EMERGENCY while a failsafe is active."""
        return self.system_status in (MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY)


@dataclass(frozen=True)
class ModeReport:
    """CURRENT_MODE: the mode flown and the mode the user last asked for (custom mode words)."""

    custom_mode: int
    intended_custom_mode: int

    @property
    def mode(self) -> FlightMode:
        return flight_mode_of(self.custom_mode)

    @property
    def intended(self) -> FlightMode:
        return flight_mode_of(self.intended_custom_mode)

    @property
    def resumes_offboard(self) -> bool:
        """Out of OFFBOARD by a failsafe while OFFBOARD is still intended: setpoints resume it."""
        return self.intended is FlightMode.OFFBOARD and self.mode is not FlightMode.OFFBOARD


def parse_fields(fields_json: str) -> dict[str, Any]:
    """A MavlinkDirect message's fields (empty on malformed JSON: the message is ignored)."""
    try:
        fields = json.loads(fields_json)
    except (TypeError, ValueError):
        return {}
    return fields if isinstance(fields, dict) else {}


def vehicle_status(fields: dict[str, Any]) -> VehicleStatus | None:
    """HEARTBEAT fields -> VehicleStatus (None when a field is missing)."""
    try:
        return VehicleStatus(int(fields["custom_mode"]), int(fields["system_status"]))
    except (KeyError, TypeError, ValueError):
        return None


def mode_report(fields: dict[str, Any]) -> ModeReport | None:
    """CURRENT_MODE fields -> ModeReport (None when a field is missing)."""
    try:
        return ModeReport(int(fields["custom_mode"]), int(fields["intended_custom_mode"]))
    except (KeyError, TypeError, ValueError):
        return None


def set_mode_fields(target_system: int, custom_mode: int) -> dict[str, Any]:
    """COMMAND_LONG fields of a DO_SET_MODE to `custom_mode` (PX4's main and sub mode)."""
    return {
        "target_system": target_system,
        "target_component": AUTOPILOT_COMPONENT_ID,
        "command": MAV_CMD_DO_SET_MODE,
        "confirmation": 0,
        "param1": MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
        "param2": (custom_mode >> 16) & 0xFF,
        "param3": (custom_mode >> 24) & 0xFF,
        "param4": 0,
        "param5": 0,
        "param6": 0,
        "param7": 0,
    }


def velocity_setpoint_fields(
    target_system: int,
    time_boot_ms: int,
    vel_ned_mps: tuple[float, float, float],
    yaw_ned_rad: float,
) -> dict[str, Any]:
    """SET_POSITION_TARGET_LOCAL_NED fields: NED velocity (m/s) and NED yaw (rad)."""
    north, east, down = vel_ned_mps
    if not all(math.isfinite(v) for v in (north, east, down, yaw_ned_rad)):
        raise ValueError(f"setpoint must be finite, got {vel_ned_mps!r}, {yaw_ned_rad!r}")
    return {
        "time_boot_ms": time_boot_ms & 0xFFFFFFFF,
        "target_system": target_system,
        "target_component": AUTOPILOT_COMPONENT_ID,
        "coordinate_frame": MAV_FRAME_LOCAL_NED,
        "type_mask": VELOCITY_YAW_TYPE_MASK,
        "x": 0.0,
        "y": 0.0,
        "z": 0.0,
        "vx": north,
        "vy": east,
        "vz": down,
        "afx": 0.0,
        "afy": 0.0,
        "afz": 0.0,
        "yaw": yaw_ned_rad,
        "yaw_rate": 0.0,
    }
