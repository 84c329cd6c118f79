"""The harness's ground station on a real PX4's GCS link, keeping the poses the world needs:
PX4's attitude estimate and SIH's simulated vehicle (the truth the drone is drawn at)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from companion.geo import GlobalPosition
from sim_harness.hil.px4_gcs import GroundStation

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TruthSample:
    """HIL_STATE_QUATERNION: SIH's simulated vehicle (receive time; WGS-84, NED m/s, NED<-FRD)."""

    t_s: float
    position: GlobalPosition
    vel_ned_mps: FloatArray
    q_ned_frd: FloatArray


class PoseStation(GroundStation):
    """A ground station that also keeps PX4's latest ATTITUDE_QUATERNION (NED <- FRD, the
    estimate) and HIL_STATE_QUATERNION (SIH's simulated vehicle, the truth)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.attitude: tuple[float, FloatArray] | None = None  # receive time, q (w, x, y, z)
        self.truth: TruthSample | None = None

    def _on_message(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "ATTITUDE_QUATERNION":
            self.attitude = (now, np.array([msg.q1, msg.q2, msg.q3, msg.q4], dtype=np.float64))
        elif kind == "HIL_STATE_QUATERNION":
            self.truth = TruthSample(
                now,
                GlobalPosition(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3),
                np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64) * 0.01,
                np.asarray(msg.attitude_quaternion, dtype=np.float64),
            )
        else:
            super()._on_message(msg, now)

    def stream(self, message_id: int, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL on this link (PX4's GCS link streams at its normal-mode rates)."""
        self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id, 1e6 / rate_hz)
