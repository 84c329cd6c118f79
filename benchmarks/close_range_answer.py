"""How strongly policies answer a close neighbour: their answer along the teacher's, by distance.

    python benchmarks/close_range_answer.py --dataset data/close17 --model models/swarm_cnn.pt \
        [--model other.pt ...] [--split test] [--samples 4000] [--seed 0]

Where a flock is judged (two opposing groups crossing 0.5-0.7 m apart just after the spawn) the
separation term is steepest, k_sep / d, and the recorded flights hold almost no samples: a network
that has barely seen a drone at 0.6 m answers it as if it were further. This script measures it
on a held-out split of a close-range dataset (`swarm-sim dataset close-range`: recorded flocks
with one pair brought within 0.4-1.1 m, every label the teacher's): for a seeded draw of
`--samples`, binned by the sample's nearest neighbour, the count, the RMSE of the 3-vector, the
mean |target| and the mean of each policy's answer projected on the target's direction ("along";
equal to the mean |target| for a policy that answers as strongly as the teacher). A second table
takes the samples whose neighbour is within `--within` (0.9 m) and bins them by where that
neighbour sits in the drone's cube map: "faceness", the largest component of its unit direction
in the body frame (1 at a face's centre, 0.577 at a cube corner, where a close drone is split over
three faces, two of them far apart in the 64x384 strip). Prints the tables per policy and writes
JSON (default benchmarks/results/close_range_answer.json). One torch thread; about a minute per
d4-symmetrized policy for 4,000 samples.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from cnn_latency import RESULTS, write_report
from command_shrinkage import policy_answers, print_table, shrinkage_table

from companion.frames import quat_to_rotmat
from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine

BINS_M = (0.0, 0.6, 0.8, 1.0, 1.2, 1.6, float("inf"))
FACENESS_BINS = (0.5, 0.7, 0.8, 0.9, 1.01)


def nearest_offset_body(meta: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """For each sample of `rows`, the offset (body FLU, m) to its nearest neighbour: (K, 3); the
    split's samples must be every agent at every step (as stored)."""
    agent = np.asarray(meta["agent"], dtype=np.intp)
    pos = np.asarray(meta["pos_world_enu"], dtype=np.float64)
    q = np.asarray(meta["q_world_body"], dtype=np.float64)
    starts = np.append(np.flatnonzero(agent == 0), len(agent))  # each step's first row, and the end
    out = np.empty((len(rows), 3))
    for k, row in enumerate(rows):
        s = int(np.searchsorted(starts, row, side="right")) - 1
        first, end = int(starts[s]), int(starts[s + 1])
        offsets = pos[first:end] - pos[row]
        dist = np.linalg.norm(offsets, axis=1)
        dist[row - first] = np.inf
        out[k] = quat_to_rotmat(q[row]).T @ offsets[int(np.argmin(dist))]
    return out


def nearest_faceness(meta: dict[str, np.ndarray], rows: np.ndarray) -> np.ndarray:
    """For each sample of `rows`, the largest component of its nearest neighbour's unit direction
    in its body frame; the split's samples must be every agent at every step (as stored)."""
    body = nearest_offset_body(meta, rows)
    return np.abs(body).max(axis=1) / np.linalg.norm(body, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="repeatable")
    parser.add_argument("--dataset", type=Path, required=True, help="a close-range dataset")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--within", type=float, default=0.9, help="m, the faceness table's samples")
    parser.add_argument("--out", type=Path, default=RESULTS / "close_range_answer.json")
    args = parser.parse_args()
    split = open_dataset(args.dataset).split(args.split)
    n = min(args.samples, split.n_samples)
    rows = np.sort(np.random.default_rng(args.seed).choice(split.n_samples, n, replace=False))
    images = np.asarray(split.images[rows])
    target = np.asarray(split.targets[rows], dtype=np.float64)
    nearest = np.asarray(split.meta["nearest_m"][rows], dtype=np.float64)
    close = np.flatnonzero(nearest < args.within)
    faceness = nearest_faceness(split.meta, rows[close])
    start = time.perf_counter()
    tables, corner_tables = {}, {}
    for model in args.model:
        pred = policy_answers(model, images)
        table = shrinkage_table(pred, target, nearest, BINS_M, "nearest_m")
        corner = shrinkage_table(pred[close], target[close], faceness, FACENESS_BINS, "faceness")
        tables[str(model)], corner_tables[str(model)] = table, corner
        print(f"{model} on {args.dataset} {args.split}, {n} samples")
        print_table(table, "nearest_m", "nearest m")
        print(f"neighbour within {args.within} m, by faceness (1 face centre, 0.58 cube corner)")
        print_table(corner, "faceness", "faceness")
    report = {
        "benchmark": "close_range_answer",
        "dataset": str(args.dataset),
        "split": args.split,
        "samples": n,
        "seed": args.seed,
        "tables": tables,
        "within_m": args.within,
        "by_faceness": corner_tables,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
