"""The acceptance bar of the vision flock (issue 17): the CNN against the teacher, same seeds.

Each experiment the suite flew with both controllers adds its criteria (so `swarm-sim demo`, which
flies the common and opposing goals only, checks those):

- common goal, N = 9: no run with a pair under 1 m; lowest closest pair >= 1.05 m; every run
  arrives; median arrival <= 1.15x the teacher's;
- opposing goals: never splits (d_max < r_max); the flock's centroid moves towards the majority's
  goal at least half as far as the teacher's (medians over seeds); mean order >= 0.5; on every
  seed the closest pair at most 0.1 m below the teacher's;
- N = 3 and N = 12: no pair under 1 m; median arrival <= 1.3x the teacher's; mean order >= 0.9;
- faster flock (vmax4): no pair under 1 m; median arrival <= 1.3x the teacher's;
- no migration point: no pair under 1 m; never splits;

and, from the model's own metadata, the aim of R² >= 0.85 on every axis of the paper's test split.

Median arrival: non-arrivals count as never arriving (infinite), so the ratio is infinite when
half or more of the runs stall. The bar suite flies `DEFAULT_SEEDS["bar"]` (20) evaluation seeds.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.experiments.stats import median_arrival

COLLISION_M = 1.0
COMMON_LOWEST_PAIR_M = 1.05
COMMON_ARRIVAL_RATIO = 1.15
ARRIVAL_RATIO = 1.3  # N = 3, N = 12, the faster flock
OPPOSING_PROGRESS_SHARE = 0.5  # of the teacher's centroid progress towards the majority's goal
OPPOSING_ORDER = 0.5
OPPOSING_PAIR_MARGIN_M = 0.1  # the CNN's closest pair may be this much below the teacher's
SIZE_ORDER = 0.9  # N = 3 and N = 12
R2_AIM = 0.85


@dataclass(frozen=True)
class BarCheck:
    """One criterion of the bar and whether the suite meets it."""

    name: str
    passed: bool
    detail: str


def _seconds(t: float) -> str:
    return f"{t:.1f} s" if math.isfinite(t) else "never (half or more stalled)"


def _metres(value: float, threshold: float, sign: str = "") -> str:
    """A distance in cm, or in mm where cm would round it onto the other side of the criterion's
    threshold (0.998 m under a 1 m bound reads "0.998 m", never "1.00 m")."""
    text = f"{value:{sign}.2f}"
    if (float(text) >= threshold) != (value >= threshold):
        text = f"{value:{sign}.3f}"
    return f"{text} m"


def _no_collision(label: str, cnn: list[RunRecord], teacher: list[RunRecord]) -> BarCheck:
    """The CNN's verdict; the detail adds the teacher's on the same seeds, which the verdict
    does not use (a crowded spawn can bring even the teacher's flock under 1 m)."""
    hit = [r for r in cnn if not r.summary["collision_free"]]
    lowest = min(r.summary["d_min_m"] for r in cnn)
    detail = (
        f"{len(cnn) - len(hit)}/{len(cnn)} runs clear; lowest pair {_metres(lowest, COLLISION_M)}"
    )
    if hit:
        closest = (f"{r.seed} ({_metres(r.summary['d_min_m'], COLLISION_M)})" for r in hit)
        detail += "; under 1 m: " + ", ".join(closest)
    clear = sum(bool(r.summary["collision_free"]) for r in teacher)
    detail += (
        f" (teacher, same seeds: {clear}/{len(teacher)} clear, lowest "
        f"{_metres(min(r.summary['d_min_m'] for r in teacher), COLLISION_M)})"
    )
    return BarCheck(f"{label}: no pair under {COLLISION_M:g} m in any run", not hit, detail)


def _arrival(label: str, cnn: list[RunRecord], teacher: list[RunRecord], bound: float) -> BarCheck:
    ours, theirs = median_arrival(cnn) or math.nan, median_arrival(teacher) or math.nan
    ratio = ours / theirs if math.isfinite(theirs) and theirs > 0 else math.nan
    detail = f"median arrival: CNN {_seconds(ours)}, teacher {_seconds(theirs)}"
    if math.isfinite(ratio):
        detail += f": {ratio:.2f}x"
    return BarCheck(f"{label}: median arrival <= {bound:g}x the teacher's", ratio <= bound, detail)


def _every_run_arrives(label: str, cnn: list[RunRecord]) -> BarCheck:
    stalled = [r.seed for r in cnn if not r.summary["arrived"]]
    detail = f"{len(cnn) - len(stalled)}/{len(cnn)} arrived"
    return BarCheck(
        f"{label}: every run arrives",
        not stalled,
        detail + (f"; stalled: seeds {stalled}" if stalled else ""),
    )


def _never_splits(label: str, cnn: list[RunRecord]) -> BarCheck:
    split = [r.seed for r in cnn if r.summary["flock_split"]]
    r_max = cnn[0].summary["r_max_m"]
    worst = max(r.summary["d_max_m"] or 0.0 for r in cnn)
    detail = f"{len(cnn) - len(split)}/{len(cnn)} stayed together; highest d_max {worst:.2f} m"
    detail += f" vs r_max {r_max:g} m" + (f"; split: seeds {split}" if split else "")
    return BarCheck(f"{label}: the flock never splits (d_max < r_max)", not split, detail)


def _mean_order(label: str, cnn: list[RunRecord], bound: float) -> BarCheck:
    orders = [r.summary["order_mean"] for r in cnn if r.summary["order_mean"] is not None]
    mean = sum(orders) / len(orders) if orders else math.nan
    lowest = min(orders) if orders else math.nan
    return BarCheck(
        f"{label}: mean order parameter >= {bound:g}",
        mean >= bound,
        f"mean {mean:.2f} over {len(orders)} runs (lowest run {lowest:.2f})",
    )


def _common(cnn: list[RunRecord], teacher: list[RunRecord]) -> list[BarCheck]:
    label = "common goal"
    lowest = min(r.summary["d_min_m"] for r in cnn)
    return [
        _no_collision(label, cnn, teacher),
        BarCheck(
            f"{label}: lowest closest pair >= {COMMON_LOWEST_PAIR_M:g} m",
            lowest >= COMMON_LOWEST_PAIR_M,
            f"lowest {_metres(lowest, COMMON_LOWEST_PAIR_M)}; median of the runs' closest pairs "
            f"{statistics.median(r.summary['d_min_m'] for r in cnn):.2f} m (teacher "
            f"{statistics.median(r.summary['d_min_m'] for r in teacher):.2f} m)",
        ),
        _every_run_arrives(label, cnn),
        _arrival(label, cnn, teacher, COMMON_ARRIVAL_RATIO),
    ]


def _opposing(cnn: list[RunRecord], teacher: list[RunRecord]) -> list[BarCheck]:
    label = "opposing goals"
    ours = statistics.median(r.summary["centroid_progress_m"] for r in cnn)
    theirs = statistics.median(r.summary["centroid_progress_m"] for r in teacher)
    share = ours / theirs if theirs > 0 else math.nan
    by_seed = {r.seed: r.summary["d_min_m"] for r in teacher}
    below = [
        (r.seed, r.summary["d_min_m"], by_seed[r.seed])
        for r in cnn
        if r.seed in by_seed and r.summary["d_min_m"] < by_seed[r.seed] - OPPOSING_PAIR_MARGIN_M
    ]
    worst = min(r.summary["d_min_m"] - by_seed[r.seed] for r in cnn if r.seed in by_seed)
    worst_text = _metres(worst, -OPPOSING_PAIR_MARGIN_M, "+")
    pair_detail = f"{len(cnn) - len(below)}/{len(cnn)} seeds within; worst {worst_text}"
    if below:
        pair_detail += "; below: " + ", ".join(f"{s} ({a:.2f} vs {b:.2f} m)" for s, a, b in below)
    return [
        _never_splits(label, cnn),
        BarCheck(
            f"{label}: the centroid drifts towards the majority's goal >= "
            f"{OPPOSING_PROGRESS_SHARE:.0%} as far as the teacher's (medians)",
            share >= OPPOSING_PROGRESS_SHARE,
            f"CNN {ours:.2f} m, teacher {theirs:.2f} m"
            + (f": {share:.0%}" if math.isfinite(share) else ""),
        ),
        _mean_order(label, cnn, OPPOSING_ORDER),
        BarCheck(
            f"{label}: closest pair at most {OPPOSING_PAIR_MARGIN_M:g} m below the teacher's on "
            "every seed",
            not below,
            pair_detail,
        ),
    ]


def _flock_size(label: str) -> Callable[[list[RunRecord], list[RunRecord]], list[BarCheck]]:
    def checks(cnn: list[RunRecord], teacher: list[RunRecord]) -> list[BarCheck]:
        return [
            _no_collision(label, cnn, teacher),
            _arrival(label, cnn, teacher, ARRIVAL_RATIO),
            _mean_order(label, cnn, SIZE_ORDER),
        ]

    return checks


def _faster(cnn: list[RunRecord], teacher: list[RunRecord]) -> list[BarCheck]:
    label = "faster flock"
    return [_no_collision(label, cnn, teacher), _arrival(label, cnn, teacher, ARRIVAL_RATIO)]


def _no_goal(cnn: list[RunRecord], teacher: list[RunRecord]) -> list[BarCheck]:
    label = "no migration point"
    return [_no_collision(label, cnn, teacher), _never_splits(label, cnn)]


CRITERIA: dict[str, Callable[[list[RunRecord], list[RunRecord]], list[BarCheck]]] = {
    "common": _common,
    "opposing": _opposing,
    "n3": _flock_size("N = 3"),
    "n12": _flock_size("N = 12"),
    "vmax4": _faster,
    "self-propelled": _no_goal,
}


def r2_check(metadata: dict[str, Any]) -> BarCheck | None:
    """The aim on the paper's test split, from the policy's metadata (None if it has none)."""
    metrics = (metadata.get("test_metrics") or {}).get("metrics") or {}
    per_axis = metrics.get("per_axis")
    if not isinstance(per_axis, dict) or not all(axis in per_axis for axis in "xyz"):
        return None
    values = {axis: float(per_axis[axis]["r2"]) for axis in "xyz"}
    return BarCheck(
        f"aim: R² >= {R2_AIM:g} on every axis of the paper's test split",
        min(values.values()) >= R2_AIM,
        ", ".join(f"{axis} {v:.3f}" for axis, v in values.items()),
    )


def bar_checks(result: SuiteResult) -> list[BarCheck]:
    """The bar's criteria of every experiment flown by both controllers, then the R² aim."""
    checks: list[BarCheck] = []
    for key, criteria in CRITERIA.items():
        cnn, teacher = result.records(key, "cnn"), result.records(key, "teacher")
        if cnn and teacher:
            checks += criteria(cnn, teacher)
    if checks:
        aim = r2_check(result.model_metadata)
        checks += [aim] if aim is not None else []
    return checks
