"""Rendering cost per control step (all N agents' six faces) versus N, both renderers.

    python benchmarks/render_cost.py [--agents 3 9 30 100] [--repeats 5]

The paper's common-goal spawn for N agents (its density kept as N grows), small random tilts, and
every agent's strip rendered once per repeat by `PyBulletRenderer` and by `RaycastRenderer` (its
numba kernels, and its numpy path).
Reports wall and CPU (process) milliseconds per step, medians over repeats (pybullet's N = 100 step
takes seconds: at most 2 repeats), their ratio, and the raycaster's split between the environment
(ground and sky; numpy, as pybullet's path) and the drones. Writes JSON (default
benchmarks/results/render_cost.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.frames import quat_from_euler_zyx, quat_to_rotmat
from sim_harness.experiments.machine import machine
from sim_harness.sim.raycast import RaycastRenderer
from sim_harness.sim.render import PyBulletRenderer, Renderer, camera_poses
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario
from sim_harness.sim.world import World

RESULTS = Path(__file__).resolve().parent / "results"


def timed(fn: Any, args: tuple[Any, ...], repeats: int) -> dict[str, float]:
    fn(*args)  # warm-up
    wall, cpu = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        fn(*args)
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return {"wall_ms": 1e3 * statistics.median(wall), "cpu_ms": 1e3 * statistics.median(cpu)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--agents", type=int, nargs="+", default=[3, 9, 30, 100])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=RESULTS / "render_cost.json")
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    rows = []
    for n in args.agents:
        rng = np.random.default_rng(n)
        pos = build_scenario(ScenarioConfig(n_agents=n, seed=1)).initial_pos_world_enu
        q = np.stack(
            [quat_from_euler_zyx(*rng.uniform(-0.2, 0.2, 2), rng.uniform(-3, 3)) for _ in pos]
        )
        row: dict[str, Any] = {"n_agents": n}
        with World(n) as world:
            renderers: dict[str, Renderer] = {
                "pybullet": PyBulletRenderer(),
                "raycast": RaycastRenderer(),  # compiled loops when numba is installed
                "raycast_numpy": RaycastRenderer(compiled=False),
            }
            for name, renderer in renderers.items():
                reps = args.repeats if name != "pybullet" or n <= 30 else min(args.repeats, 2)
                row[name] = timed(renderer.render, (world, pos, q), reps)
            raycast = RaycastRenderer(compiled=False)
            eyes, _, _ = camera_poses(pos, q)
            rot = quat_to_rotmat(q)
            row["raycast_environment"] = timed(raycast.environment.shade, (eyes, rot), args.repeats)
        for unit in ("wall_ms", "cpu_ms"):
            row[f"speedup_{unit[:-3]}"] = row["pybullet"][unit] / row["raycast"][unit]
        rows.append(row)
        print(
            f"N={n:4d}  pybullet {row['pybullet']['wall_ms']:8.1f} ms"
            f" (cpu {row['pybullet']['cpu_ms']:7.1f})  raycast {row['raycast']['wall_ms']:7.1f} ms"
            f" (cpu {row['raycast']['cpu_ms']:6.1f}; numpy {row['raycast_numpy']['cpu_ms']:6.1f};"
            " environment"
            f" {row['raycast_environment']['cpu_ms']:5.1f})  x{row['speedup_cpu']:.1f} (cpu)",
            flush=True,
        )
    result = {
        "benchmark": "render_cost",
        "machine": machine(load_average_1m={"before": load_before, "after": os.getloadavg()[0]}),
        "results": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
