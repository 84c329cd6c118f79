"""`swarm-sim compare A B`: two suite reports, seed by seed.

    swarm-sim compare docs/results/bar-round47-rest docs/results/bar-round47-jitter-rest
    swarm-sim compare A B --controller teacher --json out.json

A or B is a folder `swarm-sim experiments` wrote, or its `results.json`. For every experiment both
reports flew, over the seeds both flew, per controller (default the CNN): each seed's closest pair
in A and in B and their difference, the median and the largest |difference|, the runs under the
1 m collision threshold in each, and each report's mean order parameter with its standard error
over the runs.

What it is for: the closest pair is sensitive (a flock amplifies a 1e-6 m/s nudge of the outputs
into tens of centimetres at an arrival), so a verdict is only worth what survives another flight
of the same seeds: the same model perturbed (`--output-jitter`), two models, or two machines.
Reports flown on different seeds share no seed and compare nothing; that is an error, not an
empty table.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from companion.errors import CompanionError
from sim_harness.experiments.suites import CONTROLLERS, EXPERIMENTS, LABELS
from sim_harness.sim.metrics import COLLISION_THRESHOLD_M


class ReportError(CompanionError):
    """A suite report cannot be read, or two reports have nothing to compare."""


@dataclass(frozen=True)
class SeedPair:
    """One seed's closest pair in both reports (m)."""

    seed: int
    d_min_a_m: float
    d_min_b_m: float

    @property
    def delta_m(self) -> float:
        return self.d_min_b_m - self.d_min_a_m


@dataclass(frozen=True)
class ExperimentComparison:
    """One experiment and controller, over the seeds both reports flew."""

    experiment: str
    controller: str
    seeds: list[SeedPair]
    median_abs_delta_m: float
    largest_delta: SeedPair
    under_threshold_a: list[int]
    under_threshold_b: list[int]
    order_a: tuple[float, float] | None  # (mean over runs, standard error); None without orders
    order_b: tuple[float, float] | None


def load_runs(path: Path) -> list[dict[str, Any]]:
    """The run summaries of a report folder or `results.json`; `ReportError` if unreadable."""
    file = path / "results.json" if path.is_dir() else path
    try:
        data = json.loads(file.read_text())
    except FileNotFoundError:
        raise ReportError(
            f"{file}: no such file (give a report folder or its results.json)"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReportError(f"{file}: not a readable results.json ({exc})") from exc
    runs = data.get("runs") if isinstance(data, dict) else None
    if not isinstance(runs, list):
        raise ReportError(f"{file}: has no 'runs' list (not written by `swarm-sim experiments`)")
    needed = ("experiment", "controller", "seed", "d_min_m", "order_mean")
    for i, run in enumerate(runs):
        if not isinstance(run, dict) or any(k not in run for k in needed):
            raise ReportError(f"{file}: runs[{i}] lacks one of {', '.join(needed)}")
        if not isinstance(run["d_min_m"], int | float):
            raise ReportError(f"{file}: runs[{i}].d_min_m is {run['d_min_m']!r}, not a distance")
    return runs


def _order(runs: list[dict[str, Any]]) -> tuple[float, float] | None:
    values = [float(r["order_mean"]) for r in runs if r["order_mean"] is not None]
    if not values:
        return None
    se = statistics.stdev(values) / math.sqrt(len(values)) if len(values) > 1 else math.nan
    return statistics.fmean(values), se


def compare_runs(
    runs_a: list[dict[str, Any]], runs_b: list[dict[str, Any]], controller: str = "cnn"
) -> list[ExperimentComparison]:
    """Per experiment (in the suites' order), the seeds both flew with `controller`."""
    if controller not in CONTROLLERS:
        raise ReportError(f"controller must be one of {', '.join(CONTROLLERS)}, not {controller!r}")

    def index(runs: list[dict[str, Any]]) -> dict[tuple[str, int], dict[str, Any]]:
        return {(r["experiment"], int(r["seed"])): r for r in runs if r["controller"] == controller}

    a, b = index(runs_a), index(runs_b)
    common = a.keys() & b.keys()
    if not common:
        raise ReportError(
            f"the two reports share no (experiment, seed) flown by the {LABELS[controller]}: "
            "compare reports of the same seeds (same --seed-base and --seeds)"
        )
    rank = {key: i for i, key in enumerate(EXPERIMENTS)}
    experiments = sorted({e for e, _ in common}, key=lambda e: (rank.get(e, len(rank)), e))
    result = []
    for exp in experiments:
        keys = sorted(k for k in common if k[0] == exp)
        pairs = [
            SeedPair(s, float(a[(e, s)]["d_min_m"]), float(b[(e, s)]["d_min_m"])) for e, s in keys
        ]
        threshold = float(a[keys[0]].get("collision_threshold_m", COLLISION_THRESHOLD_M))
        result.append(
            ExperimentComparison(
                experiment=exp,
                controller=controller,
                seeds=pairs,
                median_abs_delta_m=statistics.median(abs(p.delta_m) for p in pairs),
                largest_delta=max(pairs, key=lambda p: abs(p.delta_m)),
                under_threshold_a=[p.seed for p in pairs if p.d_min_a_m < threshold],
                under_threshold_b=[p.seed for p in pairs if p.d_min_b_m < threshold],
                order_a=_order([a[k] for k in keys]),
                order_b=_order([b[k] for k in keys]),
            )
        )
    return result


def _order_text(order: tuple[float, float] | None) -> str:
    if order is None:
        return "—"
    mean, se = order
    return f"{mean:.3f}" if math.isnan(se) else f"{mean:.3f} (SE {se:.3f})"


def _seeds_text(seeds: list[int], pairs: list[SeedPair], which: str) -> str:
    if not seeds:
        return "none"
    by_seed = {p.seed: p for p in pairs}
    value = {s: getattr(by_seed[s], f"d_min_{which}_m") for s in seeds}
    return ", ".join(f"{s} ({value[s]:.2f} m)" for s in seeds)


def format_comparison(comparisons: list[ExperimentComparison], name_a: str, name_b: str) -> str:
    """Markdown: a summary table, then each experiment's seeds."""
    lines = [
        f"# {name_a} (A) against {name_b} (B)",
        "",
        "| experiment | controller | seeds | median abs(B - A) pair | largest | "
        "under 1 m in A | under 1 m in B | order A | order B |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for c in comparisons:
        big = c.largest_delta
        lines.append(
            f"| {c.experiment} | {LABELS[c.controller]} | {len(c.seeds)} | "
            f"{c.median_abs_delta_m:.3f} m | {big.delta_m:+.3f} m (seed {big.seed}: "
            f"{big.d_min_a_m:.2f} -> {big.d_min_b_m:.2f} m) | "
            f"{_seeds_text(c.under_threshold_a, c.seeds, 'a')} | "
            f"{_seeds_text(c.under_threshold_b, c.seeds, 'b')} | "
            f"{_order_text(c.order_a)} | {_order_text(c.order_b)} |"
        )
    for c in comparisons:
        lines += [
            "",
            f"## {c.experiment}, {LABELS[c.controller]}: closest pair per seed",
            "",
            "| seed | A | B | B - A |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {p.seed} | {p.d_min_a_m:.3f} m | {p.d_min_b_m:.3f} m | {p.delta_m:+.3f} m |"
            for p in c.seeds
        ]
    return "\n".join(lines) + "\n"


def comparison_json(comparisons: list[ExperimentComparison]) -> list[dict[str, Any]]:
    """The comparisons as plain data (each seed with its difference)."""
    out = []
    for c in comparisons:
        item = asdict(c)
        for seed, pair in zip(item["seeds"], c.seeds, strict=True):
            seed["delta_m"] = pair.delta_m
        item["largest_delta"]["delta_m"] = c.largest_delta.delta_m
        for key in ("order_a", "order_b"):  # one run has no standard error: null, not NaN
            if item[key] is not None:
                item[key] = [None if math.isnan(v) else v for v in item[key]]
        out.append(item)
    return out


def add_compare_command(sub: Any) -> None:
    """Register `compare` on the top-level subparsers."""
    p = sub.add_parser(
        "compare",
        help="two suite reports of the same seeds, seed by seed (closest pair, order)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("a", type=Path, help="report folder or results.json (A)")
    p.add_argument("b", type=Path, help="report folder or results.json (B)")
    p.add_argument(
        "--controller",
        choices=CONTROLLERS,
        default="cnn",
        help="whose flights to compare (default cnn)",
    )
    p.add_argument("--json", type=Path, default=None, help="also write the figures to this file")
    p.set_defaults(handler=_compare)


def _compare(args: argparse.Namespace) -> int:
    comparisons = compare_runs(load_runs(args.a), load_runs(args.b), args.controller)
    print(format_comparison(comparisons, str(args.a), str(args.b)), end="")
    if args.json is not None:
        args.json.write_text(json.dumps(comparison_json(comparisons), indent=2) + "\n")
    return 0
