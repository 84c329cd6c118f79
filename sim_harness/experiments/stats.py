"""The numbers of a suite: one table row per experiment and controller, the bar, the timings.

Per experiment and controller, over its runs (seeds):

- collision-free runs: no pair ever under the 1 m threshold (`summary["collision_free"]`);
- lowest d_min and highest d_max over all runs and steps; mean order parameter (mean of the runs'
  means);
- arrivals and the median arrival time; its ratio CNN / teacher (same seeds; a run that did not
  arrive counts as never arriving, so the median is infinite when half or more did not arrive);
- runs where the flock split (d_max >= r_max at some step) and, for experiments that expect an
  arrival, runs that stalled (no arrival by the time limit).

The bar (issue 5), on the common goal and opposing goals experiments: with the CNN, no collision in
any common-goal run, every common-goal run arrives, its median arrival time at most
`ARRIVAL_RATIO_BAR` times the teacher's, and no opposing-goals run splits.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.suites import EXPERIMENTS

ARRIVAL_RATIO_BAR = 1.3


def _median_arrival(records: list[RunRecord]) -> float | None:
    """Median arrival time in s, non-arrivals counted as infinite; None without runs."""
    if not records:
        return None
    times = [r.summary["arrival_time_s"] if r.summary["arrived"] else math.inf for r in records]
    return float(statistics.median(times))


def _extreme(records: list[RunRecord], key: str, pick: Any) -> float | None:
    values = [r.summary[key] for r in records if r.summary[key] is not None]
    return float(pick(values)) if values else None


def table_row(
    records: list[RunRecord], teacher: list[RunRecord], expects_arrival: bool
) -> dict[str, Any]:
    """The aggregate of one experiment and controller (see the module docstring)."""
    orders = [r.summary["order_mean"] for r in records if r.summary["order_mean"] is not None]
    median = _median_arrival(records)
    teacher_median = _median_arrival(teacher)
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
        "stalled_runs": len(records) - arrived if expects_arrival else None,
    }


def experiment_table(result: SuiteResult, experiment: str) -> dict[str, dict[str, Any]]:
    """{controller: table row} for one experiment; the teacher's ratio is 1 by definition."""
    teacher = result.records(experiment, "teacher")
    expects = EXPERIMENTS[experiment].expects_arrival
    controllers = dict.fromkeys(r.controller for r in result.runs if r.experiment == experiment)
    return {c: table_row(result.records(experiment, c), teacher, expects) for c in controllers}


@dataclass(frozen=True)
class BarCheck:
    """One criterion of the bar and whether the suite meets it."""

    name: str
    passed: bool
    detail: str


def bar_checks(result: SuiteResult) -> list[BarCheck]:
    """The issue's bar, for the CNN; empty unless the suite flew both common and opposing goals."""
    common = result.records("common", "cnn")
    opposing = result.records("opposing", "cnn")
    if not common or not opposing:
        return []
    n = len(common)
    collided = [r.seed for r in common if not r.summary["collision_free"]]
    stalled = [r.seed for r in common if not r.summary["arrived"]]
    cnn_median = _median_arrival(common)
    teacher_median = _median_arrival(result.records("common", "teacher"))
    assert cnn_median is not None and teacher_median is not None
    ratio = cnn_median / teacher_median if math.isfinite(teacher_median) else math.nan

    def median_text(median: float) -> str:
        return f"{median:.1f} s" if math.isfinite(median) else "none (half or more never arrived)"

    split = [r.seed for r in opposing if r.summary["flock_split"]]
    r_max = opposing[0].log.scenario.config.flocking.r_max_m
    worst_d_max = max(r.summary["d_max_m"] or 0.0 for r in opposing)
    return [
        BarCheck(
            "common goal: no collision (no pair under 1 m) in any run",
            not collided,
            f"{n - len(collided)}/{n} runs collision-free"
            + (f"; collided: seeds {collided}" if collided else ""),
        ),
        BarCheck(
            "common goal: every run arrives",
            not stalled,
            f"{n - len(stalled)}/{n} arrived" + (f"; stalled: seeds {stalled}" if stalled else ""),
        ),
        BarCheck(
            f"common goal: median arrival time <= {ARRIVAL_RATIO_BAR}x the teacher's",
            bool(ratio <= ARRIVAL_RATIO_BAR),
            f"median arrival: CNN {median_text(cnn_median)}, teacher "
            f"{median_text(teacher_median)}" + (f": {ratio:.2f}x" if math.isfinite(ratio) else ""),
        ),
        BarCheck(
            "opposing goals: the flock never splits (d_max < r_max)",
            not split,
            f"{len(opposing) - len(split)}/{len(opposing)} runs stayed together; highest d_max "
            f"{worst_d_max:.2f} m vs r_max {r_max:g} m",
        ),
    ]


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
