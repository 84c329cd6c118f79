"""How much of the taught close-range boost a policy answers, by the nearest neighbour's distance.

    python benchmarks/boost_answer.py --model models/swarm_cnn.pt [--model other.pt ...] \
        --dataset data/agg59-aa [--dataset ...] [--splits val,test] [--within 1.6]
    python benchmarks/boost_answer.py --flights runs/experiments/NAME [--flights ...] \
        [--experiment vmax4]

The students since round 50 are taught a law whose separation weighs the neighbours within R
(1.35 m) C = 2 times, k_sep x 1.15 (`swarm-sim train --separation-scale --near-separation-scale
--near-separation-radius`): a step in the label at R. A network that cannot place a neighbour to
a few centimetres from its image answers the step blurred, too weak just inside R, where the
faster flock's pairs close at the arrival. Two views of it, both against the taught law
(`--separation-scale`, `--near-separation-scale`, `--near-separation-radius`,
`--separation-radius`; round 52's law by default):

- `--dataset` (held-out splits of recorded flocks, never trained on): every sample whose nearest
  neighbour is within `--within`; the policy's answer and the taught law's label, each projected
  on the body-frame direction away from that neighbour, binned by its distance.
- `--flights` (the `runs/` of `swarm-sim experiments`, CNN flights only): every pair within
  `--within` at every control step where no setpoint is at the speed cap; the pair's commanded
  opening rate from the CNN (its setpoints less each drone's own migration term) against the
  taught law's in the same positions, and the migration terms' own (negative: closing).

"ratio" is the policy's mean over the law's: 1 for a policy that answers the boost in full.
Prints the tables and writes JSON (default benchmarks/results/boost_answer.json). Dataset mode
runs the policies on one torch thread per model; about a minute for 2,000 samples each.
"""

from __future__ import annotations

import argparse
import glob
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
from close_range_answer import nearest_offset_body
from cnn_latency import RESULTS, write_report
from command_shrinkage import policy_answers

from companion.flocking import FlockingParams, migration_velocity
from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine
from sim_harness.experiments.suites import EXPERIMENTS
from sim_harness.learning.relabel import cautious_targets, separation_parts
from sim_harness.sim.scenarios import build_scenario

BINS_M = (0.8, 1.0, 1.1, 1.2, 1.3, 1.35, 1.4, 1.5, 1.6)
# the taught law: (separation scale, near scale, near radius m, the scale's reach m or None)
Law = tuple[float, float, float, float | None]


def taught_law_world(
    pos: np.ndarray,
    params: FlockingParams,
    scale: float,
    near_scale: float,
    near_m: float,
    reach_m: float | None = None,
) -> np.ndarray:
    """Separation + cohesion (N, 3) world m/s of one flock (N, 3) under the taught law: k_sep x
    `scale` (on the neighbours within `reach_m`, if given), the neighbours within `near_m` weighing
    `near_scale` in the separation sum (the labels `learning.relabel.cautious_targets` trains
    on)."""
    offsets = pos[None, :, :] - pos[:, None, :]  # r_ij = p_j - p_i
    valid = ~np.eye(len(pos), dtype=bool)
    sep, near, rey = separation_parts(offsets, valid, params, near_m, reach_m=reach_m)
    return rey + (scale - 1.0) * sep + scale * (near_scale - 1.0) * near


def away_from_nearest_body(meta: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """For each sample of `rows`, the unit vector (body FLU) from its nearest neighbour to it;
    the split's samples must be every agent at every step (as stored)."""
    offsets = nearest_offset_body(meta, rows)
    return -offsets / np.linalg.norm(offsets, axis=1, keepdims=True)


def binned(
    distance: np.ndarray, columns: dict[str, np.ndarray], bins: tuple[float, ...] = BINS_M
) -> list[dict[str, Any]]:
    """One row per bin of `distance` that holds values: the count and each column's mean, plus
    "ratio", the "policy" column's mean over the "law" column's."""
    rows = []
    for low, high in itertools.pairwise(bins):
        inside = (distance >= low) & (distance < high)
        if not inside.any():
            continue
        row: dict[str, Any] = {"distance_m": [low, high], "count": int(inside.sum())}
        row.update({name: float(values[inside].mean()) for name, values in columns.items()})
        row["ratio"] = row["policy"] / row["law"] if abs(row["law"]) > 1e-9 else float("nan")
        rows.append(row)
    return rows


def print_rows(rows: list[dict[str, Any]], title: str) -> None:
    names = [k for k in rows[0] if k not in ("distance_m", "count")] if rows else []
    print(title)
    print(f"{'distance m':<12}{'count':>7}" + "".join(f"{n:>11}" for n in names))
    for row in rows:
        low, high = row["distance_m"]
        cells = "".join(f"{row[n]:>+11.2f}" if n != "ratio" else f"{row[n]:>11.2f}" for n in names)
        print(f"{low:4.2f}-{high:<7.2f}{row['count']:>7d}{cells}")


def dataset_samples(
    datasets: list[Path], splits: list[str], within_m: float, law: Law
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(images, taught labels (N, 3), nearest distances, away directions) of every sample of the
    splits with a neighbour within `within_m`."""
    scale, near_scale, near_m, reach_m = law
    images, labels, nearest, away = [], [], [], []
    for path in datasets:
        for name in splits:
            split = open_dataset(path).split(name)
            meta = {k: np.asarray(v) for k, v in split.meta.items()}
            taught = cautious_targets(
                np.asarray(split.targets),
                meta,
                scale,
                near_scale=near_scale,
                near_m=near_m,
                reach_m=reach_m,
            )
            rows = np.flatnonzero(meta["nearest_m"] < within_m)
            images.append(np.asarray(split.images[rows]))
            labels.append(taught[rows].astype(np.float64))
            nearest.append(meta["nearest_m"][rows].astype(np.float64))
            away.append(away_from_nearest_body(meta, rows))
    return (
        np.concatenate(images),
        np.concatenate(labels),
        np.concatenate(nearest),
        np.concatenate(away),
    )


def flight_pairs(
    run_dir: Path, experiment: str, seed: int, within_m: float, law: Law
) -> np.ndarray:
    """(K, 4) rows of (distance, CNN opening rate, taught law's, migration's) for every pair
    within `within_m` at every uncapped control step of one logged CNN flight."""
    config = EXPERIMENTS[experiment].scenario_config(seed)
    params = config.flocking
    points = build_scenario(config).migration_points
    steps = np.load(run_dir / "steps.npz")
    pos, setpoints = steps["pos_world_enu"], steps["setpoint_world_enu"]
    out = []
    for t in range(len(pos) - 1):  # the last row's setpoint is NaN
        p = pos[t]
        dist = np.linalg.norm(p[:, None] - p[None], axis=-1)
        np.fill_diagonal(dist, np.inf)
        if dist.min() >= within_m:
            continue
        if np.linalg.norm(setpoints[t], axis=1).max() >= params.v_max_mps - 1e-6:
            continue  # capped: the CNN's share of the setpoint is not recoverable
        mig = migration_velocity(p, points, params.k_mig)
        cnn = setpoints[t] - mig
        law_v = taught_law_world(p, params, *law)
        for i, j in zip(*np.nonzero(np.triu(dist < within_m)), strict=True):
            away = (p[i] - p[j]) / dist[i, j]
            out.append(
                (
                    dist[i, j],
                    (cnn[i] - cnn[j]) @ away,
                    (law_v[i] - law_v[j]) @ away,
                    (mig[i] - mig[j]) @ away,
                )
            )
    return np.asarray(out, dtype=np.float64).reshape(-1, 4)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, action="append", default=[], help="repeatable")
    parser.add_argument("--dataset", type=Path, action="append", default=[], help="repeatable")
    parser.add_argument("--splits", default="val,test", help="held-out splits (default val,test)")
    parser.add_argument("--flights", type=Path, action="append", default=[], help="repeatable")
    parser.add_argument("--experiment", default="vmax4", help="of --flights (default vmax4)")
    parser.add_argument("--within", type=float, default=1.6, help="m (default 1.6)")
    parser.add_argument("--separation-scale", type=float, default=1.15)
    parser.add_argument("--near-separation-scale", type=float, default=2.0)
    parser.add_argument("--near-separation-radius", type=float, default=1.35)
    parser.add_argument(
        "--separation-radius", type=float, default=None, help="the scale's reach (default: all)"
    )
    parser.add_argument("--out", type=Path, default=RESULTS / "boost_answer.json")
    args = parser.parse_args()
    if not (args.dataset and args.model) and not args.flights:
        parser.error("give --model with --dataset, or --flights")
    law: Law = (
        args.separation_scale,
        args.near_separation_scale,
        args.near_separation_radius,
        args.separation_radius,
    )
    start = time.perf_counter()
    report: dict[str, Any] = {
        "benchmark": "boost_answer",
        "law": dict(zip(("separation_scale", "near_scale", "near_m", "reach_m"), law, strict=True)),
        "within_m": args.within,
    }
    if args.dataset and args.model:
        splits = args.splits.split(",")
        images, labels, nearest, away = dataset_samples(args.dataset, splits, args.within, law)
        law_along = (labels * away).sum(axis=1)
        tables = {}
        for model in args.model:
            along = (policy_answers(model, images) * away).sum(axis=1)
            tables[str(model)] = binned(nearest, {"policy": along, "law": law_along})
            print_rows(tables[str(model)], f"{model}: answer away from the nearest neighbour, m/s")
        report["datasets"] = {
            "datasets": [str(p) for p in args.dataset],
            "splits": splits,
            "samples": len(images),
            "tables": tables,
        }
    if args.flights:
        flights = {}
        for folder in args.flights:
            runs = sorted(glob.glob(str(folder / "runs" / args.experiment / "cnn" / "seed-*")))
            pairs = np.concatenate(
                [
                    flight_pairs(
                        Path(r), args.experiment, int(r.rsplit("-", 1)[1]), args.within, law
                    )
                    for r in runs
                ]
            )
            table = binned(
                pairs[:, 0], {"policy": pairs[:, 1], "law": pairs[:, 2], "migration": pairs[:, 3]}
            )
            flights[str(folder)] = {"flights": len(runs), "table": table}
            print_rows(table, f"{folder} ({len(runs)} flights): pair opening rate, m/s")
        report["flights"] = {"experiment": args.experiment, "folders": flights}
    report["wall_s"] = time.perf_counter() - start
    report["machine"] = machine()
    write_report(report, args.out)


if __name__ == "__main__":
    main()
