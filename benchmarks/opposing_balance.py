"""Why a vision flock with opposing goals drifts slower than the teacher's: where it settles.

    python benchmarks/opposing_balance.py --model models/swarm_cnn.pt [--seeds 900-903] \
        [--settle 10] [--renderer NAME (default: the model's)]

With opposing goals (5 agents to one point, 4 to the opposite one) a settled flock moves as one
body at a drift d along the majority's goal direction u, so each drone's Reynolds command along u
is fixed by d: d - k_mig for the majority's drones (their migration term is +k_mig), d + k_mig for
the minority's. The teacher's commands sum to zero (separation and cohesion are pairwise
antisymmetric), which gives d = k_mig (5 - 4) / 9 = 0.111 m/s. A policy settles wherever its
answers to the two groups' views differ by 2 d: the drift is half its "count gap", how much harder
a drone with 5 drones behind it pulls back than one with 4 behind it.

Flies the CNN unfiltered on training seeds (< 1000) and, at every control step after `--settle`
seconds, evaluates the teacher's Reynolds command at the state the CNN flew into. The CNN's own
Reynolds command is the logged setpoint minus the agent's migration term (steps where the speed
cap acted are left out). Per group: the mean of both along u; the count gap of both (minority
minus the majority's magnitude: the CNN's is 2 d by the argument above, the teacher's at the same
states what it would need); the sum over the agents (the teacher's is 0) and the measured drift.
And why the order parameter stays low: the centroid's speed next to the drones' motion relative
to it (RMS per axis; the teacher's flock: 0.111 and about 0.01 m/s). Prints a table and writes
JSON (default benchmarks/results/opposing_balance.json). One thread; about a minute per flight.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report
from low_pass_tuning import training_seeds

from companion.flocking import flocking_command
from sim_harness.experiments.machine import machine
from sim_harness.experiments.runner import Job, fly_job
from sim_harness.experiments.suites import SuiteConfig
from sim_harness.experiments.vision_controller import load_policy
from sim_harness.sim.renderers import add_renderer_option, renderer_of_model
from sim_harness.sim.rollout import FlightLog

CAP_MARGIN_MPS = 1e-6  # a setpoint this close to v_max was capped: its Reynolds part is unknown


def _gap(along: np.ndarray, groups: np.ndarray, majority: int) -> float:
    """Minority's mean answer along u minus the magnitude of the majority's."""
    return float(along[:, groups != majority].mean() + along[:, groups == majority].mean())


def balance(log: FlightLog, settle_s: float) -> dict[str, Any]:
    """The per-group and summed Reynolds commands of one opposing-goal flight (module docstring)."""
    scenario = log.scenario
    params = scenario.config.flocking
    groups = scenario.groups
    majority = int(np.bincount(groups).argmax())
    teacher, cnn, direction = [], [], []
    for k in np.nonzero(log.time_s >= settle_s)[0]:
        setpoint = log.setpoint_world_enu[k]
        if not np.isfinite(setpoint).all():
            continue  # the last row: no command was sent after it
        command = flocking_command(log.pos_world_enu[k], scenario.migration_points, params)
        if (np.linalg.norm(setpoint, axis=1) >= params.v_max_mps - CAP_MARGIN_MPS).any():
            continue
        teacher.append(command.reynolds)
        cnn.append(setpoint - command.migration)
        mig = command.migration[groups == majority].mean(axis=0)
        direction.append(mig / np.linalg.norm(mig))
    if not teacher:
        raise ValueError(f"no uncapped step after {settle_s} s")
    u = np.array(direction)[:, None, :]  # (T, 1, 3): the majority's goal direction, per step
    along_teacher = (np.array(teacher) * u).sum(axis=-1)  # (T, N)
    along_cnn = (np.array(cnn) * u).sum(axis=-1)
    settled = log.time_s >= settle_s
    centroid = log.pos_world_enu[settled].mean(axis=1)
    span_s = log.time_s[settled][-1] - log.time_s[settled][0]
    drift = float((centroid[-1] - centroid[0]) @ u[-1, 0] / span_s)
    n, n_major = len(groups), int((groups == majority).sum())
    return {
        "seed": scenario.config.seed,
        "steps": len(teacher),
        "groups": [
            {
                "agents": int((groups == g).sum()),
                "majority": bool(g == majority),
                "teacher_along_mps": float(along_teacher[:, groups == g].mean()),
                "cnn_along_mps": float(along_cnn[:, groups == g].mean()),
            }
            for g in np.unique(groups)
        ],
        "sum_teacher_mps": float(along_teacher.sum(axis=1).mean()),
        "sum_cnn_mps": float(along_cnn.sum(axis=1).mean()),
        "count_gap_cnn_mps": _gap(along_cnn, groups, majority),
        "count_gap_teacher_mps": _gap(along_teacher, groups, majority),
        "drift_mps": drift,
        "teacher_drift_mps": params.k_mig * (2 * n_major - n) / n,
        "order_mean_settled": float(np.nanmean(log.order[settled])),
        **_internal_motion(log.vel_world_enu[settled]),
    }


def _internal_motion(vel: np.ndarray) -> dict[str, float]:
    """How fast the drones move relative to the flock's centroid (per axis, RMS) next to the
    centroid's own speed: the order parameter is the alignment of headings, so it stays low while
    the internal motion is comparable to the drift, however well the flock holds together."""
    centroid = vel.mean(axis=1, keepdims=True)
    return {
        "centroid_speed_mps": float(np.linalg.norm(centroid, axis=-1).mean()),
        "internal_rms_per_axis_mps": float(np.sqrt(((vel - centroid) ** 2).mean())),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="policy file (.pt)")
    parser.add_argument("--seeds", default="900-903", help="training-range seeds (< 1000)")
    parser.add_argument("--settle", type=float, default=10.0, help="skip the start (s)")
    add_renderer_option(parser, follows_model=True)
    parser.add_argument("--out", type=Path, default=RESULTS / "opposing_balance.json")
    args = parser.parse_args()
    args.renderer = args.renderer or renderer_of_model(args.model)  # as the bar
    seeds = training_seeds(args.seeds)
    config = SuiteConfig(
        suite="bar",
        model_path=args.model,
        low_pass_cutoff_hz=None,
        renderer=args.renderer,
        experiments=("opposing",),
    )
    start = time.perf_counter()
    rows = []
    with load_policy(args.model, threads=1) as policy:
        for seed in seeds:
            row = balance(fly_job(Job("opposing", "cnn", seed), config, policy).log, args.settle)
            rows.append(row)
            minority, majority = sorted(row["groups"], key=lambda g: g["majority"])
            print(
                f"seed {seed}: majority {majority['cnn_along_mps']:+.3f} (teacher at the state "
                f"{majority['teacher_along_mps']:+.3f}), minority {minority['cnn_along_mps']:+.3f}"
                f" ({minority['teacher_along_mps']:+.3f}); count gap {row['count_gap_cnn_mps']:.3f}"
                f" ({row['count_gap_teacher_mps']:.3f}); drift {row['drift_mps']:.3f} m/s, order "
                f"{row['order_mean_settled']:.2f} (centroid speed {row['centroid_speed_mps']:.3f},"
                f" internal motion {row['internal_rms_per_axis_mps']:.3f} m/s per axis)",
                flush=True,
            )
    teacher_drift = rows[0]["teacher_drift_mps"]
    summary = {
        "teacher_drift_mps": teacher_drift,
        "drift_median_mps": statistics.median(r["drift_mps"] for r in rows),
        "count_gap_cnn_median_mps": statistics.median(r["count_gap_cnn_mps"] for r in rows),
        "order_settled_mean": statistics.fmean(r["order_mean_settled"] for r in rows),
    }
    print(
        f"median drift {summary['drift_median_mps']:.3f} m/s (teacher {teacher_drift:.3f}); "
        f"the CNN's count gap {summary['count_gap_cnn_median_mps']:.3f} m/s "
        f"(teacher {2 * teacher_drift:.3f})"
    )
    report = {
        "benchmark": "opposing_balance",
        "model": str(args.model),
        "renderer": args.renderer,
        "settle_s": args.settle,
        "seeds": rows,
        "summary": summary,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
