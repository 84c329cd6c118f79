"""The drone's recent attitude, to rotate a policy output with the attitude at image capture time.

The autopilot reports its attitude as PX4's NED <- FRD quaternion, stamped with the receive time
on the host monotonic clock (the clock the camera links stamp frames with). `AttitudeHistory`
keeps the last `capacity` samples converted to the control law's world-ENU <- body-FLU quaternion;
`at(t_s)` returns the sample nearest to `t_s`, or None when none is within `max_gap_s` (no or
stale telemetry: the daemon then hovers).

`pose_enu` converts the latest position and attitude for the control law.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from companion import frames
from companion.autopilot_types import AutopilotTelemetry

FloatArray = NDArray[np.float64]
NAN3: FloatArray = np.full(3, np.nan)
NAN4: FloatArray = np.full(4, np.nan)


class AttitudeHistory:
    """Bounded history of (receive time s, q_enu_flu (4,)) samples, oldest first."""

    def __init__(self, capacity: int = 128) -> None:
        self._samples: deque[tuple[float, FloatArray]] = deque(maxlen=capacity)

    def __len__(self) -> int:
        return len(self._samples)

    def add_ned_frd(self, t_s: float, q_ned_frd_wxyz: FloatArray) -> bool:
        """Add one autopilot sample; ignored (False) if not newer than the last or not finite."""
        if self._samples and t_s <= self._samples[-1][0]:
            return False
        q = np.asarray(q_ned_frd_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
            return False
        self._samples.append((t_s, frames.quat_ned_frd_to_enu_flu(q)))
        return True

    def add_from(self, telemetry: AutopilotTelemetry) -> bool:
        """Add the telemetry's attitude if it is a new sample."""
        q = telemetry.q_ned_frd_wxyz
        return False if q is None else self.add_ned_frd(q.t_s, q.value)

    def at(self, t_s: float, max_gap_s: float) -> FloatArray | None:
        """q_enu_flu of the sample nearest to `t_s`, if within `max_gap_s` of it."""
        best: tuple[float, FloatArray] | None = None
        best_gap = math.inf
        for sample_t_s, q in reversed(self._samples):
            gap = abs(sample_t_s - t_s)
            if gap < best_gap:
                best, best_gap = (sample_t_s, q), gap
            elif sample_t_s < t_s:
                break  # older samples only get further away
        if best is None or best_gap > max_gap_s:
            return None
        return best[1]


def pose_enu(
    telemetry: AutopilotTelemetry, now_s: float, max_age_s: float
) -> tuple[FloatArray, FloatArray, float]:
    """(position ENU (3,) m, q_enu_flu (4,), yaw ENU rad) from the latest telemetry.

    Values older than `max_age_s` (or missing) are NaN, which the control law turns into a hover.
    """
    pos = telemetry.position_ned_m
    q = telemetry.q_ned_frd_wxyz
    pos_enu = NAN3 if pos is None or now_s - pos.t_s > max_age_s else frames.ned_to_enu(pos.value)
    if q is None or now_s - q.t_s > max_age_s or not np.all(np.isfinite(q.value)):
        return pos_enu, NAN4, math.nan
    q_enu_flu = frames.quat_ned_frd_to_enu_flu(q.value)
    _, _, yaw = frames.euler_zyx_from_quat(q_enu_flu)
    return pos_enu, q_enu_flu, float(yaw)
