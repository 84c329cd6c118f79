"""One drone of the real-PX4 HIL swarm (`Px4Drone`) and what the harness asks of PX4's GCS link."""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GlobalPosition
from companion.param_check import BOARD_ONLY, read_params_file
from sim_harness.hil.drone import LOOPBACK_TCP, DroneSetup, free_tcp_port
from sim_harness.hil.px4_params import SHIPPED_PARAMS
from sim_harness.hil.px4_pose_station import PoseStation
from sim_harness.hil.px4_sitl import RunningPx4
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN

POSE_RATE_HZ = 50.0  # LOCAL_POSITION_NED and ATTITUDE_QUATERNION on the GCS link
TARGET_RATE_HZ = 10.0  # POSITION_TARGET_LOCAL_NED: what PX4 flies (the flight log's setpoint)
TAKEOFF_TIMEOUT_S = 60.0
HEARTBEAT_SLACK_S = 2.5  # PX4 sends HEARTBEAT at 1 Hz on the GCS link
IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])
ORIGIN = GlobalPosition(DEFAULT_ORIGIN.lat_deg, DEFAULT_ORIGIN.lon_deg, DEFAULT_ORIGIN.alt_amsl_m)
# The GCS link's streams: SIH's vehicle at the pose rate, PX4's estimate and target for the log,
# the rest PX4 streams at 50 Hz slowed down (parsing them costs the harness's interpreter).
STREAMS_HZ = {
    mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: POSE_RATE_HZ,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 25.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION: 25.0,
    mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: TARGET_RATE_HZ,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET: 1.0,
    mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 1.0,
}


@dataclass
class Px4Drone:
    """One drone: its PX4 instance, the harness's ground station on it, and its daemon."""

    setup: DroneSetup
    px4: RunningPx4
    gcs: PoseStation
    faces: dict[str, dict[str, str]]
    migration_point_global: tuple[float, float, float] | None
    telemetry_endpoint: str = field(default_factory=lambda: f"{LOOPBACK_TCP}:{free_tcp_port()}")
    process: subprocess.Popen[bytes] | None = None
    exit_code: int | None = None
    takeoff_s: float | None = None

    @property
    def config_path(self) -> Path:
        return self.setup.folder / "companion.toml"

    @property
    def flights_dir(self) -> Path:
        return self.setup.folder / "flights"

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def daemon_log_tail(self, lines: int = 5) -> str:
        path = self.setup.folder / "daemon.log"
        text = path.read_text(errors="replace") if path.exists() else ""
        return "\n".join(text.splitlines()[-lines:])


def shipped_params() -> dict[str, float]:
    """The shipped parameter file as PX4 start-up parameters (names SITL has: not board-only)."""
    return {r.name: r.value for r in read_params_file(SHIPPED_PARAMS) if r.name not in BOARD_ONLY}
