"""How PX4 answers COMMAND_LONG / COMMAND_INT: the MAV_RESULT, and any message that follows the ACK.

Handled: ARM_DISARM (400, force-disarm magic in param2), DO_SET_MODE (176, PX4 main/sub mode in
params 2 and 3), NAV_TAKEOFF (22, AMSL altitude in param7, NaN: the default), NAV_LAND (21),
REQUEST_MESSAGE (512) for AUTOPILOT_VERSION and HOME_POSITION, SET_MESSAGE_INTERVAL (511,
accepted, rates unchanged), REQUEST_AUTOPILOT_CAPABILITIES (520). Anything else: UNSUPPORTED, so
MAVSDK stops retrying at once. Repeats (MAVSDK retries without an ACK) get the same answer.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as mavlink

from sim_harness.hil import px4_messages as msgs
from sim_harness.hil.emulated_vehicle import VehicleStateNed
from sim_harness.hil.px4_logic import FORCE_DISARM_MAGIC, MavResult, Px4Logic, Px4Mode

MSG_AUTOPILOT_VERSION = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
MSG_HOME_POSITION = mavlink.MAVLINK_MSG_ID_HOME_POSITION


def param_as_int(param: float) -> int:
    """A MAVLink float parameter as an integer; NaN ("unset") is 0."""
    return round(param) if math.isfinite(param) else 0


def command_params(msg: mavlink.MAVLink_message) -> tuple[float, ...]:
    """The seven parameters of a COMMAND_LONG, or of a COMMAND_INT (x, y, z as params 5-7)."""
    if msg.get_type() == "COMMAND_LONG":
        return tuple(float(getattr(msg, f"param{i}")) for i in range(1, 8))
    raw = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y, msg.z)
    return tuple(float(p) for p in raw)


def apply_command(
    logic: Px4Logic,
    state: VehicleStateNed,
    command: int,
    params: tuple[float, ...],
    t_s: float,
    home: msgs.Home,
) -> MavResult:
    """The result PX4 would give; updates `logic` when the command is accepted."""
    if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
        force = param_as_int(params[1]) == FORCE_DISARM_MAGIC
        return logic.arm(t_s, params[0] > 0.5, force, state)
    if command == mavlink.MAV_CMD_DO_SET_MODE:
        if not param_as_int(params[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MavResult.UNSUPPORTED
        mode = Px4Mode.from_main_sub(param_as_int(params[1]), param_as_int(params[2]))
        if mode is None:
            return MavResult.UNSUPPORTED
        return logic.set_mode(t_s, mode, "DO_SET_MODE")
    if command == mavlink.MAV_CMD_NAV_TAKEOFF:
        altitude_m = params[6] - home.alt_amsl_m
        return logic.takeoff(t_s, altitude_m if math.isfinite(altitude_m) else None)
    if command == mavlink.MAV_CMD_NAV_LAND:
        return logic.land(t_s)
    if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
        known = (MSG_AUTOPILOT_VERSION, MSG_HOME_POSITION)
        return MavResult.ACCEPTED if param_as_int(params[0]) in known else MavResult.UNSUPPORTED
    if command in (
        mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
        mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
    ):
        return MavResult.ACCEPTED
    return MavResult.UNSUPPORTED


def follow_up(
    mav: mavlink.MAVLink,
    command: int,
    params: tuple[float, ...],
    result: MavResult,
    home: msgs.Home,
    uid: int,
) -> mavlink.MAVLink_message | None:
    """The message PX4 sends after the ACK (a requested message), or None."""
    if result is not MavResult.ACCEPTED:
        return None
    wanted = param_as_int(params[0]) if command == mavlink.MAV_CMD_REQUEST_MESSAGE else None
    if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
        wanted = MSG_AUTOPILOT_VERSION
    if wanted == MSG_AUTOPILOT_VERSION:
        return msgs.autopilot_version(mav, uid)
    if wanted == MSG_HOME_POSITION:
        return msgs.home_position(mav, home)
    return None
