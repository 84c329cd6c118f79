"""HIL swarm benchmark: N unmodified daemons flying the pybullet swarm in real time.

    python benchmarks/hil_swarm.py                       # N = 9, common goal, 60 s, then N scan
    python benchmarks/hil_swarm.py --agents 9 --seconds 60 --scan 3,6,9,12

Per flight: the harness's lateness (physics steps and captures late, frames dropped, render time),
per daemon tick latency p50/p99 and image age (from its MCAP), CPU (% of one core, over the
flight) of each daemon, of the harness (physics + PX4 emulators) and of the camera process
(rendering + pty cameras), and peak memory. The scan flies each N for `--scan-seconds` and
reports the largest N whose captures and frames stayed under 1 % late or dropped. Figures go to
benchmarks/results/hil_swarm.json; docs/BENCHMARKS.md quotes them.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sim_harness.experiments.machine import machine
from sim_harness.hil.swarm import HilConfig, HilSwarm
from sim_harness.learning.shipped import PROJECT_ROOT, SHIPPED_MODEL_PATH
from sim_harness.sim.renderers import add_renderer_option
from sim_harness.sim.rollout import summarize
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


class Sampler:
    """CPU seconds of every process of the run at flight start and end; peak memory at end."""

    def __init__(self) -> None:
        self.cpu: dict[str, list[float]] = {}
        self.peak_mb: dict[str, float] = {}
        self.wall: list[float] = []

    def pids(self, swarm: HilSwarm) -> dict[str, int]:
        out = {"harness": os.getpid()}
        if swarm.camera_pid is not None:
            out["cameras"] = swarm.camera_pid
        for drone in swarm.drones:
            if drone.process is not None:
                out[drone.setup.drone_id] = drone.process.pid
        return out

    def __call__(self, phase: str, swarm: HilSwarm) -> None:
        self.wall.append(time.monotonic())
        for name, pid in self.pids(swarm).items():
            try:
                self.cpu.setdefault(name, []).append(cpu_seconds(pid))
                if phase == "flight_end":
                    self.peak_mb[name] = round(peak_rss_mb(pid), 1)
            except OSError:
                pass

    def cpu_percent(self) -> dict[str, float]:
        if len(self.wall) < 2:  # the flight never started (see "aborted")
            return {}
        wall = self.wall[-1] - self.wall[0]
        return {
            k: round(100 * (v[-1] - v[0]) / wall, 1) for k, v in self.cpu.items() if len(v) == 2
        }


def fly(n: int, seconds: float, seed: int, out: Path, renderer: str) -> dict[str, Any]:
    config = ScenarioConfig(name="common", n_agents=n, seed=seed, duration_s=seconds)
    sampler = Sampler()
    hil = HilConfig(renderer=renderer)
    swarm = HilSwarm(build_scenario(config), SHIPPED_MODEL_PATH, out, hil, on_phase=sampler)
    load_before = round(os.getloadavg()[0], 2)
    run = swarm.run(seconds)
    from sim_harness.hil.results import flight_log_stats

    logs = [flight_log_stats(d.flights_dir) for d in run.drones]
    cpu = sampler.cpu_percent()
    daemons = [cpu[d.setup.drone_id] for d in run.drones if d.setup.drone_id in cpu]
    summary = summarize(run.log)
    return {
        "agents": n,
        "seed": seed,
        "renderer": renderer,
        "seconds_flown": round(float(run.log.time_s[-1]), 1),
        "aborted": run.aborted,
        "load_average_1min_before_after": [load_before, round(os.getloadavg()[0], 2)],
        "lateness": run.lateness.summary(),
        "engage_s": [None if e is None else round(e, 2) for e in run.engage_s],
        "tick_latency_ms": {
            "p50_median": float(np.median([x["tick_latency"]["p50_ms"] for x in logs])),
            "p99_max": float(max(x["tick_latency"]["p99_ms"] for x in logs)),
        },
        "image_age_ms": {
            "p50_median": float(np.median([x["image_age"]["p50_ms"] for x in logs])),
            "p99_max": float(max(x["image_age"]["p99_ms"] for x in logs)),
        },
        "hover_episodes": sum(x["hover_episodes"] for x in logs),
        "cpu_percent_of_one_core": {
            "harness (physics + PX4 emulators)": cpu.get("harness"),
            "camera process (rendering + ptys)": cpu.get("cameras"),
            "daemon median": float(np.median(daemons)) if daemons else None,
            "daemons total": round(float(sum(daemons)), 1),
        },
        "peak_memory_mb": {
            "harness": sampler.peak_mb.get("harness"),
            "camera process": sampler.peak_mb.get("cameras"),
            "daemon max": max(
                (v for k, v in sampler.peak_mb.items() if k.startswith("drone")), default=None
            ),
        },
        "flight": {k: summary[k] for k in ("arrived", "arrival_time_s", "d_min_m", "order_mean")},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=9)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument(
        "--scan", default="3,6,9,12", help="N values for the real-time scan ('' skips)"
    )
    parser.add_argument("--scan-seconds", type=float, default=20.0)
    add_renderer_option(parser)
    parser.add_argument("--out", type=Path, default=None, help="default: hil_swarm_<renderer>")
    args = parser.parse_args()
    args.out = args.out or PROJECT_ROOT / f"benchmarks/results/hil_swarm_{args.renderer}.json"
    tmp = Path(tempfile.mkdtemp(prefix="hil-bench-"))
    results: dict[str, Any] = {
        "machine": machine(),
        "command": "python benchmarks/hil_swarm.py "
        + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items() if k != "out"),
    }
    main_run = fly(args.agents, args.seconds, args.seed, tmp / f"n{args.agents}", args.renderer)
    results["main"] = main_run
    print(json.dumps(main_run, indent=1), flush=True)
    scan = []
    for n in [int(x) for x in args.scan.split(",") if x.strip()]:
        entry = fly(n, args.scan_seconds, args.seed, tmp / f"scan{n}", args.renderer)
        lat = entry["lateness"]
        entry["real_time"] = (
            lat["captures_late_fraction"] < 0.01 and lat["frames_dropped_fraction"] < 0.01
        )
        scan.append(entry)
        print(f"N = {n}: captures late {100 * lat['captures_late_fraction']:.2f} %, physics late "
              f"{100 * lat['physics_late_fraction']:.2f} %, dropped "
              f"{100 * lat['frames_dropped_fraction']:.2f} %, real time: {entry['real_time']}",
              flush=True)  # fmt: skip
    results["scan"] = scan
    fits = [e["agents"] for e in scan if e["real_time"]]
    results["largest_real_time_n"] = max(fits) if fits else None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"largest N in real time (< 1 % late captures and dropped frames): "
          f"{results['largest_real_time_n']}; wrote {args.out}")  # fmt: skip


if __name__ == "__main__":
    main()
