"""How much a policy's answers depend on the ground behind the drones.

    python benchmarks/ground_robustness.py --model models/swarm_cnn.pt \
        [--dataset data/quick-aa-s1 --varied data/quick-aa-s1-vs] [--flocks 6] [--seed 0]

The label does not depend on the ground: the teacher's command is a function of the neighbours'
offsets only. Two measurements of how much the policy's answers do anyway:

1. Same states, other grounds. `--dataset` and `--varied` hold the same flights, the second
   redrawn against a random ground and sky per run (`swarm-sim dataset rerender --vary-scene`).
   On a seeded draw of `--samples` of the test split: RMSE and R² per axis, and the mean error per
   axis (a bias every drone shares: the whole flock climbs or sinks).
2. One flock, moved over the ground. `--flocks` settled opposing-goal flocks (the teacher's law
   with perfect positions, 5 vs 4 agents, 40 s from a random spawn), level, drawn at 30 places of
   the default scene (15 m by 10 m, one period of its texture along x) and, per flock, over three
   unseen grounds and a flat one. Per scene: each drone's error against the teacher's separation
   plus cohesion, split into its mean over the places (the part that stays with the flock's
   shape) and its spread over them (the part the ground adds as the flock drifts), and the same
   for the flock's mean error (what moves the whole flock). A settled opposing flock drifts at
   1/9 m/s, so a flock-mean error that changes by a few cm/s from place to place is what makes it
   wander.

Prints and writes JSON (default benchmarks/results/ground_robustness.json). One torch thread;
a few minutes with both parts.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report

from companion.flocking import FlockingParams, flocking_command
from sim_harness.dataset.store import open_dataset
from sim_harness.experiments.machine import machine
from sim_harness.experiments.vision_controller import load_policy
from sim_harness.learning.evaluate import regression_metrics
from sim_harness.learning.model import AXES
from sim_harness.sim.renderers import make_renderer
from sim_harness.sim.scene import SceneSpec, random_scene
from sim_harness.sim.world import World

BATCH = 256
N_AGENTS = 9
PLACES = [(dx, dy) for dx in np.arange(0.0, 15.0, 1.5) for dy in (0.0, 5.0, 10.0)]


def split_errors(
    policy: Any, dataset: Path, rows: np.ndarray
) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    split = open_dataset(dataset).split("test")
    images = np.asarray(split.images[rows])
    target = np.asarray(split.targets[rows], dtype=np.float64)
    pred = np.concatenate(
        [policy.infer_batch(images[i : i + BATCH]) for i in range(0, len(rows), BATCH)]
    ).astype(np.float64)
    return regression_metrics(pred, target), pred, target


def settled_opposing_flock(rng: np.random.Generator) -> np.ndarray:
    """(9, 3) positions of the teacher's opposing flock after 40 s, centred at (0, 0, 5)."""
    params = FlockingParams()
    while True:
        p = rng.uniform(-2.0, 2.0, (N_AGENTS, 3)) + [0.0, 0.0, 5.0]
        gap = np.linalg.norm(p[:, None] - p[None], axis=-1) + 9.0 * np.eye(N_AGENTS)
        if gap.min() >= 1.5:
            break
    goals = np.array([[40.0, 0.0, 5.0]] * 5 + [[-40.0, 0.0, 5.0]] * 4)
    for _ in range(400):
        p = p + 0.1 * flocking_command(p, goals, params).final
    return p - (p.mean(axis=0) - [0.0, 0.0, 5.0])


def flock_over_ground(policy: Any, flock: np.ndarray, scene: SceneSpec) -> dict[str, Any]:
    """The error decomposition of one flock drawn at every place of `PLACES` against `scene`."""
    renderer = make_renderer("raycast-aa", scene)
    level = np.tile([1.0, 0.0, 0.0, 0.0], (N_AGENTS, 1))
    teacher = flocking_command(flock, None, FlockingParams()).reynolds
    with World(N_AGENTS) as world:
        answers = np.array(
            [
                policy.infer_batch(renderer.render(world, flock + [dx, dy, 0.0], level))
                for dx, dy in PLACES
            ],
            dtype=np.float64,
        )  # (places, agents, 3)
    error = answers - teacher[None]
    flock_mean = error.mean(axis=1)  # (places, 3)
    return {
        "drone_rmse_mps": float(np.sqrt((error**2).mean())),
        "drone_shape_rms_mps": float(np.sqrt((error.mean(axis=0) ** 2).mean())),
        "drone_ground_rms_mps": float(np.sqrt((error.std(axis=0) ** 2).mean())),
        "flock_mean_error_mps": [float(v) for v in flock_mean.mean(axis=0)],
        "flock_mean_spread_mps": [float(v) for v in flock_mean.std(axis=0)],
    }


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Medians over flocks; the flock-mean error as the median of its absolute value per axis."""
    return {
        "drone_rmse_mps": float(np.median([r["drone_rmse_mps"] for r in rows])),
        "drone_shape_rms_mps": float(np.median([r["drone_shape_rms_mps"] for r in rows])),
        "drone_ground_rms_mps": float(np.median([r["drone_ground_rms_mps"] for r in rows])),
        "flock_mean_abs_error_mps": [
            float(v) for v in np.median([np.abs(r["flock_mean_error_mps"]) for r in rows], axis=0)
        ],
        "flock_mean_spread_mps": [
            float(v) for v in np.median([r["flock_mean_spread_mps"] for r in rows], axis=0)
        ],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="policy file (.pt)")
    parser.add_argument("--dataset", type=Path, default=None, help="default-scene dataset")
    parser.add_argument("--varied", type=Path, default=None, help="its --vary-scene redraw")
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--flocks", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=RESULTS / "ground_robustness.json")
    args = parser.parse_args()
    if (args.dataset is None) != (args.varied is None):
        parser.error("--dataset and --varied go together")
    start = time.perf_counter()
    report: dict[str, Any] = {"benchmark": "ground_robustness", "model": str(args.model)}
    rng = np.random.default_rng(args.seed)
    with load_policy(args.model, threads=1) as policy:
        if args.dataset is not None:
            n_test = open_dataset(args.dataset).split("test").n_samples
            if open_dataset(args.varied).split("test").n_samples != n_test:
                parser.error(f"{args.varied} is not a redraw of {args.dataset}: test sizes differ")
            n = min(args.samples, n_test)
            rows = np.sort(rng.choice(n_test, n, replace=False))
            same: dict[str, Any] = {"samples": n}
            for name, path in (("default", args.dataset), ("varied", args.varied)):
                metrics, pred, target = split_errors(policy, path, rows)
                r2 = [metrics["per_axis"][axis]["r2"] for axis in AXES]
                same[name] = {
                    "dataset": str(path),
                    "rmse_mps": metrics["overall"]["rmse"],
                    "r2": r2,
                    "mean_error_mps": [float(v) for v in (pred - target).mean(axis=0)],
                }
                print(
                    f"test split, {name} scene ({path}): R² x/y/z "
                    + "/".join(f"{v:.3f}" for v in r2)
                    + ", mean error x/y/z "
                    + "/".join(f"{v:+.3f}" for v in same[name]["mean_error_mps"])
                    + " m/s"
                )
            report["same_states"] = same
        scenes: dict[str, list[dict[str, Any]]] = {"default": [], "unseen": [], "flat": []}
        for _ in range(args.flocks):
            flock = settled_opposing_flock(rng)
            scenes["default"].append(flock_over_ground(policy, flock, SceneSpec()))
            scenes["flat"].append(flock_over_ground(policy, flock, SceneSpec(ground_std=0.0)))
            for _ in range(3):
                scenes["unseen"].append(flock_over_ground(policy, flock, random_scene(rng)))
    report["settled_flocks"] = {"flocks": args.flocks, "places": len(PLACES)}
    print("settled opposing flocks (medians over flocks): scene, drone RMSE, its shape part,")
    print("  its ground part, |flock-mean error| x/y/z, its spread over places x/y/z (m/s)")
    for name, rows_ in scenes.items():
        s = summarize(rows_)
        report["settled_flocks"][name] = {"summary": s, "flocks": rows_}
        print(
            f"  {name:8s} {s['drone_rmse_mps']:.3f} {s['drone_shape_rms_mps']:.3f}"
            f" {s['drone_ground_rms_mps']:.3f}  "
            + "/".join(f"{v:.3f}" for v in s["flock_mean_abs_error_mps"])
            + "  "
            + "/".join(f"{v:.3f}" for v in s["flock_mean_spread_mps"])
        )
    report["seed"] = args.seed
    report["wall_s"] = time.perf_counter() - start
    report["machine"] = machine()
    write_report(report, args.out)


if __name__ == "__main__":
    main()
