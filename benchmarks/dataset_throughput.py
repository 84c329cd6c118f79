"""Dataset generation throughput: samples/s with one worker and with all workers, and where the
time goes (rendering, physics, teacher, writing).

    python benchmarks/dataset_throughput.py [--samples 2000] [--repeats 3]
        [--renderer pybullet|raycast]   # raycast writes dataset_throughput_raycast.json
        [--compression deflate|none]    # none writes dataset_throughput_<renderer>_stored.json

Each measurement generates a fresh dataset of the paper's runs (9 drones, full-length runs) with
`--samples` training samples and small validation/test splits, timing the whole generation
(process start-up of the workers included). Reports the median over repeats of samples/s, the ratio
all-workers / one-worker, and the stage shares summed over workers. Prints a table and writes JSON
(default benchmarks/results/dataset_throughput.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

from sim_harness.dataset.generate import generate
from sim_harness.dataset.spec import COMPRESSIONS, DatasetSpec
from sim_harness.experiments.machine import machine
from sim_harness.sim.renderers import RENDERERS

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's


def measure(
    workers: int, samples: int, repeats: int, renderer: str, compression: str = "deflate"
) -> dict[str, object]:
    rates, shares = [], []
    for repeat in range(repeats):
        spec = DatasetSpec(
            train_samples=samples,
            val_samples=200,
            test_samples=200,
            seed=100 + repeat,
            renderer=renderer,
            compression=compression,
        )
        with tempfile.TemporaryDirectory(prefix="bench-ds-") as tmp:
            started = time.perf_counter()
            ds = generate(Path(tmp) / "ds", spec, workers=workers, progress=False)
            wall = time.perf_counter() - started
            total = sum(ds.manifest["counts"].values())
            rates.append(total / wall)
            shares.append(ds.manifest["generation"]["stage_share"])
    return {
        "workers": workers,
        "samples_per_s_median": round(statistics.median(rates), 1),
        "samples_per_s_all": [round(r, 1) for r in rates],
        "stage_share": {k: round(statistics.median(s[k] for s in shares), 3) for k in shares[0]},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=2000, help="training samples per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--renderer", default="pybullet", choices=RENDERERS)
    parser.add_argument("--compression", default="deflate", choices=COMPRESSIONS)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    suffix = "" if args.renderer == "pybullet" else f"_{args.renderer}"
    if args.compression == "none":
        suffix = f"_{args.renderer}_stored"
    args.out = args.out or RESULTS / f"dataset_throughput{suffix}.json"
    cores = os.cpu_count() or 1
    rows = [measure(1, args.samples, args.repeats, args.renderer, args.compression)]
    if cores > 1:
        rows.append(measure(cores, args.samples, args.repeats, args.renderer, args.compression))
    result = {
        "benchmark": "dataset_throughput",
        "machine": machine(),
        "n_agents": 9,
        "renderer": args.renderer,
        "compression": args.compression,
        "load_average_1m_after": os.getloadavg()[0],
        "samples_per_repeat": args.samples + 400,
        "repeats": args.repeats,
        "results": rows,
        "speedup_all_workers": round(
            rows[-1]["samples_per_s_median"] / rows[0]["samples_per_s_median"],
            2,  # type: ignore[operator]
        ),
    }
    print(f"{'workers':>8s} {'samples/s':>10s}  stage shares")
    for r in rows:
        print(f"{r['workers']:>8d} {r['samples_per_s_median']:>10.1f}  {r['stage_share']}")
    print(f"all workers / one worker: {result['speedup_all_workers']}x")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
