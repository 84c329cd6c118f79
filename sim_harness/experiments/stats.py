"""The numbers of a suite: one table row per experiment and controller, and the timings.

Per experiment and controller, over its runs (seeds):

- collision-free runs: no pair ever under the 1 m threshold (`summary["collision_free"]`);
- lowest d_min and highest d_max over all runs and steps; mean order parameter (mean of the runs'
  means);
- arrivals and the median arrival time; its ratio CNN / teacher (same seeds; a run that did not
  arrive counts as never arriving, so the median is infinite when half or more did not arrive);
- runs where the flock split (d_max >= r_max at some step) and, for experiments that expect an
  arrival, runs that stalled (no arrival by the time limit);
- the median of the runs' closest pairs (the lowest alone hides how close the rest came);
- centroid progress: how far the flock's centroid moved towards the goal that ends the run (the
  majority's, with opposing goals), median over the runs.

The bar is `sim_harness.experiments.bar`.
"""

from __future__ import annotations

import math
import statistics
from typing import Any

import numpy as np

from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.suites import EXPERIMENTS


def median_arrival(records: list[RunRecord]) -> float | None:
    """Median arrival time in s, non-arrivals counted as infinite; None without runs."""
    if not records:
        return None
    times = [r.summary["arrival_time_s"] if r.summary["arrived"] else math.inf for r in records]
    return float(statistics.median(times))


def _extreme(records: list[RunRecord], key: str, pick: Any) -> float | None:
    values = [r.summary[key] for r in records if r.summary[key] is not None]
    return float(pick(values)) if values else None


def _median_of(records: list[RunRecord], key: str) -> float | None:
    values = [r.summary[key] for r in records if r.summary.get(key) is not None]
    return float(statistics.median(values)) if values else None


def table_row(
    records: list[RunRecord], teacher: list[RunRecord], expects_arrival: bool
) -> dict[str, Any]:
    """The aggregate of one experiment and controller (see the module docstring)."""
    orders = [r.summary["order_mean"] for r in records if r.summary["order_mean"] is not None]
    median = median_arrival(records)
    teacher_median = median_arrival(teacher)
    ratio = None
    if median is not None and teacher_median not in (None, 0.0) and math.isfinite(median):
        assert teacher_median is not None
        ratio = median / teacher_median if math.isfinite(teacher_median) else None
    arrived = sum(r.summary["arrived"] for r in records)
    return {
        "runs": len(records),
        "collision_free_runs": sum(r.summary["collision_free"] for r in records),
        "contact_runs": sum(r.summary["physical_contacts"] > 0 for r in records),
        "d_min_lowest_m": _extreme(records, "d_min_m", min),
        "d_max_highest_m": _extreme(records, "d_max_m", max),
        "order_mean": float(np.mean(orders)) if orders else None,
        "arrived_runs": arrived,
        "arrival_median_s": median if median is not None and math.isfinite(median) else None,
        "arrival_ratio_to_teacher": ratio,
        "split_runs": sum(r.summary["flock_split"] for r in records),
        "d_min_median_m": _median_of(records, "d_min_m"),
        "centroid_progress_median_m": _median_of(records, "centroid_progress_m"),
        "stalled_runs": len(records) - arrived if expects_arrival else None,
    }


def experiment_table(result: SuiteResult, experiment: str) -> dict[str, dict[str, Any]]:
    """{controller: table row} for one experiment; the teacher's ratio is 1 by definition."""
    teacher = result.records(experiment, "teacher")
    expects = EXPERIMENTS[experiment].expects_arrival
    controllers = dict.fromkeys(r.controller for r in result.runs if r.experiment == experiment)
    return {c: table_row(result.records(experiment, c), teacher, expects) for c in controllers}


def timing_row(records: list[RunRecord]) -> dict[str, Any]:
    """Mean wall time per control step of each stage (ms) and the real-time factor, pooled."""
    steps = sum(r.log.n_steps - 1 for r in records)
    simulated = sum(float(r.log.time_s[-1]) for r in records)
    wall = sum(r.log.wall_time_s for r in records)
    row: dict[str, Any] = {"flights": len(records), "control_steps": steps}
    for stage in ("render", "inference", "control", "physics"):
        total = sum(r.log.stage_time_s.get(stage, 0.0) for r in records)
        row[f"{stage}_ms_per_step"] = 1e3 * total / steps if steps else None
    row["wall_s"] = wall
    row["real_time_factor"] = simulated / wall if wall > 0 else None
    return row
