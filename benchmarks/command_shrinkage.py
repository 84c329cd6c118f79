"""How much a policy shrinks large commands: its answer along the teacher's, by command size.

    python benchmarks/command_shrinkage.py --model models/swarm_cnn.pt --dataset data/agg7 \
        [--split val] [--samples 6000] [--seed 0]

A network trained with a plain mean squared error on images that cannot pin every detail (a far
group's distance from 2-3 pixel blobs) answers large commands too small: the loss is lowest at
the mean of what each image might mean. The large commands are the ones the flock needs (a close
neighbour, a stretched flock), so this script measures it. For a seeded draw of `--samples` of the
split, binned by the teacher's |target|: the count, the RMSE of the 3-vector, the mean |target|
and the mean of the policy's answer projected on the target's direction ("along"; equal to the
mean |target| for a policy that does not shrink). Then the least-squares output gain: the one
number g (and one per axis) that minimizes the squared error of g x answer, with the error at
g = 1 and at g; a policy that does not shrink has g = 1. Prints both and writes JSON (default
benchmarks/results/command_shrinkage.json). One torch thread; about a minute for 6,000 samples of
a c4-symmetrized policy.
"""

from __future__ import annotations

import argparse
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report

from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine
from sim_harness.experiments.vision_controller import load_policy

BINS_MPS = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, float("inf"))
BATCH = 256


def shrinkage_table(
    pred: np.ndarray,
    target: np.ndarray,
    by: np.ndarray | None = None,
    bins: tuple[float, ...] = BINS_MPS,
    key: str = "target_mps",
) -> list[dict[str, Any]]:
    """One row per bin that holds samples: (N, 3) answers and targets, binned by `by` (N,)
    (default: |target|, in `BINS_MPS`); `key` names the bin's bounds in each row."""
    speed = np.linalg.norm(target, axis=1)
    by = speed if by is None else by
    rows = []
    for low, high in itertools.pairwise(bins):
        inside = (by >= low) & (by < high)
        if not inside.any():
            continue
        error = pred[inside] - target[inside]
        direction = target[inside] / np.maximum(speed[inside, None], 1e-9)
        rows.append(
            {
                key: [low, high],
                "samples": int(inside.sum()),
                "rmse_mps": float(np.sqrt((error**2).sum(axis=1).mean())),
                "target_mean_mps": float(speed[inside].mean()),
                "along_mean_mps": float((pred[inside] * direction).sum(axis=1).mean()),
            }
        )
    return rows


def policy_answers(model: Path, images: np.ndarray) -> np.ndarray:
    """The policy's (N, 3) answers to (N, 64, 384) uint8 images, in batches, one torch thread."""
    with load_policy(model, threads=1) as policy:
        return np.concatenate(
            [policy.infer_batch(images[i : i + BATCH]) for i in range(0, len(images), BATCH)]
        ).astype(np.float64)


def print_table(table: list[dict[str, Any]], key: str, title: str) -> None:
    """Print the rows of `shrinkage_table` (binned by `key`, titled `title`), with the answer's
    share of the teacher's |command|."""
    print(f"{title:<13}samples   RMSE   mean |target|   mean along   along / |target|")
    for row in table:
        low, high = row[key]
        ratio = row["along_mean_mps"] / max(row["target_mean_mps"], 1e-9)
        print(
            f"{low:4.2f}-{high:<6.2f} {row['samples']:9d} {row['rmse_mps']:6.3f}"
            f" {row['target_mean_mps']:15.2f} {row['along_mean_mps']:12.2f} {ratio:18.2f}"
        )


def least_squares_gain(pred: np.ndarray, target: np.ndarray) -> dict[str, Any]:
    """The scalar and per-axis g minimizing |g pred - target|^2 over (N, 3) answers, and the MSE
    (mean over samples and axes) at g = 1 and at the scalar g."""
    gain = float((pred * target).sum() / max(float((pred**2).sum()), 1e-12))
    per_axis = (pred * target).sum(axis=0) / np.maximum((pred**2).sum(axis=0), 1e-12)
    return {
        "gain": gain,
        "gain_per_axis": [float(g) for g in per_axis],
        "mse_at_1": float(((pred - target) ** 2).mean()),
        "mse_at_gain": float(((gain * pred - target) ** 2).mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="policy file (.pt)")
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--split", default="val", choices=("train", "val", "test"))
    parser.add_argument("--samples", type=int, default=6000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS / "command_shrinkage.json")
    args = parser.parse_args()
    split = open_dataset(args.dataset).split(args.split)
    n = min(args.samples, split.n_samples)
    rows = np.sort(np.random.default_rng(args.seed).choice(split.n_samples, n, replace=False))
    images = np.asarray(split.images[rows])
    target = np.asarray(split.targets[rows], dtype=np.float64)
    start = time.perf_counter()
    pred = policy_answers(args.model, images)
    table = shrinkage_table(pred, target)
    print(f"{args.model} on {args.dataset} {args.split}, {n} samples")
    print_table(table, "target_mps", "|target| m/s")
    fit = least_squares_gain(pred, target)
    print(
        f"least-squares output gain {fit['gain']:.3f} (per axis "
        + "/".join(f"{g:.3f}" for g in fit["gain_per_axis"])
        + f"): MSE {fit['mse_at_1']:.4f} at 1, {fit['mse_at_gain']:.4f} at the gain"
    )
    report = {
        "benchmark": "command_shrinkage",
        "model": str(args.model),
        "dataset": str(args.dataset),
        "split": args.split,
        "samples": n,
        "seed": args.seed,
        "table": table,
        "least_squares_gain": fit,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
