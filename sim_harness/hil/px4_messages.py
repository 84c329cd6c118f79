"""MAVLink messages as PX4 sends them, built from the emulated vehicle's state; setpoint decoding.

Every builder takes the pymavlink `MAVLink` encoder and returns a message object (not yet packed).
Units follow the MAVLink spec: angles in rad unless the field says otherwise, GLOBAL_POSITION_INT
in 1e-7 deg / mm / cm/s / cdeg, HOME_POSITION in 1e-7 deg / mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pymavlink.dialects.v20 import common as mavlink
from pymavlink.dialects.v20 import development

from companion.frames import euler_zyx_from_quat
from sim_harness.hil.emulated_vehicle import VehicleStateNed, VelocityCommand
from sim_harness.hil.px4_logic import LandedState, Px4Mode

EARTH_RADIUS_M = 6_378_137.0
# PX4 v1.15.0, FIRMWARE_VERSION_TYPE_OFFICIAL.
PX4_FLIGHT_SW_VERSION = (1 << 24) | (15 << 16) | (0 << 8) | 255

FRAME_LOCAL_NED = mavlink.MAV_FRAME_LOCAL_NED  # 1
FRAME_BODY_NED = mavlink.MAV_FRAME_BODY_NED  # 8

_TYPEMASK_VEL_IGNORE = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
)

# Sensors an autopilot with GPS and a healthy estimator reports present, enabled and healthy.
_SENSORS_OK = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mavlink.MAV_SYS_STATUS_AHRS
    | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)

_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
)


@dataclass(frozen=True)
class Home:
    """Where local NED (0, 0, 0), PX4's EKF origin, is on the globe: degrees and metres above
    mean sea level; and where the home PX4 reports lies in that frame (NED, m): at the origin
    by default, but real PX4 can start its origin off the home (0.74 m above it seen in SITL on
    a loaded machine). The emulated vehicle's ground stays the origin's plane."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    local_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_global(self, pos_ned_m: np.ndarray) -> tuple[float, float, float]:
        """(lat deg, lon deg, alt AMSL m) of a local NED position (flat earth, fine for km)."""
        north, east, down = (float(c) for c in pos_ned_m)
        lat = self.lat_deg + math.degrees(north / EARTH_RADIUS_M)
        lon = self.lon_deg + math.degrees(
            east / (EARTH_RADIUS_M * math.cos(math.radians(self.lat_deg)))
        )
        return lat, lon, self.alt_amsl_m - down


def heartbeat(
    mav: mavlink.MAVLink, mode: Px4Mode, armed: bool, in_air: bool, failsafe: bool = False
) -> mavlink.MAVLink_message:
    """PX4's HEARTBEAT: quadrotor, custom mode, SAFETY_ARMED while armed, CRITICAL in failsafe."""
    base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    status = mavlink.MAV_STATE_ACTIVE if armed or in_air else mavlink.MAV_STATE_STANDBY
    if failsafe:
        status = mavlink.MAV_STATE_CRITICAL
    return mav.heartbeat_encode(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base_mode, mode.custom_mode, status
    )


def current_mode(mav: mavlink.MAVLink, mode: Px4Mode, intended: Px4Mode) -> mavlink.MAVLink_message:
    """PX4's CURRENT_MODE (>= 1.15): the mode flown and the one the user last asked for.

    PX4 sends it within ~0.1 s of a change and about once a second otherwise (measured on SITL).
    """
    del mav  # CURRENT_MODE is in MAVLink's development dialect, not in common
    return development.MAVLink_current_mode_message(0, mode.custom_mode, intended.custom_mode)


def local_position(
    mav: mavlink.MAVLink, time_boot_ms: int, state: VehicleStateNed
) -> mavlink.MAVLink_message:
    """LOCAL_POSITION_NED (m, m/s)."""
    x, y, z = (float(c) for c in state.pos_ned_m)
    vx, vy, vz = (float(c) for c in state.vel_ned_mps)
    return mav.local_position_ned_encode(time_boot_ms, x, y, z, vx, vy, vz)


def attitude_quaternion(
    mav: mavlink.MAVLink, time_boot_ms: int, state: VehicleStateNed
) -> mavlink.MAVLink_message:
    """ATTITUDE_QUATERNION: NED <- FRD, w first, body rates in rad/s."""
    w, x, y, z = (float(c) for c in state.q_ned_frd_wxyz)
    p, q, r = (float(c) for c in state.rates_frd_rad_s)
    return mav.attitude_quaternion_encode(time_boot_ms, w, x, y, z, p, q, r)


def attitude(
    mav: mavlink.MAVLink, time_boot_ms: int, state: VehicleStateNed
) -> mavlink.MAVLink_message:
    """ATTITUDE: Z-Y-X Euler angles (rad) and body rates (rad/s)."""
    roll, pitch, yaw = (float(a) for a in euler_zyx_from_quat(state.q_ned_frd_wxyz))
    p, q, r = (float(c) for c in state.rates_frd_rad_s)
    return mav.attitude_encode(time_boot_ms, roll, pitch, yaw, p, q, r)


def global_position(
    mav: mavlink.MAVLink, time_boot_ms: int, state: VehicleStateNed, home: Home
) -> mavlink.MAVLink_message:
    """GLOBAL_POSITION_INT: the position on the globe, relative_alt above the home."""
    lat, lon, alt = home.to_global(state.pos_ned_m)
    vx, vy, vz = (round(float(c) * 100.0) for c in state.vel_ned_mps)
    hdg_cdeg = round(math.degrees(state.yaw_ned_rad) * 100.0) % 36000
    return mav.global_position_int_encode(
        time_boot_ms,
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000.0),
        round((state.altitude_m + home.local_ned_m[2]) * 1000.0),
        vx,
        vy,
        vz,
        hdg_cdeg,
    )


def sys_status(mav: mavlink.MAVLink) -> mavlink.MAVLink_message:
    """SYS_STATUS with every sensor healthy and the pre-arm check passed; 16.2 V, 80 %."""
    return mav.sys_status_encode(
        _SENSORS_OK, _SENSORS_OK, _SENSORS_OK, 200, 16_200, 500, 80, 0, 0, 0, 0, 0, 0
    )


GPS_FIX_TYPE = mavlink.GPS_FIX_TYPE_3D_FIX
GPS_SATELLITES = 12


def gps_raw_int(
    mav: mavlink.MAVLink, time_boot_ms: int, state: VehicleStateNed, home: Home
) -> mavlink.MAVLink_message:
    """GPS_RAW_INT: a 3-D fix with 12 satellites at the vehicle's position (1e-7 deg, mm)."""
    lat, lon, alt = home.to_global(state.pos_ned_m)
    speed_cm_s = round(float(np.linalg.norm(state.vel_ned_mps[:2])) * 100.0)
    return mav.gps_raw_int_encode(
        time_boot_ms * 1000,
        GPS_FIX_TYPE,
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000.0),
        80,  # eph: HDOP 0.8
        120,  # epv: VDOP 1.2
        speed_cm_s,
        65535,  # course over ground unknown
        GPS_SATELLITES,
    )


def extended_sys_state(mav: mavlink.MAVLink, landed: LandedState) -> mavlink.MAVLink_message:
    """EXTENDED_SYS_STATE: multicopter (no VTOL state) and the landed state."""
    return mav.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, int(landed))


def home_position(mav: mavlink.MAVLink, home: Home) -> mavlink.MAVLink_message:
    """HOME_POSITION: the home on the globe and in the local frame."""
    lat, lon, alt = home.to_global(np.asarray(home.local_ned_m, dtype=np.float64))
    north, east, down = home.local_ned_m
    return mav.home_position_encode(
        round(lat * 1e7),
        round(lon * 1e7),
        round(alt * 1000.0),
        north,
        east,
        down,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
    )


def autopilot_version(mav: mavlink.MAVLink, uid: int) -> mavlink.MAVLink_message:
    """AUTOPILOT_VERSION of a PX4 1.15 with the capabilities MAVSDK looks for."""
    zeros8 = [0] * 8
    return mav.autopilot_version_encode(
        _CAPABILITIES, PX4_FLIGHT_SW_VERSION, 0, 0, 0, zeros8, zeros8, zeros8, 0x26AC, 0x11, uid
    )


@dataclass(frozen=True)
class SetpointRecord:
    """One SET_POSITION_TARGET_LOCAL_NED as received (emulator clock, s; MAVLink units)."""

    t_s: float
    frame: int
    type_mask: int
    vx_mps: float
    vy_mps: float
    vz_mps: float
    yaw_rad: float
    yaw_rate_rad_s: float

    @property
    def uses_velocity(self) -> bool:
        """Whether the type mask enables all three velocity fields."""
        return self.type_mask & _TYPEMASK_VEL_IGNORE == 0

    @property
    def uses_yaw(self) -> bool:
        """Whether the type mask enables the yaw field."""
        return self.type_mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE == 0

    @property
    def uses_yaw_rate(self) -> bool:
        """Whether the type mask enables the yaw-rate field."""
        return self.type_mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE == 0


def decode_setpoint(
    t_s: float, msg: mavlink.MAVLink_set_position_target_local_ned_message, yaw_now_rad: float
) -> tuple[SetpointRecord, VelocityCommand | None]:
    """The log record of a setpoint and the command PX4 would fly (None: a frame it rejects).

    LOCAL_NED velocities are used as they are; BODY_NED velocities are rotated by the current
    heading. Setpoints without velocity (position, acceleration) fly zero velocity.
    """
    record = SetpointRecord(
        t_s=t_s,
        frame=int(msg.coordinate_frame),
        type_mask=int(msg.type_mask),
        vx_mps=float(msg.vx),
        vy_mps=float(msg.vy),
        vz_mps=float(msg.vz),
        yaw_rad=float(msg.yaw),
        yaw_rate_rad_s=float(msg.yaw_rate),
    )
    if record.frame not in (FRAME_LOCAL_NED, FRAME_BODY_NED):
        return record, None
    vel = np.array([record.vx_mps, record.vy_mps, record.vz_mps])
    if not record.uses_velocity or not np.all(np.isfinite(vel)):
        vel = np.zeros(3)
    elif record.frame == FRAME_BODY_NED:
        c, s = math.cos(yaw_now_rad), math.sin(yaw_now_rad)
        vel = np.array([c * vel[0] - s * vel[1], s * vel[0] + c * vel[1], vel[2]])
    command = VelocityCommand(
        vel_ned_mps=vel,
        yaw_ned_rad=record.yaw_rad if record.uses_yaw else None,
        yaw_rate_rad_s=record.yaw_rate_rad_s if record.uses_yaw_rate else None,
    )
    return record, command
