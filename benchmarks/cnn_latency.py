"""CNN inference latency on one CPU thread: eager against the exported policy, batch 1 and 9.

    python benchmarks/cnn_latency.py [--model models/swarm_cnn.pt] [--calls 2000] [--rounds 10]

Variants, all the same network and weights (`--model`'s eager weights, else a seeded untrained
ResNet-8 whose batch norms are calibrated on random images: latency does not depend on weights):

- eager NCHW: the `nn.Module` in PyTorch's default contiguous layout
- eager channels_last: the `nn.Module` as `build_model` makes it
- exported: the policy file as the drone loads it (`torch.jit.load`; the `InferenceDroNet` graph
  traced, frozen, channels_last)
- exported DroNet graph: `DroNet` itself traced and frozen, as exports were before
  `sim_harness.inference_graph` (the before/after of that rewrite)
- exported + optimize_for_inference: the same after `torch.jit.optimize_for_inference` at load
  time (MKL-DNN; cannot be saved to the file, see `sim_harness.export`)

Calls are timed one by one with `time.perf_counter` inside `torch.inference_mode`, variants
interleaved in `--rounds` rounds so that load changes hit them alike. Bar (issue 4): exported
batch-1 p99 <= 2 ms and >= 2x faster than eager. Prints a table and writes JSON (default
benchmarks/results/cnn_latency.json), the machine's load average included.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from sim_harness.export import export_policy, load_eager_model, to_torchscript
from sim_harness.model import DroNet, build_model

Policy = Callable[[torch.Tensor], torch.Tensor]


def calibrated_model(seed: int = 0) -> DroNet:
    """A seeded untrained network with batch-norm statistics from random images."""
    torch.manual_seed(seed)
    model = build_model(pixel_mean=185.0, pixel_std=36.0)
    with torch.no_grad():
        model.head.weight.normal_(0.0, 0.01)
        model.train()
        model(torch.randint(0, 256, (64, 64, 384), dtype=torch.uint8))
    return model.eval()


def variants(model: DroNet, policy_path: Path, plain_path: Path) -> dict[str, Policy]:
    nchw = copy.deepcopy(model).to(memory_format=torch.contiguous_format).eval()
    nchw.standardize.forward = lambda images: (
        (images.unsqueeze(1).float() - model.standardize.pixel_mean) / model.standardize.pixel_std
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        exported = torch.jit.load(str(policy_path))
        plain = torch.jit.load(str(plain_path))
        optimized = torch.jit.optimize_for_inference(torch.jit.load(str(policy_path)))
    return {
        "eager NCHW": nchw,
        "eager channels_last": model,
        "exported": exported,
        "exported DroNet graph": plain,
        "exported + optimize_for_inference": optimized,
    }


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, default=None, help="policy file (default: untrained)")
    parser.add_argument("--calls", type=int, default=2000, help="batch-1 calls per variant")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/cnn_latency.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    model = load_eager_model(args.model)[0] if args.model else calibrated_model()
    with tempfile.TemporaryDirectory() as tmp:
        policy = Path(tmp) / "policy.pt"
        export_policy(model, policy, {"id": "benchmark"}, None, {"command": "cnn_latency.py"})
        plain = Path(tmp) / "plain.pt"
        torch.jit.save(to_torchscript(model, graph="eager"), str(plain))
        fns = variants(model, policy, plain)
    rng = np.random.default_rng(0)
    results: dict[str, dict[str, dict[str, float]]] = {}
    with torch.inference_mode():
        for batch, calls in ((1, args.calls), (9, max(args.calls // 5, 50))):
            images = torch.from_numpy(rng.integers(0, 256, (batch, 64, 384), dtype=np.uint8))
            samples: dict[str, list[float]] = {name: [] for name in fns}
            for fn in fns.values():
                time_calls(fn, images, 50)  # warm-up (allocator, MKL-DNN primitives)
            for _ in range(args.rounds):
                for name, fn in fns.items():
                    samples[name] += time_calls(fn, images, max(calls // args.rounds, 1))
            results[f"batch_{batch}"] = {name: summarize(s) for name, s in samples.items()}
    load_after = os.getloadavg()
    b1 = results["batch_1"]
    exported = b1["exported"]
    speedup = {
        "p50_vs_eager_nchw": b1["eager NCHW"]["p50_ms"] / exported["p50_ms"],
        "p99_vs_eager_nchw": b1["eager NCHW"]["p99_ms"] / exported["p99_ms"],
        "p50_vs_eager_channels_last": b1["eager channels_last"]["p50_ms"] / exported["p50_ms"],
        "p50_vs_exported_dronet_graph": b1["exported DroNet graph"]["p50_ms"] / exported["p50_ms"],
        "p99_vs_exported_dronet_graph": b1["exported DroNet graph"]["p99_ms"] / exported["p99_ms"],
    }
    bar = {
        "exported_p99_le_2ms": exported["p99_ms"] <= 2.0,
        "exported_2x_faster_than_eager": speedup["p50_vs_eager_nchw"] >= 2.0,
    }
    print(f"{'':36} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8}")
    for key, table in results.items():
        print(key.replace("_", " "))
        for name, r in table.items():
            print(f"  {name:34} {r['p50_ms']:8.3f} {r['p90_ms']:8.3f} {r['p99_ms']:8.3f}")
    print(f"exported vs eager NCHW, batch 1: {speedup['p50_vs_eager_nchw']:.2f}x (p50)")
    print(f"bar: {bar}; load average {load_before[0]:.1f} -> {load_after[0]:.1f}")
    report = {
        "benchmark": "cnn_latency",
        "threads": 1,
        "model": str(args.model) if args.model else "untrained ResNet-8 (seed 0)",
        "results": results,
        "speedup": speedup,
        "bar": bar,
        "load_average_1min": [load_before[0], load_after[0]],
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": torch.__version__,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
