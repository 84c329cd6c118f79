"""Training throughput (samples/s) of the real training loop, and of its batch loader alone.

    python benchmarks/train_throughput.py [--samples 1536] [--threads 2] [--device cpu]
                                          [--arch dronet|cube]
    python benchmarks/train_throughput.py --dataset data/quick-s0      # + loader from the memmap

Trains with `learning.train.train_on` (batch 128, the paper's SGD, channels_last on CPU) on
random uint8 images for `--epochs` epochs and reports each epoch's training samples/s (the first
epoch includes warm-up); `--arch` picks the network (`dronet`, or `cube`: the same layers on
the six faces, padded by their neighbours). With `--dataset`, also times the loader alone: sorted
random batches of 128 fancy-indexed from the training split's memory-mapped images, as the loop
reads them. Prints a table and writes JSON (default benchmarks/results/train_throughput.json).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from sim_harness.learning.batches import InMemorySplit, load_batch, shuffled_batches
from sim_harness.learning.model import ARCHS
from sim_harness.learning.train import TrainConfig, resolve_device, train_on

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's


def loop_throughput(
    samples: int, epochs: int, device: str, threads: int, arch: str = "dronet"
) -> list[float]:
    rng = np.random.default_rng(0)
    split = InMemorySplit(
        images=rng.integers(0, 256, (samples, 64, 384), dtype=np.uint8),
        targets=rng.normal(0.0, 0.5, (samples, 3)).astype(np.float32),
        meta={},
    )
    val = InMemorySplit(split.images[:128], split.targets[:128], {})
    with tempfile.TemporaryDirectory() as tmp:
        config = TrainConfig(
            dataset=Path(tmp),
            out_dir=Path(tmp) / "run",
            max_epochs=epochs,
            device=device,
            threads=threads,
            progress=False,
            arch=arch,
        )
        result = train_on(
            config, {"id": "benchmark", "pixel_mean": 127.5, "pixel_std": 74.0}, split, val
        )
    return [row["train_samples_per_s"] for row in result.history]


def loader_throughput(dataset: Path, batches: int) -> dict[str, float]:
    from sim_harness.dataset.store import open_dataset

    split = open_dataset(dataset).split("train")
    order = shuffled_batches(split.n_samples, 128, seed=0, epoch=1)[:batches]
    start = time.perf_counter()
    for rows in order:
        load_batch(split, rows)
    elapsed = time.perf_counter() - start
    n = sum(len(rows) for rows in order)
    return {"split_samples": split.n_samples, "batches": len(order), "samples_per_s": n / elapsed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=1536, help="random training images")
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="cpu")
    parser.add_argument("--arch", choices=ARCHS, default="dronet")
    parser.add_argument("--dataset", type=Path, default=None, help="also time the loader on it")
    parser.add_argument("--loader-batches", type=int, default=200)
    parser.add_argument("--out", type=Path, default=RESULTS / "train_throughput.json")
    args = parser.parse_args()
    load_before = os.getloadavg()
    device = str(resolve_device(args.device))
    per_epoch = loop_throughput(args.samples, args.epochs, device, args.threads, args.arch)
    load_after = os.getloadavg()
    steady = float(np.median(per_epoch[1:] if len(per_epoch) > 1 else per_epoch))
    print(
        f"training loop, {args.arch}, batch 128, {device}, {args.threads} thread(s), "
        f"{args.samples} images"
    )
    for epoch, rate in enumerate(per_epoch, start=1):
        print(f"  epoch {epoch}: {rate:7.1f} samples/s")
    print(f"  steady (median after the first epoch): {steady:.1f} samples/s")
    print(f"  load average {load_before[0]:.1f} -> {load_after[0]:.1f}")
    report: dict[str, object] = {
        "benchmark": "train_throughput",
        "arch": args.arch,
        "device": device,
        "threads": args.threads,
        "batch_size": 128,
        "samples": args.samples,
        "samples_per_s_per_epoch": per_epoch,
        "samples_per_s_steady": steady,
        "load_average_1min": [load_before[0], load_after[0]],
        "machine": {
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "cuda": torch.cuda.get_device_name() if device == "cuda" else None,
        },
    }
    if args.dataset is not None:
        loader = loader_throughput(args.dataset, args.loader_batches)
        print(
            f"loader alone ({loader['batches']} batches of 128 from a "
            f"{loader['split_samples']}-sample memmap): {loader['samples_per_s']:.0f} samples/s"
        )
        report["loader"] = loader
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
