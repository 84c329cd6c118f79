"""The drone's recent attitude, to rotate a policy output with the attitude at image capture time.

The autopilot reports its attitude as PX4's NED <- FRD quaternion, stamped with the receive time
on the host monotonic clock (the clock the camera links stamp frames with). `AttitudeHistory`
keeps the last `capacity` samples as received; `at(t_s)` returns the one nearest to `t_s`,
converted to the control law's world-ENU <- body-FLU quaternion, or None when none is within
`max_gap_s` (no or stale telemetry: the daemon then hovers).

`pose_enu` converts the latest position and heading for the control law.
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
    """Bounded history of (receive time s, q_ned_frd (4,)) samples, oldest first."""

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
        self._samples.append((t_s, q))
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
        return frames.quat_ned_frd_to_enu_flu(best[1])


def pose_enu(
    telemetry: AutopilotTelemetry, now_s: float, max_age_s: float
) -> tuple[FloatArray, float]:
    """(position ENU (3,) m, yaw ENU rad) from the latest telemetry, for the control law.

    Values older than `max_age_s` (or missing) are NaN, which the control law turns into a hover.
    Plain float arithmetic (this runs on every tick, between the image and the setpoint).
    """
    pos, q = telemetry.position_ned_m, telemetry.q_ned_frd_wxyz
    pos_enu = NAN3
    if pos is not None and now_s - pos.t_s <= max_age_s:
        north, east, down = (float(v) for v in pos.value)
        pos_enu = np.array([east, north, -down])
    if q is None or now_s - q.t_s > max_age_s:
        return pos_enu, math.nan
    w, x, y, z = (float(v) for v in q.value)
    yaw_ned = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))  # nan stays nan
    return pos_enu, float(frames.wrap_angle(math.pi / 2 - yaw_ned))
