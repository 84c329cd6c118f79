"""Closed-loop real-time factor with the CNN flying the swarm: rendering, inference, physics.

    python benchmarks/closed_loop_rtf.py [--model models/swarm_cnn.pt] [--agents 9 12]
        [--sim-seconds 10] [--repeats 2] [--threads 1]
        [--renderer pybullet|raycast]   # raycast writes closed_loop_rtf_raycast.json

Flies the common-goal scenario with the CNN controller (all agents' images rendered each control
step by pybullet's TinyRenderer, or by the batched ray caster with --renderer raycast; one batched
inference), the migration point out of reach so every
repeat simulates the same span. Reports, per control step (median over repeats): wall time of
rendering, of inference, of physics (vehicle model + contact checks), of everything else, and the
real-time factor (simulated seconds per wall-clock second). Prints a table and writes JSON
(default benchmarks/results/closed_loop_rtf.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from pathlib import Path
from typing import Any

from sim_harness.experiments.machine import machine
from sim_harness.experiments.vision_controller import (
    VisionControlConfig,
    VisionController,
    load_policy,
)
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH
from sim_harness.sim.renderers import RENDERERS, make_renderer
from sim_harness.sim.rollout import fly
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario
from sim_harness.sim.world import SimRates

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's

STAGES = ("render", "inference", "physics", "other")


def measure(
    controller: VisionController,
    n_agents: int,
    sim_seconds: float,
    repeats: int,
    rates: SimRates,
    renderer: str = "pybullet",
) -> dict[str, Any]:
    per_repeat: list[dict[str, float]] = []
    for seed in range(repeats):
        config = ScenarioConfig(
            name="common",
            n_agents=n_agents,
            seed=1000 + seed,
            goal_distance_m=1e4,
            duration_s=sim_seconds,
        )
        log = fly(build_scenario(config), controller, rates, renderer=make_renderer(renderer))
        steps = log.n_steps - 1
        stage = log.stage_time_s
        other = log.wall_time_s - stage["render"] - stage["control"] - stage["physics"]
        other += stage["control"] - stage["inference"]  # composing the command, observing
        ms = {
            "render": stage["render"],
            "inference": stage["inference"],
            "physics": stage["physics"],
            "other": other,
        }
        per_repeat.append(
            {
                **{f"{k}_ms_per_step": 1e3 * v / steps for k, v in ms.items()},
                "wall_s": log.wall_time_s,
                "real_time_factor": float(log.time_s[-1]) / log.wall_time_s,
            }
        )
    keys = per_repeat[0].keys()
    result: dict[str, Any] = {"n_agents": n_agents, "simulated_s": sim_seconds, "repeats": repeats}
    for key in keys:
        result[f"{key}_median"] = statistics.median(r[key] for r in per_repeat)
    result["render_ms_per_agent_median"] = result["render_ms_per_step_median"] / n_agents
    result["per_repeat"] = per_repeat
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=SHIPPED_MODEL_PATH)
    parser.add_argument("--agents", type=int, nargs="+", default=[9, 12])
    parser.add_argument("--sim-seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    parser.add_argument("--renderer", default="pybullet", choices=RENDERERS)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    suffix = "" if args.renderer == "pybullet" else f"_{args.renderer}"
    args.out = args.out or RESULTS / f"closed_loop_rtf{suffix}.json"
    rates = SimRates()
    load_before = os.getloadavg()[0]
    with load_policy(args.model, threads=args.threads) as policy:
        controller = VisionController(policy, VisionControlConfig(), rates.control_dt_s)
        results = [
            measure(controller, n, args.sim_seconds, args.repeats, rates, args.renderer)
            for n in args.agents
        ]
        sha256 = policy.sha256
    print(
        f"{'N':>4} {'render ms':>10} {'infer ms':>9} {'physics ms':>11} {'other ms':>9}"
        f" {'ms/step':>8} {'RTF':>6}   (per control step, medians)"
    )
    for r in results:
        total = sum(r[f"{s}_ms_per_step_median"] for s in STAGES)
        print(
            f"{r['n_agents']:>4} {r['render_ms_per_step_median']:>10.1f}"
            f" {r['inference_ms_per_step_median']:>9.1f} {r['physics_ms_per_step_median']:>11.1f}"
            f" {r['other_ms_per_step_median']:>9.1f} {total:>8.1f}"
            f" {r['real_time_factor_median']:>6.2f}"
        )
    report = {
        "benchmark": "closed_loop_rtf",
        "renderer": args.renderer,
        "model": {"path": str(args.model), "sha256": sha256},
        "physics_hz": rates.physics_hz,
        "control_hz": rates.control_hz,
        "torch_threads": args.threads,
        # Other jobs share the cores: a load above the core count inflates every stage.
        "machine": machine(load_average_1m={"before": load_before, "after": os.getloadavg()[0]}),
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
