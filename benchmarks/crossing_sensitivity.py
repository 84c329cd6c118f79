"""How close to the teacher a student must answer for the opposing crossing to stay within 0.1 m.

    python benchmarks/crossing_sensitivity.py [--seeds 300-339] [--workers 2] \
        [--variants near0.8,near0.9,...]

The bar's opposing-goals pair criterion asks the CNN flock's closest pair to be at most 0.1 m
below the teacher's, seed by seed. That pair is made in the first two seconds, when the two
groups cross each other after the spawn. This script asks how accurate a policy has to be for
that, with no camera and no network: "students" that are the teacher's law with one controlled
error in the part the CNN learns (the Reynolds term, separation + cohesion), flown on training
seeds (the evaluation seeds stay unseen) against the exact teacher on the same seeds:

- `nearS`: every neighbour within 1.2 m (`--near-m`) weighs S in the separation sum (S < 1: a close
  neighbour answered too weakly, the CNN's error at a cube-map corner; S > 1: too strongly, or
  a close-range boost, the law `swarm-sim train --near-separation-scale S` teaches);
- `farS`: every neighbour beyond that weighs S in the separation sum (the approach before the
  crossing answered too weakly or too strongly);
- `reyS`: the whole Reynolds term times S (a policy that shrinks, or inflates, every answer);
- `sepS`: the whole separation term times S, at every distance (the law with the separation gain
  k_sep x S: a more, or less, cautious teacher);
- `noiseS`: the Reynolds term plus white Gaussian noise of S m/s per axis, drawn anew every
  control step (a policy with unbiased, uncorrelated errors of that size).

Terms join with `+`: `sep1.15+near2` is the law `swarm-sim train --separation-scale 1.15
--near-separation-scale 2` teaches (the whole separation sum, its close-range boost included,
times 1.15); with `--near-m 1.5`, the law `--near-separation-radius 1.5` teaches; with
`--near-ramp-m W`, the near term ramps in over W metres inside `--near-m` (a neighbour's share of
it rising linearly from 0 at `--near-m` to 1 at `--near-m` - W, the far term taking the rest),
the law `--near-separation-ramp W` teaches; with `--scale-reach-m M`, `sepS` scales only the
neighbours within M metres, the law `--separation-radius M` teaches.

Each keeps the migration term and the speed cap exact, as the CNN's flight does. Per variant:
seeds whose closest pair is within 0.1 m of the teacher's (the bar's criterion), the mean
difference, the mean order parameter and the centroid drift against the teacher's (two more of
the bar's opposing criteria). Prints a line per variant and writes JSON (default
benchmarks/results/crossing_sensitivity.json). About 1.5 s per 60 s flight on one core.

`--experiment` flies another of the suites' experiments instead (`n12`, `vmax4`, `common`, ...:
its flock size, speed cap and migration speed); each variant's line then also counts the seeds
with a pair under 1 m (the bar's absolute criterion) and the median arrival against the teacher's.
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report
from low_pass_tuning import training_seeds

from companion.flocking import (
    FlockingParams,
    cap_speed,
    migration_velocity,
    reynolds_from_offsets,
)
from sim_harness.experiments.machine import machine
from sim_harness.experiments.suites import EXPERIMENTS
from sim_harness.learning.relabel import NEAR_M, RAMP_M, SCALE_REACH_M, separation_parts
from sim_harness.sim.controllers import SENSE_NEIGHBOURS, Observation, TeacherController
from sim_harness.sim.rollout import fly, summarize
from sim_harness.sim.scenarios import build_scenario

PAIR_MARGIN_M = 0.1  # the bar's criterion: at most this far below the teacher's closest pair
DEFAULT_VARIANTS = (
    "near0.7,near0.8,near0.9,near1.1,near1.25,far0.8,far0.9,far1.1,"
    "rey0.8,rey0.9,rey1.1,noise0.1,noise0.2,noise0.3"
)


class StudentController:
    """The teacher's law with controlled errors in its Reynolds term (see the module doc)."""

    name = "student"
    senses = frozenset({SENSE_NEIGHBOURS})

    def __init__(
        self,
        params: FlockingParams,
        terms: dict[str, float],
        seed: int,
        near_m: float = NEAR_M,
        ramp_m: float = RAMP_M,
        reach_m: float | None = SCALE_REACH_M,
    ) -> None:
        self.params = params
        self.terms = terms
        self.seed = seed
        self.near_m = near_m
        self.ramp_m = ramp_m
        self.reach_m = reach_m
        self._rng = np.random.default_rng(seed)

    def reset(self, n_agents: int) -> None:
        del n_agents
        self._rng = np.random.default_rng(self.seed)

    def command(self, observation: Observation) -> np.ndarray:
        sensing = observation.neighbours
        if sensing is None:
            raise ValueError("the student needs the 'neighbours' sense")
        own = observation.own
        p = self.params
        t = self.terms
        valid = np.asarray(sensing.perceived, dtype=bool)
        offsets = np.asarray(sensing.offsets_world_enu, dtype=float)
        separation, cohesion, _ = reynolds_from_offsets(offsets, valid, p)
        # the separation of the neighbours in range (ramped in), averaged over all of them as the
        # law averages, and the rest; and the share of those within the scale's reach
        within, near_part, _ = separation_parts(
            offsets, valid, p, self.near_m, self.ramp_m, self.reach_m
        )
        near_k, far_k = t.get("near", 1.0), t.get("far", 1.0)
        within = within + (near_k - 1.0) * near_part + (far_k - 1.0) * (within - near_part)
        separation = separation + (near_k - 1.0) * near_part
        separation = separation + (far_k - 1.0) * (separation - near_k * near_part)
        # `sepS`: k_sep x S on the neighbours within the reach (every one without a reach)
        reynolds = separation + (t.get("sep", 1.0) - 1.0) * within + cohesion
        reynolds = t.get("rey", 1.0) * reynolds
        if "noise" in t:
            reynolds = reynolds + self._rng.normal(0.0, t["noise"], size=reynolds.shape)
        migration = migration_velocity(own.pos_world_enu, own.migration_point_world_enu, p.k_mig)
        return cap_speed(reynolds + migration, p.v_max_mps)


def parse_variant(key: str) -> dict[str, float]:
    """`near1.5` -> {"near": 1.5}; `sep1.15+near2` -> {"sep": 1.15, "near": 2.0}."""
    terms: dict[str, float] = {}
    for term in key.split("+"):
        kind = next((k for k in ("near", "far", "rey", "sep", "noise") if term.startswith(k)), "")
        try:
            value = float(term[len(kind) :]) if kind else None
        except ValueError:
            value = None
        if value is None or kind in terms:
            raise ValueError(
                f"unknown variant {key!r}: nearS, farS, reyS, sepS or noiseS with S a number, "
                "joined by '+', each kind once"
            )
        terms[kind] = value
    return terms


def fly_one(
    variant: str,
    seed: int,
    experiment: str = "opposing",
    near_m: float = NEAR_M,
    ramp_m: float = RAMP_M,
    reach_m: float | None = SCALE_REACH_M,
) -> dict[str, Any]:
    """One flight of an experiment (default opposing goals, N = 9) by the teacher or a student
    whose near and far terms part at `near_m` (ramped over `ramp_m`), its `sepS` reaching
    `reach_m`."""
    config = EXPERIMENTS[experiment].scenario_config(seed)
    params = config.flocking
    scenario = build_scenario(config)
    if variant == "teacher":
        controller: Any = TeacherController(params)
    else:
        controller = StudentController(
            params, parse_variant(variant), seed, near_m, ramp_m, reach_m
        )
    log = fly(scenario, controller)
    s = summarize(log)
    step = int(np.nanargmin(log.d_min_m))
    return {
        "seed": seed,
        "d_min_m": s["d_min_m"],
        "at_s": float(log.time_s[step]),
        "order_mean": s["order_mean"],
        "drift_m": s["centroid_progress_m"],
        "split": s["flock_split"],
        "arrival_time_s": s["arrival_time_s"],
    }


def compare(student: list[dict[str, Any]], teacher: list[dict[str, Any]]) -> dict[str, Any]:
    """The bar's criteria that depend on the policy's accuracy, per variant."""
    diff = np.array([s["d_min_m"] - t["d_min_m"] for s, t in zip(student, teacher, strict=True)])
    below = [s["seed"] for s, d in zip(student, diff, strict=True) if d < -PAIR_MARGIN_M]
    drift = float(np.median([s["drift_m"] for s in student]))
    teacher_drift = float(np.median([t["drift_m"] for t in teacher]))
    arrivals = [r["arrival_time_s"] for r in student]
    teacher_arrivals = [r["arrival_time_s"] for r in teacher]
    arrival_ratio = float("nan")
    if None not in arrivals and None not in teacher_arrivals:
        arrival_ratio = float(np.median(arrivals) / np.median(teacher_arrivals))
    return {
        "pair_within": len(student) - len(below),
        "pair_below_seeds": below,
        "mean_diff_m": float(diff.mean()),
        "worst_diff_m": float(diff.min()),
        "lowest_pair_m": float(min(s["d_min_m"] for s in student)),
        "under_1m": sum(s["d_min_m"] < 1.0 for s in student),
        "order_mean": float(np.mean([s["order_mean"] for s in student])),
        "drift_ratio": drift / teacher_drift if teacher_drift else float("nan"),
        "arrival_ratio": arrival_ratio,
        "splits": sum(bool(s["split"]) for s in student),
        "flights": student,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="300-339", help="training seeds (< 1000), A-B")
    parser.add_argument("--variants", default=DEFAULT_VARIANTS, help="comma-separated")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2)")
    parser.add_argument(
        "--experiment", default="opposing", choices=tuple(EXPERIMENTS), help="(default opposing)"
    )
    parser.add_argument(
        "--near-m",
        type=float,
        default=NEAR_M,
        help=f"where near ends and far begins, metres (default {NEAR_M})",
    )
    parser.add_argument(
        "--near-ramp-m",
        type=float,
        default=RAMP_M,
        help="the near term ramps in over this many metres inside --near-m (default 0: a step)",
    )
    parser.add_argument(
        "--scale-reach-m",
        type=float,
        default=SCALE_REACH_M,
        help="sepS scales the neighbours within this many metres only, the law "
        "`--separation-radius` teaches (default: every neighbour)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="default results/crossing_sensitivity[_EXP].json"
    )
    args = parser.parse_args()
    suffix = "" if args.experiment == "opposing" else f"_{args.experiment}"
    out = args.out or RESULTS / f"crossing_sensitivity{suffix}.json"
    seeds = training_seeds(args.seeds)
    keys = [k for k in args.variants.split(",") if k]
    for key in keys:
        try:
            parse_variant(key)
        except ValueError as exc:
            parser.error(f"--variants: {exc}")
    if not 0.5 <= args.near_m <= 5.0:
        parser.error(f"--near-m must be in 0.5-5 m, got {args.near_m}")
    if not 0.0 <= args.near_ramp_m < args.near_m:
        parser.error(f"--near-ramp-m must be in [0, --near-m), got {args.near_ramp_m}")
    if args.scale_reach_m is not None and args.scale_reach_m < args.near_m:
        parser.error(f"--scale-reach-m must reach at least --near-m, got {args.scale_reach_m}")
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    start = time.perf_counter()
    order = ["teacher", *keys]
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = {
            (v, s): pool.submit(
                fly_one, v, s, args.experiment, args.near_m, args.near_ramp_m, args.scale_reach_m
            )
            for v in order
            for s in seeds
        }
        flights = {v: [futures[(v, s)].result() for s in seeds] for v in order}
    teacher = flights["teacher"]
    t_order = float(np.mean([t["order_mean"] for t in teacher]))
    t_under = sum(t["d_min_m"] < 1.0 for t in teacher)
    print(
        f"teacher    : lowest pair {min(t['d_min_m'] for t in teacher):.2f} m"
        f" ({t_under} seeds under 1 m),"
        f" order {t_order:.3f}, drift {np.median([t['drift_m'] for t in teacher]):.2f} m"
    )
    results = {}
    for key in keys:
        r = results[key] = compare(flights[key], teacher)
        print(
            f"{key:11s}: pair within {PAIR_MARGIN_M} m on {r['pair_within']}/{len(seeds)} seeds,"
            f" mean {r['mean_diff_m']:+.3f} m, worst {r['worst_diff_m']:+.2f} m;"
            f" lowest {r['lowest_pair_m']:.2f} m ({r['under_1m']} under 1 m);"
            f" order {r['order_mean']:.3f}; drift {100 * r['drift_ratio']:.0f} %;"
            f" arrival {r['arrival_ratio']:.2f}x",
            flush=True,
        )
    report = {
        "benchmark": "crossing_sensitivity",
        "experiment": args.experiment,
        "seeds": [seeds[0], seeds[-1]],
        "near_m": args.near_m,
        "near_ramp_m": args.near_ramp_m,
        "scale_reach_m": args.scale_reach_m,
        "pair_margin_m": PAIR_MARGIN_M,
        "teacher": {"order_mean": t_order, "under_1m": t_under, "flights": teacher},
        "variants": results,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, out)


if __name__ == "__main__":
    main()
