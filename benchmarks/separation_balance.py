"""What a policy makes of the teacher's three parts: near separation, far separation, cohesion.

    python benchmarks/separation_balance.py --dataset data/agg20-aa --model models/swarm_cnn.pt \
        [--model other.pt ...] [--split val] [--samples 4000] [--seed 0] [--near 1.2]

`crossing_sensitivity.py` finds that the opposing flock's crossing pair is set less by how a
policy answers a neighbour within 1.2 m than by the balance of separation and cohesion beyond it:
a student whose separation from neighbours beyond 1.2 m is 20 % weak (cohesion exact) crosses
more than 0.1 m closer than the teacher on 24 of 40 seeds, one whose whole command is 20 % weak
on 1. This script measures that balance in a trained policy. On a seeded draw of a recorded
dataset's split (every agent at every step, so each sample's flock is known), the teacher's
Reynolds command is split, in the drone's body frame, into

    sep_near: separation from the neighbours within --near m,
    sep_far:  separation from the others,
    coh:      cohesion,

(their sum is the label), and the policy's answer is fitted by least squares as
a * sep_near + b * sep_far + c * coh + bias (one bias per body axis). The teacher itself is
a = b = c = 1, bias 0: a policy with b / c below 1 holds its neighbours closer than the teacher's
flock does. The fit is also reported on the samples whose nearest neighbour is within 1.5 m (the
crowded states of a spawn or a crossing). Prints a line per policy and writes JSON (default
benchmarks/results/separation_balance.json). One torch thread; about a minute per d4 policy for
4,000 samples.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report
from command_shrinkage import policy_answers

from companion.flocking import COINCIDENT_M, FlockingParams
from companion.frames import quat_to_rotmat
from sim_harness.dataset.spec import DatasetSpec
from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine

PARTS = ("sep_near", "sep_far", "coh")
CROWDED_M = 1.5


def decompose(
    meta: dict[str, np.ndarray], rows: np.ndarray, params: FlockingParams, near_m: float
) -> np.ndarray:
    """(len(rows), 3 parts, 3 axes): each sample's teacher command split as in the module doc,
    body FLU, m/s; the split's samples must be every agent at every step (as stored)."""
    agent = np.asarray(meta["agent"], dtype=np.intp)
    pos = np.asarray(meta["pos_world_enu"], dtype=np.float64)
    q = np.asarray(meta["q_world_body"], dtype=np.float64)
    starts = np.append(np.flatnonzero(agent == 0), len(agent))
    out = np.zeros((len(rows), len(PARTS), 3))
    for k, row in enumerate(rows):
        s = int(np.searchsorted(starts, row, side="right")) - 1
        first, end = int(starts[s]), int(starts[s + 1])
        r = np.delete(pos[first:end] - pos[row], row - first, axis=0)  # offsets to the others
        d2 = np.einsum("mk,mk->m", r, r)
        neighbour = d2 < params.r_max_m**2
        if not neighbour.any():
            continue
        r, d2 = r[neighbour], d2[neighbour]
        inv = np.divide(1.0, d2, out=np.zeros_like(d2), where=d2 >= COINCIDENT_M**2)
        near = d2 < near_m**2
        scale = 1.0 / len(r)
        world = np.stack(
            [
                -params.k_sep * scale * (inv * near) @ r,
                -params.k_sep * scale * (inv * ~near) @ r,
                params.k_coh * scale * r.sum(axis=0),
            ]
        )
        out[k] = world @ quat_to_rotmat(q[row])  # world -> body: R^T v, row-wise
    return out


def fit(answer: np.ndarray, parts: np.ndarray) -> dict[str, Any]:
    """Least squares answer ~ sum_p gain_p * part_p + bias (per axis), pooled over axes."""
    n = len(answer)
    columns = [parts[:, p, :].reshape(-1) for p in range(len(PARTS))]
    bias = [np.kron(np.ones(n), np.eye(3)[a]) for a in range(3)]
    design = np.stack(columns + bias, axis=1)
    coef, *_ = np.linalg.lstsq(design, answer.reshape(-1), rcond=None)
    residual = answer.reshape(-1) - design @ coef
    return {
        "samples": n,
        **{f"gain_{p}": float(coef[i]) for i, p in enumerate(PARTS)},
        "bias_flu_mps": [float(b) for b in coef[len(PARTS) :]],
        "residual_rms_mps": float(np.sqrt(np.mean(residual**2))),
        "far_over_coh": float(coef[1] / coef[2]) if coef[2] else float("nan"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, action="append", required=True, help="repeatable")
    parser.add_argument("--dataset", type=Path, required=True, help="a recorded dataset")
    parser.add_argument("--split", default="val", choices=("train", "val", "test"))
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--near", type=float, default=1.2, help="m, sep_near's radius")
    parser.add_argument("--out", type=Path, default=RESULTS / "separation_balance.json")
    args = parser.parse_args()
    if args.samples < 10:
        parser.error(f"--samples must be >= 10, got {args.samples}")
    if not args.near > 0:
        parser.error(f"--near must be > 0 m, got {args.near}")
    dataset = open_dataset(args.dataset)
    split = dataset.split(args.split)
    n = min(args.samples, split.n_samples)
    rows = np.sort(np.random.default_rng(args.seed).choice(split.n_samples, n, replace=False))
    params = DatasetSpec.from_dict(dataset.manifest["spec"]).flocking
    parts = decompose(split.meta, rows, params, args.near)
    target = np.asarray(split.targets[rows], dtype=np.float64)
    images = np.asarray(split.images[rows])  # read once, answered by every model
    # the label is the three parts' sum (a check that the decomposition is the teacher's)
    label_error = float(np.abs(parts.sum(axis=1) - target).max())
    nearest = np.asarray(split.meta["nearest_m"][rows], dtype=np.float64)
    crowded = nearest < CROWDED_M
    start = time.perf_counter()
    fits: dict[str, Any] = {}
    for name, answer in [("teacher (the label)", target)] + [
        (str(m), policy_answers(m, images)) for m in args.model
    ]:
        fits[name] = {"all": fit(answer, parts), "crowded": fit(answer[crowded], parts[crowded])}
        for which, f in fits[name].items():
            print(
                f"{name} [{which}, {f['samples']}]: near {f['gain_sep_near']:.2f},"
                f" far {f['gain_sep_far']:.2f}, cohesion {f['gain_coh']:.2f}"
                f" (far / cohesion {f['far_over_coh']:.2f}); bias FLU"
                f" {', '.join(f'{b:+.2f}' for b in f['bias_flu_mps'])} m/s;"
                f" residual {f['residual_rms_mps']:.3f} m/s",
                flush=True,
            )
    report = {
        "benchmark": "separation_balance",
        "dataset": str(args.dataset),
        "split": args.split,
        "samples": n,
        "seed": args.seed,
        "near_m": args.near,
        "crowded_m": CROWDED_M,
        "label_error_mps": label_error,
        "fits": fits,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
