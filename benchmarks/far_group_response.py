"""How a policy's command answers a group of drones behind it, by the group's distance and size.

    python benchmarks/far_group_response.py --model models/swarm_cnn.pt \
        [--distances 2,3,4,5,6,7] [--draws 40] [--seed 0] [--renderer NAME (default: the model's)]

The opposing-goals flock holds one drone between two pulls: its own group around it and the
other group behind it, pulling back along the line between the goals
(`benchmarks/opposing_balance.py`). A drone of the 4-agent group sees 5 drones behind it, a drone
of the 5-agent group sees 4; the teacher's answers differ by that count (cohesion sums the
offsets), and the flock's drift comes from that difference. This probe asks the policy the same
question in a static scene: the observer (level, facing +x, 5 m up) with its own group of
`near` drones 1.2-2.2 m around it, and `far` drones in a 1.5 m cluster centred `D` m behind it
(-x); for each D and each view ((near, far) = (4, 4) and (3, 5): the 5-group's and the
4-group's drone), `--draws` random layouts, rendered and answered by the policy, against the
teacher's Reynolds command for the observer. Reports the mean (and spread) of both along -x;
the policy's slope with D and its (3, 5) minus (4, 4) gap, next to the teacher's, say how much
of the far group's distance and count reach its answer. Writes JSON (default
benchmarks/results/far_group_response.json). A few seconds per distance.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report

from companion.flocking import FlockingParams, flocking_command
from sim_harness.experiments.machine import machine
from sim_harness.experiments.vision_controller import load_policy
from sim_harness.sim.renderers import add_renderer_option, make_renderer, renderer_of_model
from sim_harness.sim.world import World

VIEWS = ((4, 4), (3, 5))  # (own group around the observer, drones behind it)
ALTITUDE_M = 5.0
NEAR_M = (1.2, 2.2)  # own group: distance range from the observer
FAR_SPREAD_M = 1.5  # far group: cube side around its centre
MIN_GAP_M = 0.9  # no two drones of a layout closer than this


def layout(rng: np.random.Generator, near: int, far: int, distance_m: float) -> np.ndarray:
    """Positions (1 + near + far, 3): the observer first, at (0, 0, ALTITUDE_M)."""
    while True:
        pos = [np.array([0.0, 0.0, ALTITUDE_M])]
        for _ in range(near):
            direction = rng.normal(size=3)
            direction[2] *= 0.3  # a flock is flatter than tall
            direction /= np.linalg.norm(direction)
            pos.append(pos[0] + direction * rng.uniform(*NEAR_M))
        centre = pos[0] + np.array([-distance_m, 0.0, 0.0])
        pos += [centre + rng.uniform(-0.5, 0.5, 3) * FAR_SPREAD_M for _ in range(far)]
        p = np.array(pos)
        gaps = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(len(p)) * 1e9
        if gaps.min() >= MIN_GAP_M:
            return p


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="policy file (.pt)")
    parser.add_argument("--distances", default="2,3,4,5,6,7", help="far group's distance (m)")
    parser.add_argument("--draws", type=int, default=40, help="random layouts per distance")
    parser.add_argument("--seed", type=int, default=0)
    add_renderer_option(parser, follows_model=True)
    parser.add_argument("--out", type=Path, default=RESULTS / "far_group_response.json")
    args = parser.parse_args()
    args.renderer = args.renderer or renderer_of_model(args.model)  # as the bar
    distances = [float(d) for d in args.distances.split(",")]
    params = FlockingParams()
    renderer = make_renderer(args.renderer)
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    with load_policy(args.model, threads=1) as policy:
        for near, far in VIEWS:
            n = 1 + near + far
            q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))  # level, facing +x (body = world axes)
            with World(n) as world:
                for distance in distances:
                    scenes = [layout(rng, near, far, distance) for _ in range(args.draws)]
                    images = np.concatenate([renderer.render(world, p, q, [0]) for p in scenes])
                    answer = policy.infer_batch(images).astype(np.float64)
                    no_goal = np.full((n, 3), np.nan)
                    teacher = np.array(
                        [flocking_command(p, no_goal, params).reynolds[0] for p in scenes]
                    )
                    rows.append(
                        {
                            "near": near,
                            "far": far,
                            "distance_m": distance,
                            "teacher_back_mps": float(-teacher[:, 0].mean()),
                            "cnn_back_mps": float(-answer[:, 0].mean()),
                            "cnn_back_std_mps": float(answer[:, 0].std()),
                            "rmse_mps": float(np.sqrt(((answer - teacher) ** 2).sum(1).mean())),
                        }
                    )
    print(f"{args.model}: the answer along -x (towards the far group), mean over {args.draws}")
    print("near far  D (m)   teacher   policy (std)")
    for r in rows:
        print(
            f"{r['near']:4d} {r['far']:4d} {r['distance_m']:5.1f} {r['teacher_back_mps']:9.2f}"
            f" {r['cnn_back_mps']:8.2f} ({r['cnn_back_std_mps']:.2f})"
        )
    summary = {}
    for who in ("teacher", "cnn"):
        key = f"{who}_back_mps"
        by_view = {
            view: np.array([r[key] for r in rows if (r["near"], r["far"]) == view])
            for view in VIEWS
        }
        slope = [float(np.polyfit(distances, by_view[view], 1)[0]) for view in VIEWS]
        gap = by_view[VIEWS[1]] - by_view[VIEWS[0]]
        summary[who] = {"slope_per_m": slope, "count_gap_mps": gap.tolist()}
        print(
            f"{who:8s} slope with D {slope[0]:+.3f} / {slope[1]:+.3f} (m/s per m; views "
            f"{VIEWS[0]}, {VIEWS[1]}); 5-behind minus 4-behind: "
            + " ".join(f"{g:+.2f}" for g in gap)
        )
    report = {
        "benchmark": "far_group_response",
        "model": str(args.model),
        "renderer": args.renderer,
        "draws": args.draws,
        "seed": args.seed,
        "rows": rows,
        "summary": summary,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
