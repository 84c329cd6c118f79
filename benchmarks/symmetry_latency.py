"""What the symmetrized policy costs on the drone: batch-1 latency per symmetry group, one thread.

    python benchmarks/symmetry_latency.py [--model models/swarm_cnn.pt] [--calls 400]

The same weights (`--model`'s eager weights, else a seeded untrained ResNet-8) exported with each
group of `sim_harness.learning.symmetry` (none: 1 view, mirror: 2, c4: 4, d4: 8 per image), each
loaded as the drone loads it (oneDNN Graph fuser on, warmed up) and timed call by call, groups
interleaved in rounds so that load changes hit them alike. Prints p50 / p99 and the ratio to
`none`; writes JSON (default benchmarks/results/symmetry_latency.json) with the load average.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from cnn_latency import (
    RESULTS,
    WARMUP_CALLS,
    batch1_report,
    calibrated_model,
    load_script,
    summarize,
    time_calls,
    write_report,
)

from companion.model_file import enable_graph_fusion
from sim_harness.learning.export import export_policy, load_eager_model
from sim_harness.learning.symmetry import GROUPS


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=None, help="policy file (default: untrained)")
    parser.add_argument("--calls", type=int, default=400, help="calls per group")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=RESULTS / "symmetry_latency.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    model = load_eager_model(args.model)[0] if args.model else calibrated_model()
    image = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (1, 64, 384), np.uint8))
    samples: dict[str, list[float]] = {group: [] for group in GROUPS}
    with tempfile.TemporaryDirectory() as tmp, torch.inference_mode():
        enable_graph_fusion(True)
        policies = {}
        for group in GROUPS:
            path = Path(tmp) / f"{group}.pt"
            export_policy(
                model, path, {"id": "benchmark"}, None, {"command": "bench"}, symmetry=group
            )
            policies[group] = load_script(path)
            time_calls(policies[group], image, WARMUP_CALLS)
        for _ in range(args.rounds):
            for group, policy in policies.items():
                samples[group] += time_calls(policy, image, max(args.calls // args.rounds, 1))
        enable_graph_fusion(False)
    results = {group: summarize(s) for group, s in samples.items()}
    base = results["none"]["p50_ms"]
    print(f"{'group':8} {'views':>5} {'p50 ms':>8} {'p99 ms':>8} {'p50 / none':>10}")
    for group, r in results.items():
        r["views"] = len(GROUPS[group])
        r["p50_vs_none"] = r["p50_ms"] / base
        print(
            f"{group:8} {r['views']:5d} {r['p50_ms']:8.3f} {r['p99_ms']:8.3f} "
            f"{r['p50_vs_none']:9.2f}x"
        )
    model_name = str(args.model) if args.model else "untrained ResNet-8 (seed 0)"
    report = batch1_report("symmetry_latency", dict(results), load_before, model=model_name)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
