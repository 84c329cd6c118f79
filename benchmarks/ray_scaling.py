"""Ray against the local pool: dataset samples/s and an experiment suite's wall time.

    python benchmarks/ray_scaling.py [--samples 2000] [--repeats 2] [--flight-s 8]

Modes, each with all of this machine's cores:
- `local`: the local process pool (`--workers N`), the default without `--ray`;
- `ray-local`: `--ray local`, one Ray node started by the job (its start-up is timed too);
- `ray-2-nodes`: two Ray nodes on this machine (a head and a worker node, N/2 CPUs each, both
  bound to 127.0.0.1), started before the job, which connects by address: what a cluster adds
  (scheduling across raylets, runs sent between object stores). On one machine it measures the
  overhead of going multi-node, not a speed-up; add machines for that.

Every dataset is checked identical to the local pool's (same run files, byte for byte). Prints a
table and writes JSON (default benchmarks/results/ray_scaling.json).
"""

from __future__ import annotations

import os

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # nodes started here bind 127.0.0.1 only

import argparse
import json
import statistics
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sim_harness.dataset.generate import generate
from sim_harness.dataset.spec import SPLITS, DatasetSpec
from sim_harness.dataset.store import run_path
from sim_harness.experiments.machine import machine
from sim_harness.experiments.runner import run_suite
from sim_harness.experiments.suites import SuiteConfig
from sim_harness.sim.executor import ClusterChoice

RESULTS = Path(__file__).resolve().parent / "results"
MODES = ("local", "ray-local", "ray-2-nodes")


@contextmanager
def two_nodes(cpus: int) -> Iterator[str]:
    """A head and a worker node on this machine, `cpus` // 2 CPUs each; yields the address."""
    from ray.cluster_utils import Cluster

    per_node = max(cpus // 2, 1)
    loopback = {"node_ip_address": "127.0.0.1", "num_cpus": per_node}
    cluster = Cluster(initialize_head=True, head_node_args={**loopback, "include_dashboard": False})
    try:
        cluster.add_node(**loopback)
        yield str(cluster.address)
    finally:
        cluster.shutdown()


@contextmanager
def choice(mode: str, cpus: int) -> Iterator[ClusterChoice | None]:
    if mode == "local":
        yield None
    elif mode == "ray-local":
        yield ClusterChoice("local", num_cpus=cpus)
    else:
        with two_nodes(cpus) as address:
            yield ClusterChoice(address)


def run_files(root: Path, manifest: dict[str, Any]) -> dict[str, bytes]:
    return {
        f"{s}/{e['run_index']}": run_path(root, s, e["run_index"]).read_bytes()
        for s in SPLITS
        for e in manifest["splits"][s]["runs"]
    }


def dataset_rate(mode: str, cpus: int, samples: int, repeat: int, tmp: Path) -> dict[str, Any]:
    spec = DatasetSpec(train_samples=samples, val_samples=200, test_samples=200, seed=300 + repeat)
    out = tmp / f"{mode}-{repeat}"
    with choice(mode, cpus) as cluster:
        started = time.perf_counter()
        ds = generate(out, spec, workers=cpus, progress=False, cluster=cluster)
        wall = time.perf_counter() - started
    total = sum(ds.manifest["counts"].values())
    return {"wall_s": wall, "samples": total, "files": run_files(out, ds.manifest)}


def suite_wall(mode: str, cpus: int, flight_s: float) -> dict[str, Any]:
    config = SuiteConfig(suite="paper", n_seeds=1, duration_s=flight_s, workers=cpus)
    with choice(mode, cpus) as cluster:
        started = time.perf_counter()
        result = run_suite(config, cluster=cluster)
        wall = time.perf_counter() - started
    return {"wall_s": wall, "summaries": [r.summary for r in result.runs]}


def ray_start_s(cpus: int) -> float:
    """Seconds to start and stop a `--ray local` pool with nothing to run."""
    from sim_harness.sim.executor import open_pool

    started = time.perf_counter()
    with open_pool(cpus, ClusterChoice("local", num_cpus=cpus)):
        pass
    return time.perf_counter() - started


def median(rows: list[dict[str, Any]], fn: Callable[[dict[str, Any]], float]) -> float:
    return round(statistics.median(fn(r) for r in rows), 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=2000, help="training samples per dataset")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--flight-s", type=float, default=8.0, help="suite flights cut here")
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--out", type=Path, default=RESULTS / "ray_scaling.json")
    args = parser.parse_args()
    cpus = os.cpu_count() or 1
    modes = [m for m in args.modes.split(",") if m]
    rows: dict[str, dict[str, Any]] = {}
    reference: dict[int, dict[str, bytes]] = {}
    suite_reference: list[dict[str, Any]] | None = None
    datasets: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    suites: dict[str, list[float]] = {m: [] for m in modes}
    with tempfile.TemporaryDirectory(prefix="bench-ray-") as tmp:
        # Rounds, each mode once per round in a rotated order: the machine's other load drifts.
        for k in range(args.repeats):
            for mode in modes[k % len(modes) :] + modes[: k % len(modes)]:
                run = dataset_rate(mode, cpus, args.samples, k, Path(tmp))
                # the same bytes whatever ran them
                assert reference.setdefault(k, run["files"]) == run["files"], f"{mode} differs"
                datasets[mode].append(run)
                suite = suite_wall(mode, cpus, args.flight_s)
                suite_reference = suite_reference or suite["summaries"]
                assert suite["summaries"] == suite_reference, f"{mode}: other flights"
                suites[mode].append(suite["wall_s"])
                print(
                    f"round {k}: {mode}: {run['samples'] / run['wall_s']:.1f} samples/s, "
                    f"suite {suite['wall_s']:.1f} s, load {os.getloadavg()[0]:.2f}",
                    flush=True,
                )
    for mode in modes:
        runs = datasets[mode]
        rows[mode] = {
            "samples_per_s_median": median(runs, lambda r: r["samples"] / r["wall_s"]),
            "dataset_wall_s": [round(r["wall_s"], 1) for r in runs],
            "samples": runs[0]["samples"],
            "suite_wall_s_median": round(statistics.median(suites[mode]), 1),
            "suite_wall_s": [round(w, 1) for w in suites[mode]],
        }
    base = rows[modes[0]]
    for row in rows.values():
        row["samples_per_s_vs_first"] = round(
            row["samples_per_s_median"] / base["samples_per_s_median"], 3
        )
        row["suite_wall_vs_first"] = round(
            row["suite_wall_s_median"] / base["suite_wall_s_median"], 3
        )
    result = {
        "benchmark": "ray_scaling",
        "ray_local_start_s": round(ray_start_s(cpus), 2),
        "machine": machine(),
        "load_average_1m_after": os.getloadavg()[0],
        "dataset": {
            "train_samples": args.samples,
            "val_test_samples": 200,
            "repeats": args.repeats,
        },
        "suite": {"suite": "paper", "seeds": 1, "flight_s": args.flight_s, "flights": 4},
        "results": rows,
        "identical_outputs": True,  # asserted above
    }
    print(f"{'mode':>12s} {'samples/s':>10s} {'vs first':>9s} {'suite s':>8s} {'vs first':>9s}")
    for mode, r in rows.items():
        print(
            f"{mode:>12s} {r['samples_per_s_median']:>10.1f} {r['samples_per_s_vs_first']:>9.2f} "
            f"{r['suite_wall_s_median']:>8.1f} {r['suite_wall_vs_first']:>9.2f}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
