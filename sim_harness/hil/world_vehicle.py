"""One drone of the shared simulated world, seen by its PX4 emulator as its own vehicle.

The emulator thread calls `step(dt_s, command)` at its own rate: the command is kept as the
drone's latest (what PX4's velocity controller would track) and the state returned is the one
the world loop last published. The world loop (`hil.swarm`) owns the physics: it reads every
drone's latest command, steps all vehicles together and publishes each drone's state back.

Frames: the world is ENU with its origin at the spawn centre's ground point; each drone's PX4
has its home and EKF origin on the ground under its own spawn point (as a real drone has where
it was switched on), so its local NED position is the world position minus that home, in NED.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from numpy.typing import NDArray

from companion.frames import enu_to_ned, ned_to_enu, quat_enu_flu_to_ned_frd, yaw_ned_to_enu
from sim_harness.hil.emulated_vehicle import VehicleStateNed, VelocityCommand
from sim_harness.hil.px4_messages import Home

FloatArray = NDArray[np.float64]

DEFAULT_ORIGIN = Home(47.397742, 8.545594, 488.0)  # the world origin's geodetic position
FALL_SPEED_MPS = 3.0  # descent with the motors off (disarmed in the air)


def home_of(origin: Home, home_world_enu: FloatArray) -> Home:
    """Geodetic position of a point `home_world_enu` (m, ENU) from the world origin."""
    return Home(*origin.to_global(enu_to_ned(home_world_enu)))


def states_ned(
    pos_world_enu: FloatArray,
    vel_world_enu: FloatArray,
    q_world_body: FloatArray,
    homes: FloatArray,
) -> list[VehicleStateNed]:
    """Every drone's state as its own PX4 sees it (local NED from its home), vectorized.

    (N, 3) positions and velocities, (N, 4) attitudes world ENU <- body FLU, (N, 3) homes (ENU).
    """
    pos_ned = enu_to_ned(pos_world_enu - homes)
    vel_ned = enu_to_ned(vel_world_enu)
    q_ned = quat_enu_flu_to_ned_frd(q_world_body)
    return [VehicleStateNed(p, v, q) for p, v, q in zip(pos_ned, vel_ned, q_ned, strict=True)]


class WorldVehicle:
    """`VehicleBackend` of one drone in the shared world (thread-safe)."""

    def __init__(self, home_world_enu: FloatArray, state: VehicleStateNed) -> None:
        self.home_world_enu = np.asarray(home_world_enu, dtype=np.float64).copy()
        self._lock = threading.Lock()
        self._command: VelocityCommand | None = VelocityCommand(vel_ned_mps=np.zeros(3))
        self._state = state

    # -- the emulator's side -------------------------------------------------------------

    def state(self) -> VehicleStateNed:
        with self._lock:
            return self._state

    def step(self, dt_s: float, command: VelocityCommand | None) -> VehicleStateNed:
        """Keep `command` as the drone's latest; the physics runs in the world loop."""
        with self._lock:
            self._command = command
            return self._state

    # -- the world loop's side -----------------------------------------------------------

    def velocity_setpoint_enu(self) -> FloatArray:
        """What the vehicle should fly now (world ENU, m/s): PX4's command, or a motor-off fall."""
        with self._lock:
            command = self._command
        if command is None:
            return np.array([0.0, 0.0, -FALL_SPEED_MPS])
        vel = np.asarray(command.vel_ned_mps, dtype=np.float64)
        if vel.shape != (3,) or not np.all(np.isfinite(vel)):
            return np.zeros(3)
        return ned_to_enu(vel)

    def yaw_setpoint_enu(self) -> float:
        """PX4's yaw setpoint (ENU rad), NaN when none (disarmed, no yaw in the setpoint)."""
        with self._lock:
            command = self._command
        if command is None or command.yaw_ned_rad is None or not math.isfinite(command.yaw_ned_rad):
            return math.nan
        return float(yaw_ned_to_enu(command.yaw_ned_rad))

    def publish(self, state: VehicleStateNed) -> None:
        """The world loop's latest state of this drone (see `states_ned`)."""
        with self._lock:
            self._state = state
