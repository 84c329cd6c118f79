"""Real-time factor of the position-based swarm simulation (no cameras).

    python benchmarks/sim_rtf.py [--agents 9 30] [--sim-seconds 30] [--repeats 5]

Flies the common-goal scenario with the teacher, the migration point placed out of reach so every
repeat simulates the same span, and reports the median over repeats of wall time and real-time
factor (simulated seconds per wall-clock second). Prints a table and writes JSON
(default benchmarks/results/sim_rtf.json).
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from sim_harness.experiments.machine import machine
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.rollout import fly
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario
from sim_harness.sim.world import SimRates

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's


def measure(n_agents: int, sim_seconds: float, repeats: int, rates: SimRates) -> dict[str, float]:
    walls = []
    for seed in range(repeats):
        config = ScenarioConfig(
            name="common", n_agents=n_agents, seed=seed, goal_distance_m=1e4, duration_s=sim_seconds
        )
        scenario = build_scenario(config)
        log = fly(scenario, TeacherController(config.flocking), rates)
        walls.append(log.wall_time_s)
    wall = statistics.median(walls)
    steps = round(sim_seconds * rates.control_hz)
    return {
        "n_agents": n_agents,
        "simulated_s": sim_seconds,
        "repeats": repeats,
        "wall_s_median": wall,
        "wall_s_min": min(walls),
        "wall_s_max": max(walls),
        "real_time_factor_median": sim_seconds / wall,
        "control_step_ms_median": 1e3 * wall / steps,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[9, 30])
    parser.add_argument("--sim-seconds", type=float, default=30.0)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--physics-hz", type=int, default=100)
    parser.add_argument("--control-hz", type=int, default=10)
    parser.add_argument("--out", type=Path, default=RESULTS / "sim_rtf.json")
    args = parser.parse_args()
    rates = SimRates(args.physics_hz, args.control_hz)
    results = [measure(n, args.sim_seconds, args.repeats, rates) for n in args.agents]
    print(f"{'N':>4} {'wall s (median)':>16} {'RTF':>8} {'ms / control step':>18}")
    for r in results:
        print(
            f"{r['n_agents']:>4} {r['wall_s_median']:>16.3f} {r['real_time_factor_median']:>8.1f}"
            f" {r['control_step_ms_median']:>18.3f}"
        )
    report = {
        "benchmark": "sim_rtf",
        "physics_hz": rates.physics_hz,
        "control_hz": rates.control_hz,
        "machine": machine(),
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
