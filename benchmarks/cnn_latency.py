"""CNN inference latency on one CPU thread: eager against the exported policy, batch 1 and 9.

    python benchmarks/cnn_latency.py [--model models/swarm_cnn.pt] [--compare OLD.pt]
                                     [--calls 2000] [--rounds 10]

Variants, all the same network and weights (`--model`'s eager weights, else a seeded untrained
ResNet-8 whose batch norms are calibrated on random images: latency does not depend on weights):

- eager NCHW: the `nn.Module` in PyTorch's default contiguous layout
- eager channels_last: the `nn.Module` as `build_model` makes it
- exported, fused: the policy file as the drone runs it: `torch.jit.load` after
  `companion.model_file.enable_graph_fusion` (oneDNN Graph), warmed up
- exported, unfused: the same file under a plain `torch.jit.load`
- `--compare FILE`, unfused: another policy file as it was run before the fuser was used (e.g. the
  previous export: `git show REV:models/swarm_cnn.pt > old.pt`); its own weights

The fuser is process-wide, but a module keeps the plan compiled at its first calls: unfused
variants are warmed up with it off, fused ones with it on, then all are timed with it on. Each
variant records whether its plan really is fused. Calls are timed one by one with
`time.perf_counter` inside `torch.inference_mode`, variants interleaved in `--rounds` rounds so
that load changes hit them alike. Bar (issue 4): exported batch-1 p99 <= 2 ms and >= 2x faster
than eager. Prints a table and writes JSON (default benchmarks/results/cnn_latency.json), the
machine's load average included.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from companion.model_file import enable_graph_fusion, graph_is_fused
from sim_harness.experiments.machine import machine
from sim_harness.learning.export import export_policy, load_eager_model
from sim_harness.learning.model import DroNet, build_model

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's

Policy = Callable[[torch.Tensor], torch.Tensor]
WARMUP_CALLS = 50  # compiles the fused plan (2 calls), then lets allocator and caches settle


def calibrated_model(seed: int = 0) -> DroNet:
    """A seeded untrained network with batch-norm statistics from random images."""
    torch.manual_seed(seed)
    model = build_model(pixel_mean=185.0, pixel_std=36.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
        model.train()
        model(torch.randint(0, 256, (64, 64, 384), dtype=torch.uint8))
    return model.eval()


def load_script(path: Path) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        module: torch.jit.ScriptModule = torch.jit.load(str(path))
    return module


def warmed_variants(
    model: DroNet, policy: Path, compare: Path | None, images: torch.Tensor
) -> tuple[dict[str, Policy], dict[str, bool]]:
    """Fresh variants for one batch size, each warmed up on `images`; and whether each is fused."""
    nchw = copy.deepcopy(model).to(memory_format=torch.contiguous_format).eval()
    nchw.standardize.forward = lambda x: (
        (x.unsqueeze(1).float() - model.standardize.pixel_mean) / model.standardize.pixel_std
    )
    unfused: dict[str, Policy] = {
        "eager NCHW": nchw,
        "eager channels_last": model,
        "exported, unfused": load_script(policy),
    }
    if compare is not None:
        unfused[f"compare {compare.name}, unfused"] = load_script(compare)
    fused: dict[str, Policy] = {"exported, fused": load_script(policy)}
    is_fused: dict[str, bool] = {}
    for setting, group in ((False, unfused), (True, fused)):
        enable_graph_fusion(setting)
        for name, fn in group.items():
            time_calls(fn, images, WARMUP_CALLS)
            is_fused[name] = graph_is_fused() if isinstance(fn, torch.jit.ScriptModule) else False
    order = ["eager NCHW", "eager channels_last", "exported, fused", "exported, unfused"]
    fns = {**unfused, **fused}
    return {name: fns[name] for name in order + sorted(set(fns) - set(order))}, is_fused


def time_calls(fn: Policy, images: torch.Tensor, calls: int) -> list[float]:
    out = []
    for _ in range(calls):
        start = time.perf_counter()
        fn(images)
        out.append(time.perf_counter() - start)
    return out


def summarize(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "calls": int(ms.size),
        "p50_ms": float(np.percentile(ms, 50)),
        "p90_ms": float(np.percentile(ms, 90)),
        "p99_ms": float(np.percentile(ms, 99)),
        "mean_ms": float(ms.mean()),
        "min_ms": float(ms.min()),
    }


def time_variants(
    model: DroNet, policy: Path, args: argparse.Namespace, rng: np.random.Generator
) -> tuple[dict[str, dict[str, dict[str, float]]], dict[str, dict[str, bool]]]:
    """Latency summaries and fused flags per batch size and variant."""
    results: dict[str, dict[str, dict[str, float]]] = {}
    fused: dict[str, dict[str, bool]] = {}
    for batch, calls in ((1, args.calls), (9, max(args.calls // 5, 50))):
        images = torch.from_numpy(rng.integers(0, 256, (batch, 64, 384), dtype=np.uint8))
        fns, fused[f"batch_{batch}"] = warmed_variants(model, policy, args.compare, images)
        samples: dict[str, list[float]] = {name: [] for name in fns}
        for _ in range(args.rounds):
            for name, fn in fns.items():
                samples[name] += time_calls(fn, images, max(calls // args.rounds, 1))
        results[f"batch_{batch}"] = {name: summarize(s) for name, s in samples.items()}
    return results, fused


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=None, help="policy file (default: untrained)")
    parser.add_argument("--compare", type=Path, default=None, help="another policy file (unfused)")
    parser.add_argument("--calls", type=int, default=2000, help="batch-1 calls per variant")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=RESULTS / "cnn_latency.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    model = load_eager_model(args.model)[0] if args.model else calibrated_model()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        policy = Path(tmp) / "policy.pt"
        export_policy(model, policy, {"id": "benchmark"}, None, {"command": "cnn_latency.py"})
        with torch.inference_mode():
            results, fused = time_variants(model, policy, args, rng)
    enable_graph_fusion(False)
    load_after = os.getloadavg()
    b1 = results["batch_1"]
    exported = b1["exported, fused"]
    speedup = {
        "p50_vs_eager_nchw": b1["eager NCHW"]["p50_ms"] / exported["p50_ms"],
        "p99_vs_eager_nchw": b1["eager NCHW"]["p99_ms"] / exported["p99_ms"],
        "p50_vs_eager_channels_last": b1["eager channels_last"]["p50_ms"] / exported["p50_ms"],
        "p50_vs_unfused": b1["exported, unfused"]["p50_ms"] / exported["p50_ms"],
        "p99_vs_unfused": b1["exported, unfused"]["p99_ms"] / exported["p99_ms"],
    }
    for name in b1:
        if name.startswith("compare "):
            speedup["p50_vs_compare"] = b1[name]["p50_ms"] / exported["p50_ms"]
            speedup["p99_vs_compare"] = b1[name]["p99_ms"] / exported["p99_ms"]
    bar = {
        "exported_p99_le_2ms": exported["p99_ms"] <= 2.0,
        "exported_2x_faster_than_eager": speedup["p50_vs_eager_nchw"] >= 2.0,
    }
    print(f"{'':36} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8}")
    for key, table in results.items():
        print(key.replace("_", " "))
        for name, r in table.items():
            flag = " (fused)" if fused[key].get(name) else ""
            print(f"  {name + flag:34} {r['p50_ms']:8.3f} {r['p90_ms']:8.3f} {r['p99_ms']:8.3f}")
    print(f"exported vs eager NCHW, batch 1: {speedup['p50_vs_eager_nchw']:.2f}x (p50)")
    print(f"bar: {bar}; load average {load_before[0]:.1f} -> {load_after[0]:.1f}")
    report = {
        "benchmark": "cnn_latency",
        "threads": 1,
        "model": str(args.model) if args.model else "untrained ResNet-8 (seed 0)",
        "compare": str(args.compare) if args.compare else None,
        "results": results,
        "fused": fused,
        "speedup": speedup,
        "bar": bar,
        "load_average_1min": [load_before[0], load_after[0]],
        "machine": machine(),
    }
    write_report(report, args.out)


def batch1_report(
    benchmark: str, results: dict[str, object], load_before: tuple[float, ...], **extra: object
) -> dict[str, object]:
    """The JSON of a batch-1, one-thread, fused latency benchmark: its figures, the machine and
    the 1-minute load average before and after."""
    return {
        "benchmark": benchmark,
        "threads": 1,
        "batch": 1,
        "graph_fusion": True,
        **extra,
        "results": results,
        "load_average_1min": [load_before[0], os.getloadavg()[0]],
        "machine": machine(),
    }


def write_report(report: dict[str, object], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
