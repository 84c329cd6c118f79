"""The HIL bar: nine daemons against the in-process CNN controller, on the same seeds and model.

    python benchmarks/hil_vs_inprocess.py --seeds 1000-1004 --agents 9 --seconds 60

For each seed: `swarm-sim hil --compare` (the daemons, then the in-process CNN on the same seed).
Reports per seed arrival, closest pair, order and speed for both, whether each HIL run was valid
(the harness kept up with real time), and whether the HIL arrival time and closest pair fall
inside the spread (min..max) of the in-process flights.
JSON: benchmarks/results/hil_bar_<renderer>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from sim_harness.hil.cli import fly_hil
from sim_harness.learning.shipped import PROJECT_ROOT, SHIPPED_MODEL_PATH
from sim_harness.sim.renderers import add_renderer_option
from sim_harness.sim.scenarios import ScenarioConfig


def seed_list(text: str) -> list[int]:
    if "-" in text:
        first, last = (int(x) for x in text.split("-"))
        return list(range(first, last + 1))
    return [int(x) for x in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="1000-1004")
    parser.add_argument("--agents", type=int, default=9)
    parser.add_argument("--seconds", type=float, default=60.0)
    add_renderer_option(parser)
    parser.add_argument("--out", type=Path, default=None, help="default: hil_bar_<renderer>")
    args = parser.parse_args()
    args.out = args.out or PROJECT_ROOT / f"benchmarks/results/hil_bar_{args.renderer}.json"
    tmp = Path(tempfile.mkdtemp(prefix="hil-bar-"))
    rows: list[dict[str, Any]] = []
    for seed in seed_list(args.seeds):
        config = ScenarioConfig(
            name="common", n_agents=args.agents, seed=seed, duration_s=args.seconds
        )
        load = round(os.getloadavg()[0], 2)
        doc = fly_hil(
            config,
            SHIPPED_MODEL_PATH,
            tmp / f"s{seed}",
            args.seconds,
            compare=True,
            renderer=args.renderer,
        )
        hil, ref = doc["summary"], doc["compare"]["in_process"]
        row = {
            "seed": seed,
            "load_average_before": load,
            "valid": doc["valid"],
            "lateness": {
                k: doc["lateness"][k]
                for k in (
                    "physics_late_fraction",
                    "captures_late_fraction",
                    "frames_dropped_fraction",
                )
            },
            "hil": {
                k: hil[k]
                for k in ("arrived", "arrival_time_s", "d_min_m", "order_mean", "mean_speed_mps")
            },
            "in_process": {
                k: ref[k]
                for k in ("arrived", "arrival_time_s", "d_min_m", "order_mean", "mean_speed_mps")
            },
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    ref_arrival = [r["in_process"]["arrival_time_s"] for r in rows if r["in_process"]["arrived"]]
    ref_dmin = [r["in_process"]["d_min_m"] for r in rows]
    spread = {
        "in_process_arrival_s": [min(ref_arrival), max(ref_arrival)] if ref_arrival else None,
        "in_process_d_min_m": [min(ref_dmin), max(ref_dmin)],
    }
    for r in rows:
        h = r["hil"]
        r["inside_spread"] = {
            "arrival": bool(
                ref_arrival
                and h["arrived"]
                and min(ref_arrival) <= h["arrival_time_s"] <= max(ref_arrival)
            ),
            "d_min": min(ref_dmin) <= h["d_min_m"] <= max(ref_dmin),
        }
    results = {
        "command": f"python benchmarks/hil_vs_inprocess.py --seeds {args.seeds} "
        f"--agents {args.agents} --seconds {args.seconds:g} --renderer {args.renderer}",
        "renderer": args.renderer,
        "spread": spread,
        "runs": rows,
        "bar": {
            "all_hil_arrived": all(r["hil"]["arrived"] for r in rows),
            "no_hil_pair_under_1m": all(r["hil"]["d_min_m"] >= 1.0 for r in rows),
            "all_valid": all(r["valid"] for r in rows),
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps({"spread": spread, "bar": results["bar"]}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
