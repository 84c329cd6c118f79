"""Choosing the CNN's low-pass cut-off on training seeds (never on the bar's evaluation seeds).

    python benchmarks/low_pass_tuning.py --model models/swarm_cnn.pt --cutoffs off,2,1,0.5 \
        [--experiments opposing,common] [--seeds 900-903] [--duration S]
        [--renderer NAME (default: the model's)]

Flies each experiment with the CNN once per seed and cut-off (and the teacher once per seed), all
on scenario seeds below 1000, which `swarm-sim experiments` refuses so that the bar is never tuned
on. Prints, per experiment and cut-off: the lowest and median closest pair, how many seeds come
more than 0.1 m closer than the teacher on the same seed (the opposing-goals criterion of the bar),
the mean order parameter and the median centroid progress, next to the teacher's; writes JSON
(default benchmarks/results/low_pass_tuning.json) with the per-seed closest pairs. Sequential, one
thread: about a minute per CNN flight. `--duration 6` keeps only the start, where opposing-goal
neighbours cross: cheap enough for 20 seeds.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any

from companion.errors import ConfigError
from sim_harness.experiments.runner import Job, fly_job
from sim_harness.experiments.suites import EVAL_SEED_BASE, SuiteConfig
from sim_harness.experiments.vision_controller import load_policy
from sim_harness.sim.renderers import add_renderer_option, renderer_of_model

RESULTS = Path(__file__).resolve().parent / "results"


def _cutoff(text: str) -> float | None:
    return None if text in ("off", "none") else float(text)


def seed_ranges(text: str) -> list[int]:
    """'900,901' or '900-919' (inclusive), or both mixed."""
    seeds: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds += range(int(first), int(last or first) + 1)
    return seeds


def training_seeds(text: str) -> list[int]:
    """As `seed_ranges`, refusing evaluation seeds (>= 1000)."""
    seeds = seed_ranges(text)
    if max(seeds) >= EVAL_SEED_BASE:
        raise ConfigError(f"seeds: tune on training seeds (< {EVAL_SEED_BASE}), got {seeds}")
    return seeds


def _row(summaries: list[dict[str, Any]], teacher: list[float] | None) -> dict[str, Any]:
    progress = [s["centroid_progress_m"] for s in summaries if s["centroid_progress_m"] is not None]
    d_min = [s["d_min_m"] for s in summaries]
    below = (
        None if teacher is None else sum(d < t - 0.1 for d, t in zip(d_min, teacher, strict=True))
    )
    return {
        "runs": len(summaries),
        "d_min_m": d_min,
        "seeds_more_than_0_1_m_below_teacher": below,
        "d_min_lowest_m": min(d_min),
        "d_min_median_m": statistics.median(d_min),
        "order_mean": statistics.fmean(s["order_mean"] for s in summaries),
        "centroid_progress_median_m": statistics.median(progress) if progress else None,
        "arrived": sum(s["arrived"] for s in summaries),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--cutoffs", default="off,2,1,0.5", help="Hz, comma-separated; off: none")
    parser.add_argument("--experiments", default="opposing,common")
    parser.add_argument("--seeds", default="900-903", help="training-range seeds (< 1000)")
    add_renderer_option(parser, follows_model=True)
    parser.add_argument("--duration", type=float, default=None, help="cut each flight (s)")
    parser.add_argument("--out", type=Path, default=RESULTS / "low_pass_tuning.json")
    args = parser.parse_args()
    args.renderer = args.renderer or renderer_of_model(args.model)  # as the bar
    seeds = training_seeds(args.seeds)
    cutoffs = [_cutoff(c) for c in args.cutoffs.split(",")]
    experiments = args.experiments.split(",")
    table: dict[str, dict[str, Any]] = {}
    start = time.perf_counter()
    with load_policy(args.model) as policy:
        for experiment in experiments:
            table[experiment] = {}
            flights = [("teacher", "teacher", None)]
            flights += [("cnn", "off" if c is None else f"{c:g} Hz", c) for c in cutoffs]
            for controller, label, cutoff in flights:
                config = SuiteConfig(
                    suite="bar",
                    model_path=args.model,
                    low_pass_cutoff_hz=cutoff,
                    renderer=args.renderer,
                    duration_s=args.duration,
                )
                runs = [
                    fly_job(Job(experiment, controller, seed), config, policy).summary
                    for seed in seeds
                ]
                teacher = table[experiment].get("teacher", {}).get("d_min_m")
                row = table[experiment][label] = _row(runs, teacher)
                print(
                    f"{experiment:10} {label:8} lowest pair {row['d_min_lowest_m']:.2f} m, "
                    f"median {row['d_min_median_m']:.2f} m, "
                    f"below teacher - 0.1 m: {row['seeds_more_than_0_1_m_below_teacher']}, "
                    f"order {row['order_mean']:.2f}, "
                    f"progress {row['centroid_progress_median_m'] or 0.0:.1f} m, "
                    f"arrived {row['arrived']}/{row['runs']}",
                    flush=True,
                )
    report = {
        "benchmark": "low_pass_tuning",
        "model": str(args.model),
        "seeds": seeds,
        "renderer": args.renderer,
        "duration_s": args.duration,
        "table": table,
        "wall_s": time.perf_counter() - start,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
