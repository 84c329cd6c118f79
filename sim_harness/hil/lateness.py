"""The HIL harness's own timing: did the world keep up with the wall clock?

The daemons run in real time, so a harness that falls behind changes what they see (late
frames, a world that moves in jumps). Its lateness is measured, not assumed, and a run outside
the stated thresholds is marked invalid in its summary and report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sim_harness.hil.camera_side import CaptureStats


@dataclass
class Lateness:
    """The harness's own timing: is the world keeping up with the wall clock?"""

    physics_steps: int = 0
    physics_late: int = 0
    physics_max_behind_s: float = 0.0
    captures: int = 0
    captures_late: int = 0
    capture_max_late_s: float = 0.0
    render_s: list[float] = field(default_factory=list)
    frames_sent: int = 0
    frames_dropped: int = 0
    max_late_fraction: float = 0.01

    def add_cameras(self, cameras: CaptureStats) -> None:
        """The camera process's side of the timing."""
        self.captures, self.captures_late = cameras.captures, cameras.captures_late
        self.capture_max_late_s = cameras.capture_max_late_s
        self.render_s = list(cameras.render_s)
        self.frames_sent = sum(cameras.frames_sent)
        self.frames_dropped = sum(cameras.frames_dropped)

    @property
    def physics_late_fraction(self) -> float:
        return self.physics_late / max(self.physics_steps, 1)

    @property
    def captures_late_fraction(self) -> float:
        return self.captures_late / max(self.captures, 1)

    @property
    def frames_dropped_fraction(self) -> float:
        return self.frames_dropped / max(self.frames_sent + self.frames_dropped, 1)

    @property
    def valid(self) -> bool:
        worst = max(
            self.physics_late_fraction, self.captures_late_fraction, self.frames_dropped_fraction
        )
        return worst <= self.max_late_fraction

    def summary(self) -> dict[str, Any]:
        render = np.asarray(self.render_s) * 1e3 if self.render_s else np.zeros(1)
        return {
            "valid": self.valid,
            "threshold_fraction": self.max_late_fraction,
            "physics_steps": self.physics_steps,
            "physics_late": self.physics_late,
            "physics_late_fraction": round(self.physics_late_fraction, 5),
            "physics_max_behind_ms": round(self.physics_max_behind_s * 1e3, 2),
            "captures": self.captures,
            "captures_late": self.captures_late,
            "captures_late_fraction": round(self.captures_late_fraction, 5),
            "capture_max_late_ms": round(self.capture_max_late_s * 1e3, 2),
            "render_ms_p50": round(float(np.percentile(render, 50)), 3),
            "render_ms_p99": round(float(np.percentile(render, 99)), 3),
            "frames_sent": self.frames_sent,
            "frames_dropped": self.frames_dropped,
            "frames_dropped_fraction": round(self.frames_dropped_fraction, 5),
        }


class GridClock:
    """A world loop on a fixed time grid: `advance_until` runs `_run_due(now)` (the steps whose
    grid time has come, which move `next_step` on) and sleeps to the next one, until `until`."""

    next_step: float  # monotonic time of the next grid step

    def advance_until(self, until: float) -> set[tuple[int, int]]:
        """Keep the world on the wall clock until monotonic time `until`; the drone pairs that
        touched meanwhile."""
        touching: set[tuple[int, int]] = set()
        while True:
            now = time.monotonic()
            touching |= self._run_due(now)
            if now >= until:
                return touching
            time.sleep(max(0.0, min(self.next_step, until) - time.monotonic()))

    def _run_due(self, now: float) -> set[tuple[int, int]]:
        raise NotImplementedError
