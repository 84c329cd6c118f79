"""What a policy file costs on the drone: batch-1 latency of exported policies, one thread.

    python benchmarks/policy_latency.py models/swarm_cnn.pt models/candidates/round47/swarm_cnn.pt

Each file is loaded as the drone loads it (`load_model`: hash and metadata verified; oneDNN
Graph fuser on, warmed up) and timed call by call on one seeded image, the files interleaved in
rounds so that load changes hit them alike. An ensemble (`swarm-sim ensemble`) calls every
member, so it costs their sum. Prints p50 / p99 and the ratio to the first file; writes JSON
(default benchmarks/results/policy_latency.json) with the machine and its load average.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch
from cnn_latency import (
    RESULTS,
    WARMUP_CALLS,
    batch1_report,
    summarize,
    time_calls,
    write_report,
)

from companion.model_file import enable_graph_fusion, load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, nargs="+", help="policy files (.pt)")
    parser.add_argument("--calls", type=int, default=400, help="calls per file")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=RESULTS / "policy_latency.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    image = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (1, 64, 384), np.uint8))
    names = [str(path) for path in args.models]
    samples: dict[str, list[float]] = {name: [] for name in names}
    views: dict[str, int] = {}
    with torch.inference_mode():
        enable_graph_fusion(True)
        policies = {}
        for name, path in zip(names, args.models, strict=True):
            loaded = load_model(path)
            symmetry = loaded.metadata.get("runtime", {}).get("symmetry", {})
            views[name] = int(symmetry.get("views", 1))
            policies[name] = loaded.module
            time_calls(loaded.module, image, WARMUP_CALLS)
        for _ in range(args.rounds):
            for name, policy in policies.items():
                samples[name] += time_calls(policy, image, max(args.calls // args.rounds, 1))
        enable_graph_fusion(False)
    results = {name: summarize(s) for name, s in samples.items()}
    base = results[names[0]]["p50_ms"]
    print(f"{'p50 ms':>8} {'p99 ms':>8} {'vs first':>8} {'calls/image':>11}  policy")
    for name, r in results.items():
        r["network_calls_per_image"] = views[name]
        r["p50_vs_first"] = r["p50_ms"] / base
        print(
            f"{r['p50_ms']:8.2f} {r['p99_ms']:8.2f} {r['p50_vs_first']:7.2f}x "
            f"{views[name]:11d}  {name}"
        )
    report = batch1_report("policy_latency", dict(results), load_before)
    write_report(report, args.out)


if __name__ == "__main__":
    main()
