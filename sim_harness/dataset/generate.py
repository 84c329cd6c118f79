"""Parallel, resumable, deterministic dataset generation, and merging of shards.

Determinism: run k of a split is a pure function of (seed, split, k) (see `spec.run_rng`). A split
is the shortest prefix of its run sequence that reaches the requested sample count, whatever the
number of workers and whatever order the runs finished in; runs generated past that prefix are
deleted. Resume: every run is stored atomically on completion, so an interrupted generation (Ctrl-C,
kill, power loss) loses at most the runs in flight; the same command continues from the runs on
disk. Shards: `shard_index`/`shard_count` interleave run indices (shard i of n makes runs i, i+n,
...), so shards made on several machines never overlap and `merge` unites them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from companion.camera.layout import camera_spec
from sim_harness.dataset.runs import simulate_run
from sim_harness.dataset.spec import SPLITS, TERMINATIONS, DatasetSpec
from sim_harness.dataset.store import (
    FORMAT,
    MANIFEST,
    SPEC,
    Dataset,
    RunSummary,
    encode_run,
    open_dataset,
    pixel_stats,
    read_run_summary,
    remove_partial_files,
    run_path,
    stored_runs,
    write_json,
    write_run_bytes,
)
from sim_harness.errors import DatasetError
from sim_harness.sim.executor import ClusterChoice, Task, TaskPool, announce, open_pool
from sim_harness.sim.progress import ProgressBar, progress_bar
from sim_harness.sim.render import Renderer
from sim_harness.sim.renderers import make_renderer
from sim_harness.sim.scene import SceneSpec
from sim_harness.sim.vehicle import VehicleParams
from sim_harness.sim.world import World

log = logging.getLogger(__name__)

FRAMES = {
    "world": "ENU (x east, y north, z up), metres",
    "body": "FLU (x forward, y left, z up)",
    "quaternion": "wxyz, rotates body FLU vectors into world ENU",
    "targets": "teacher's Reynolds command (separation + cohesion, no migration), body FLU, m/s",
}


@dataclass
class StageTimes:
    """Seconds summed over runs, per stage, across all workers."""

    render_s: float = 0.0
    physics_s: float = 0.0
    teacher_s: float = 0.0
    write_s: float = 0.0

    def add(self, other: StageTimes) -> None:
        for k in asdict(self):
            setattr(self, k, getattr(self, k) + getattr(other, k))


# One world and renderer per worker process, created on its first run.
_WORKER: tuple[World, Renderer, str] | None = None


def _make_run(
    worker_root: Path | None, spec: DatasetSpec, split: str, run_index: int
) -> tuple[int, StageTimes, bytes | None]:
    """Simulate one run (in a worker or in-process): its size, times, and its file's bytes for
    the driver to store, or None when written here under `worker_root` (a folder it shares)."""
    global _WORKER
    if _WORKER is None or (_WORKER[0].n_agents, _WORKER[2]) != (spec.n_agents, spec.renderer):
        if _WORKER is not None:
            _WORKER[0].close()
        _WORKER = (World(spec.n_agents), make_renderer(spec.renderer), spec.renderer)
    world, renderer, _ = _WORKER
    run = simulate_run(spec, split, run_index, world, renderer)
    started = time.perf_counter()
    data: bytes | None = encode_run(run, spec.compression)
    if worker_root is not None and data is not None:
        write_run_bytes(worker_root, split, run_index, data)
        data = None
    t = run.timing
    times = StageTimes(t.render_s, t.physics_s, t.teacher_s, time.perf_counter() - started)
    return run.n_samples, times, data


def store_run(root: Path, split: str, run_index: int, data: bytes | None) -> None:
    """Write a run a worker returned (`data`), or check that the worker wrote it where we read."""
    if data is not None:
        write_run_bytes(root, split, run_index, data)
    elif not run_path(root, split, run_index).exists():
        raise DatasetError(
            f"{split} run {run_index} was written by a worker but is not in {root}: "
            "--ray-shared-dir must be this folder as the workers see it"
        )


def check_or_write_spec(root: Path, spec: DatasetSpec) -> None:
    """Record the spec of a new dataset, or check that a resumed one was started with it."""
    path = root / SPEC
    if not path.exists():
        root.mkdir(parents=True, exist_ok=True)
        write_json(path, spec.as_dict())
        return
    started = DatasetSpec.from_dict(json.loads(path.read_text()))
    if started.content_dict() != spec.content_dict() or (
        started.shard_index,
        started.shard_count,
    ) != (spec.shard_index, spec.shard_count):
        old, new = started.as_dict(), spec.as_dict()
        diff = [k for k in new if k not in (f"{s}_samples" for s in SPLITS) and old[k] != new[k]]
        raise DatasetError(
            f"{root} was started with other parameters ({', '.join(diff)}): use another folder, "
            "or the original parameters to resume"
        )
    if started != spec:  # only the sizes changed: record the new targets
        write_json(path, spec.as_dict())


class _SplitProgress:
    """Which runs of one split exist (by position k in this shard's sequence) and their sizes."""

    def __init__(self, root: Path, spec: DatasetSpec, split: str) -> None:
        self.spec, self.split = spec, split
        self.target = spec.target(split)
        self.sizes: dict[int, int] = {}
        for idx, path in stored_runs(root, split).items():
            offset = idx - spec.shard_index
            if offset >= 0 and offset % spec.shard_count == 0:  # else another shard's run
                self.sizes[offset // spec.shard_count] = read_run_summary(path).n_samples

    def prefix(self) -> tuple[int, int]:
        """(number of runs, samples) of the contiguous prefix, stopping at the target."""
        k, total = 0, 0
        while k in self.sizes and total < self.target:
            total += self.sizes[k]
            k += 1
        return k, total

    def done(self) -> bool:
        return self.prefix()[1] >= self.target

    def next_missing(self, busy: set[int]) -> int:
        k = 0
        while k in self.sizes or k in busy:
            k += 1
        return k

    def worth_starting(self, k: int, busy: set[int]) -> bool:
        """False when the runs before k, counting busy ones at the mean size, reach the target."""
        mean_run = sum(self.sizes.values()) / len(self.sizes) if self.sizes else 300.0
        before = sum(n for j, n in self.sizes.items() if j < k)
        before += mean_run * sum(1 for j in busy if j < k)
        return before < self.target


def _generate_split(
    root: Path,
    spec: DatasetSpec,
    split: str,
    pool: TaskPool,
    worker_root: Path | None,
    progress: bool,
    times: StageTimes,
) -> None:
    state = _SplitProgress(root, spec, split)
    in_flight: dict[Task[tuple[int, StageTimes, bytes | None]], int] = {}

    def record(k: int, n: int, t: StageTimes, bar: ProgressBar[Any]) -> None:
        state.sizes[k] = n
        times.add(t)
        # A split ends with its last whole run, past the target: the bar counts what is kept.
        kept = state.prefix()[1]
        if kept > (bar.total or 0):
            bar.total = kept
        bar.update(max(0, kept - bar.n))

    kept = state.prefix()[1]  # runs already on disk (a resumed generation)
    with progress_bar(
        total=max(state.target, kept),
        initial=kept,
        desc=f"{split:5s}",
        enabled=progress,
        unit=" samples",
        smoothing=0.05,
    ) as bar:
        while not state.done():
            # At most `slots` runs in flight: a finished run waits here only until it is stored.
            while len(in_flight) < pool.info.slots:
                busy = set(in_flight.values())
                k = state.next_missing(busy)
                if busy and not state.worth_starting(k, busy):
                    break
                index = spec.run_index(split, k)
                task = pool.submit(
                    _make_run, worker_root, spec, split, index, label=f"{split}-run-{index}"
                )
                in_flight[task] = k
            for task in pool.wait(list(in_flight)):
                k = in_flight.pop(task)
                n, t, data = task.result()
                started = time.perf_counter()
                store_run(root, split, spec.run_index(split, k), data)
                t.write_s += time.perf_counter() - started
                record(k, n, t, bar)
        for task, k in in_flight.items():  # started but not needed: let them finish, drop them
            if task.result()[2] is None:  # a worker wrote it
                run_path(root, split, spec.run_index(split, k)).unlink(missing_ok=True)
    n_runs, _ = state.prefix()
    for k in state.sizes:
        if k >= n_runs:
            run_path(root, split, spec.run_index(split, k)).unlink(missing_ok=True)


def code_version() -> dict[str, str | None]:
    """Package version and, when run from a git checkout, its commit."""
    try:
        version: str | None = metadata.version("vision-swarm")
    except metadata.PackageNotFoundError:
        version = None
    commit = None
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
        commit = out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"package": version, "git_commit": commit}


def finalize(
    root: Path,
    spec: DatasetSpec,
    runs: dict[str, list[int]],
    command: str,
    generation: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    id_extra: dict[str, Any] | None = None,
) -> Dataset:
    """Write the manifest for these runs (run indices per split, in order) and open the dataset.

    `id_extra` (e.g. an aggregated dataset's source model and scenarios) enters the dataset id
    along with the spec's content id and the run lists.
    """
    summaries: dict[str, list[RunSummary]] = {
        split: [read_run_summary(run_path(root, split, k)) for k in runs[split]] for split in SPLITS
    }
    for split in SPLITS:
        if not summaries[split]:
            raise DatasetError(f"split {split!r} has no runs")
    mean, std = pixel_stats(summaries["train"])
    split_info = {
        split: {
            "n_samples": sum(r.n_samples for r in rs),
            "n_runs": len(rs),
            "terminations": {t: sum(r.termination == t for r in rs) for t in TERMINATIONS},
            "runs": [
                {"run_index": r.run_index, "n_samples": r.n_samples, "termination": r.termination}
                for r in rs
            ],
        }
        for split, rs in summaries.items()
    }
    content: dict[str, Any] = {
        "content_id": spec.content_id(),
        "runs": {s: runs[s] for s in SPLITS},
    }
    if id_extra:
        content["extra"] = id_extra
    dataset_id = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:16]
    manifest: dict[str, Any] = {
        "format": FORMAT,
        "id": dataset_id,
        "content_id": spec.content_id(),
        "spec": spec.as_dict(),
        "camera": camera_spec(),
        "scene": SceneSpec().as_dict(),
        "renderer": spec.renderer,
        "vehicle": asdict(VehicleParams()),
        "frames": FRAMES,
        "code_version": code_version(),
        "command": command,
        "counts": {s: split_info[s]["n_samples"] for s in SPLITS},
        "splits": split_info,
        "pixel_mean": mean,
        "pixel_std": std,
        "generation": generation or {},
        **(extra or {}),
    }
    write_json(root / MANIFEST, manifest)
    dataset = open_dataset(root)
    stats = {}
    for split in SPLITS:
        targets = dataset.split(split).targets.astype(np.float64)
        stats[split] = {
            "mean": targets.mean(axis=0).round(6).tolist(),
            "std": targets.std(axis=0).round(6).tolist(),
            "min": targets.min(axis=0).round(6).tolist(),
            "max": targets.max(axis=0).round(6).tolist(),
        }
    manifest["target_stats"] = stats
    write_json(root / MANIFEST, manifest)
    return open_dataset(root)


def generate(
    root: str | Path,
    spec: DatasetSpec,
    workers: int | None = None,
    progress: bool = True,
    command: str = "",
    cluster: ClusterChoice | None = None,
) -> Dataset:
    """Generate (or resume) the dataset `spec` in `root`; returns it when complete.

    `cluster`: run on Ray (workers return each run to this process, which writes it; or write it
    themselves under `cluster.shared_dir`); None: `workers` local processes (default: all cores).
    The dataset is the same byte for byte either way.
    """
    root = Path(root)
    workers = workers or os.cpu_count() or 1
    check_or_write_spec(root, spec)
    (root / MANIFEST).unlink(missing_ok=True)  # incomplete again until finalized
    leftovers = remove_partial_files(root)
    if leftovers:
        log.info("removed %d partial run file(s) of an interrupted generation", leftovers)
    times = StageTimes()
    started = time.perf_counter()
    before = {s: len(stored_runs(root, s)) for s in SPLITS}
    with open_pool(workers, cluster) as pool:
        announce(pool, progress)
        worker_root = root if pool.same_files else (cluster.shared_dir if cluster else None)
        for split in SPLITS:
            _generate_split(root, spec, split, pool, worker_root, progress, times)
        info = pool.info
    wall = time.perf_counter() - started
    runs = {
        s: [spec.run_index(s, k) for k in range(_SplitProgress(root, spec, s).prefix()[0])]
        for s in SPLITS
    }
    made = {s: len(stored_runs(root, s)) - before[s] for s in SPLITS}
    busy = sum(asdict(times).values())
    generation = {
        "workers": info.cpus,
        "pool": info.as_dict(),
        "wall_s": round(wall, 3),
        "new_runs": made,
        "stage_share": {k: round(v / busy, 4) for k, v in asdict(times).items()} if busy else {},
    }
    return finalize(root, spec, runs, command, generation)


def merge(sources: Sequence[str | Path], out: str | Path, command: str = "") -> Dataset:
    """Unite completed datasets made with the same parameters (e.g. shards) into `out`.

    A run present in several sources (same split and index) must be identical in each and is
    taken once. Files are hard-linked when possible, else copied.
    """
    out = Path(out)
    if (out / MANIFEST).exists() or (out / "runs").exists():
        raise DatasetError(f"{out} already holds a dataset: merge into a new folder")
    datasets = [open_dataset(s) for s in sources]
    if not datasets:
        raise DatasetError("merge needs at least one source dataset")
    specs = [DatasetSpec.from_dict(d.manifest["spec"]) for d in datasets]
    ids = {s.content_id() for s in specs}
    if len(ids) != 1:
        raise DatasetError(
            "cannot merge datasets made with different parameters (content ids "
            f"{', '.join(sorted(ids))}); only seed-compatible shards of one spec merge"
        )
    chosen: dict[str, dict[int, RunSummary]] = {s: {} for s in SPLITS}
    for ds in datasets:
        for split in SPLITS:
            for entry in ds.manifest["splits"][split]["runs"]:
                k = int(entry["run_index"])
                src = run_path(ds.root, split, k)
                summary = read_run_summary(src)
                if k in chosen[split]:
                    if chosen[split][k] != summary:
                        raise DatasetError(f"run {k} of {split} differs between sources")
                    continue
                chosen[split][k] = summary
                dst = run_path(out, split, k)
                dst.parent.mkdir(parents=True, exist_ok=True)
                try:
                    os.link(src, dst)
                except OSError:
                    shutil.copy2(src, dst)
    runs = {s: sorted(chosen[s]) for s in SPLITS}
    sizes = {f"{s}_samples": sum(r.n_samples for r in chosen[s].values()) for s in SPLITS}
    merged = DatasetSpec.from_dict(
        {**specs[0].as_dict(), **sizes, "shard_index": 0, "shard_count": 1}
    )
    write_json(out / SPEC, merged.as_dict())
    return finalize(
        out, merged, runs, command, extra={"merged_from": [str(d.root) for d in datasets]}
    )
