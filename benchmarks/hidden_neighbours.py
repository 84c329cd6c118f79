"""How much of the teacher's command comes from drones no camera sees, hidden behind nearer ones.

    python benchmarks/hidden_neighbours.py [--seeds 300-307] \
        [--cases opposing-spawn,n12-spawn,opposing]

The teacher sums separation and cohesion over every drone within 20 m; a camera sees only the
drones no nearer drone stands in front of. Where that differs, no network can learn the label
from the image, however much data it gets. This script flies the teacher (perfect positions,
no camera) and, at every control step and for every drone, computes the Reynolds command twice:
over all neighbours, and over the visible ones only (neighbour j is hidden from drone i when
another drone k nearer to i passes within `HIDE_RADIUS_M` of the line of sight from i to j: a
body and arms about 0.4 m across, the rotor discs left out, so a graze counts as visible).
Cases, on training seeds so the evaluation seeds stay unseen:

- `opposing-spawn`: the opposing goals' first 4 s, where the two groups cross (the bar's
  closest-pair criterion is decided there);
- `n12-spawn`: N = 12's first 4 s, the dense spawn spreading out;
- `opposing`: the whole 60 s opposing flight, the settled flock whose order the bar asks for.

Per case: the share of drone-steps with a hidden neighbour, the mean and 99th percentile of
|visible-only - full| (m/s) against the mean |full|, and the visible-only command's component
along the full one (1 where hiding changes nothing), by nearest-neighbour distance. Writes JSON
(default benchmarks/results/hidden_neighbours.json). About 2 s per flight plus the geometry.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
from cnn_latency import RESULTS, write_report
from low_pass_tuning import training_seeds

from companion.flocking import FlockingParams, pairwise_offsets, reynolds_from_offsets
from sim_harness.experiments.machine import machine
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.rollout import fly
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

HIDE_RADIUS_M = 0.2
# case -> (scenario, N, seconds flown: None for the scenario's own limit)
CASES: dict[str, tuple[str, int, float | None]] = {
    "opposing-spawn": ("opposing", 9, 4.0),
    "n12-spawn": ("common", 12, 4.0),
    "opposing": ("opposing", 9, None),
}
NEAREST_BINS_M = ((0.0, 1.0), (1.0, 1.5), (1.5, float("inf")))


def visible(pos: np.ndarray) -> np.ndarray:
    """(N, 3) positions -> (N, N) bool: j can be seen from i (False on the diagonal)."""
    offsets = pairwise_offsets(pos)  # [i, j] = p_j - p_i
    dist = np.linalg.norm(offsets, axis=-1)
    n = pos.shape[0]
    ahead = dist[..., None]
    unit = np.divide(offsets, ahead, out=np.zeros_like(offsets), where=ahead > 0)
    # s[i, j, k]: how far along i's line of sight to j drone k stands; miss[i, j, k]: how far off it
    s = np.einsum("ijc,ikc->ijk", unit, offsets)
    closest = offsets[:, None, :, :] - s[..., None] * unit[:, :, None, :]
    miss = np.linalg.norm(closest, axis=-1)
    blocker = (s > 0) & (s < dist[:, :, None]) & (miss < HIDE_RADIUS_M)
    eye = np.eye(n, dtype=bool)
    blocker &= ~eye[:, None, :] & ~eye[None, :, :] & ~eye[:, :, None]  # i, j and k distinct
    return ~blocker.any(axis=-1) & ~eye


def measure_case(key: str, seeds: list[int]) -> dict[str, Any]:
    scenario_name, n, duration = CASES[key]
    params = FlockingParams()
    everyone = ~np.eye(n, dtype=bool)
    full_norm, diff_norm, along, nearest, hidden = [], [], [], [], []
    for seed in seeds:
        config = ScenarioConfig(
            name=scenario_name, n_agents=n, seed=seed, flocking=params, duration_s=duration
        )
        log = fly(build_scenario(config), TeacherController(params))
        for pos in log.pos_world_enu[:-1]:
            offsets = pairwise_offsets(pos)
            seen = visible(pos)
            sep, coh, _ = reynolds_from_offsets(offsets, everyone, params)
            sep_v, coh_v, _ = reynolds_from_offsets(offsets, seen, params)
            full, vis = sep + coh, sep_v + coh_v
            norm = np.linalg.norm(full, axis=1)
            full_norm.append(norm)
            diff_norm.append(np.linalg.norm(vis - full, axis=1))
            along.append((vis * full).sum(axis=1) / np.maximum(norm**2, 1e-12))
            nearest.append(np.linalg.norm(offsets, axis=-1)[everyone].reshape(n, n - 1).min(axis=1))
            hidden.append((everyone & ~seen).sum(axis=1))
    f, d, a, near, h = (np.concatenate(x) for x in (full_norm, diff_norm, along, nearest, hidden))
    by_distance = []
    for low, high in NEAREST_BINS_M:
        inside = (near >= low) & (near < high)
        if inside.any():
            by_distance.append(
                {
                    "nearest_m": [low, high if np.isfinite(high) else None],
                    "drone_steps": int(inside.sum()),
                    "full_mean_mps": float(f[inside].mean()),
                    "difference_mean_mps": float(d[inside].mean()),
                    "along_mean": float(a[inside].mean()),
                    "hidden_mean": float(h[inside].mean()),
                }
            )
    return {
        "scenario": scenario_name,
        "n_agents": n,
        "duration_s": duration,
        "drone_steps": int(f.size),
        "with_a_hidden_neighbour": float(np.mean(h > 0)),
        "hidden_mean": float(h.mean()),
        "full_mean_mps": float(f.mean()),
        "difference_mean_mps": float(d.mean()),
        "difference_p99_mps": float(np.percentile(d, 99)),
        "along_mean": float(a.mean()),
        "by_nearest": by_distance,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=training_seeds, default=training_seeds("300-307"))
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--out", type=Path, default=RESULTS / "hidden_neighbours.json")
    args = parser.parse_args()
    cases = [c for c in args.cases.split(",") if c]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        parser.error(f"--cases: unknown {', '.join(unknown)}; choose from {', '.join(CASES)}")
    start = time.perf_counter()
    results = {}
    for key in cases:
        r = measure_case(key, args.seeds)
        results[key] = r
        print(
            f"{key}: {r['drone_steps']} drone-steps, {100 * r['with_a_hidden_neighbour']:.1f} % "
            f"with a hidden neighbour; |full| {r['full_mean_mps']:.3f} m/s, |visible - full| "
            f"mean {r['difference_mean_mps']:.4f}, p99 {r['difference_p99_mps']:.3f} m/s; "
            f"along {r['along_mean']:.3f}"
        )
    report = {
        "benchmark": "hidden_neighbours",
        "seeds": args.seeds,
        "hide_radius_m": HIDE_RADIUS_M,
        "cases": results,
        "wall_s": time.perf_counter() - start,
        "machine": machine(),
    }
    write_report(report, args.out)


if __name__ == "__main__":
    main()
