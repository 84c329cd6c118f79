"""The dataset on disk: one compressed file per run, a manifest, and a memory-mapped reader.

Layout of a dataset folder:

    spec.json                      parameters it was started with (resume and merge check them)
    runs/<split>/run-<k>.npz       one run, zip-deflate compressed (numpy .npz): images (n, 64, 384)
                                   uint8, targets (n, 3) float32 body FLU m/s, per-sample metadata,
                                   and the run's exact pixel sums (for the mean and std)
    manifest.json                  written when generation completes: every parameter and seed, the
                                   camera spec, frame conventions, code version, the runs of each
                                   split, counts, termination reasons, training pixel mean and std
    cache/<split>-<id>.npy         built on first read: the split's images as one raw uint8 array,
                                   memory-mapped (the OS pages it in; nothing is held twice in RAM)

Why plain numpy files: the client fixed the dependency list, and numpy's .npz (zip deflate, about
4x smaller on these images) gives chunked (a chunk = a run, the unit of resume, split and merge),
compressed and appendable storage; a run file appears atomically (written aside, then renamed),
so an interrupted generation never leaves a half-written run. Training reads a split through one
memory-mapped .npy: random batches without loading a 500k-sample set (12 GB raw) into RAM.
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from sim_harness.dataset.runs import RunData
from sim_harness.dataset.spec import SPLITS, TERMINATIONS
from sim_harness.errors import DatasetError

MANIFEST = "manifest.json"
SPEC = "spec.json"
FORMAT = "vision-swarm-dataset/1"
_SCALARS = ("run_index", "termination", "migration_point_world_enu", "pixel_sum", "pixel_sumsq")


def run_path(root: Path, split: str, run_index: int) -> Path:
    return root / "runs" / split / f"run-{run_index:07d}.npz"


def encode_run(run: RunData, compression: str = "deflate") -> bytes:
    """The bytes of a run's file (what `write_run` stores): the same run gives the same bytes.

    `compression` "deflate": zip deflate level 1, about half the size (12 KB per sample here)
    for ~0.45 ms of one core per sample; "none": stored (24 KB per sample), ~0.04 ms. The reader
    reads both.
    """
    images = run.images
    arrays: dict[str, NDArray[np.generic]] = {
        "images": images,
        "run_index": np.array(run.run_index, dtype=np.int64),
        "termination": np.array(run.termination),
        "migration_point_world_enu": run.migration_point_world_enu,
        "pixel_sum": np.array(images.sum(dtype=np.int64), dtype=np.int64),
        # 255^2 fits uint16: exact squares without an int64 copy of the images
        "pixel_sumsq": np.array(np.square(images, dtype=np.uint16).sum(dtype=np.int64)),
        **run.arrays,
    }
    buffer = io.BytesIO()
    # A numpy .npz written directly, to pick deflate level 1: 3-4x faster to write than
    # np.savez_compressed's default level with nearly the same size on these images.
    method = zipfile.ZIP_STORED if compression == "none" else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(buffer, "w", compression=method, compresslevel=1) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array(member, np.asanyarray(array), allow_pickle=False)
    return buffer.getvalue()


def write_run_bytes(root: Path, split: str, run_index: int, data: bytes) -> Path:
    """Store a run's file (`encode_run`) atomically: a crash leaves the whole file or a `.tmp`."""
    path = run_path(root, split, run_index)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def write_run(root: Path, run: RunData) -> Path:
    """Store one run atomically (a crash leaves either the whole file or only a `.tmp`)."""
    return write_run_bytes(root, run.split, run.run_index, encode_run(run))


@dataclass(frozen=True)
class RunSummary:
    """What the manifest records about one stored run."""

    run_index: int
    n_samples: int
    termination: str
    pixel_sum: int
    pixel_sumsq: int


def read_run_summary(path: Path) -> RunSummary:
    """Scalars of a stored run (reads only the small arrays and the images' header)."""
    try:
        with np.load(path) as z:
            n = int(z["targets"].shape[0])
            return RunSummary(
                int(z["run_index"]),
                n,
                str(z["termination"]),
                int(z["pixel_sum"]),
                int(z["pixel_sumsq"]),
            )
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise DatasetError(
            f"run file {path} is unreadable ({exc}); delete it to regenerate"
        ) from exc


def stored_runs(root: Path, split: str) -> dict[int, Path]:
    """Complete run files of a split by run index (`.tmp` leftovers are not runs)."""
    folder = root / "runs" / split
    if not folder.is_dir():
        return {}
    return {int(p.stem.split("-")[1]): p for p in sorted(folder.glob("run-*.npz"))}


def remove_partial_files(root: Path) -> int:
    """Delete leftovers of interrupted writes; returns how many there were."""
    leftovers = list((root / "runs").glob("*/*.tmp")) if (root / "runs").is_dir() else []
    for p in leftovers:
        p.unlink()
    return len(leftovers)


def pixel_stats(runs: list[RunSummary]) -> tuple[float, float]:
    """Exact mean and standard deviation of all pixels of these runs."""
    count = sum(r.n_samples for r in runs) * IMAGE_HEIGHT_PX * IMAGE_WIDTH_PX
    if count == 0:
        raise DatasetError("no samples: cannot compute the pixel mean and standard deviation")
    total = sum(r.pixel_sum for r in runs)
    total_sq = sum(r.pixel_sumsq for r in runs)
    mean = total / count
    return mean, float(np.sqrt(max(total_sq / count - mean * mean, 0.0)))


def write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    os.replace(tmp, path)


@dataclass
class SplitData:
    """One split: images memory-mapped, targets and metadata in RAM, samples in manifest order."""

    root: Path
    name: str
    runs: list[int]
    dataset_id: str
    _arrays: dict[str, NDArray[np.generic]] | None = field(default=None, repr=False)

    @cached_property
    def n_samples(self) -> int:
        return int(self.targets.shape[0])

    def _run_files(self) -> Iterator[tuple[int, Path]]:
        for k in self.runs:
            path = run_path(self.root, self.name, k)
            if not path.exists():
                raise DatasetError(f"{path} listed in the manifest is missing")
            yield k, path

    def _load_small(self) -> dict[str, NDArray[np.generic]]:
        if self._arrays is None:
            parts: dict[str, list[NDArray[np.generic]]] = {}
            for k, path in self._run_files():
                with np.load(path) as z:
                    n = int(z["targets"].shape[0])
                    for key in z.files:
                        if key == "images" or key in _SCALARS:
                            continue
                        parts.setdefault(key, []).append(z[key])
                    parts.setdefault("run", []).append(np.full(n, k, dtype=np.int64))
                    code = TERMINATIONS.index(str(z["termination"]))
                    parts.setdefault("termination", []).append(np.full(n, code, dtype=np.int8))
            self._arrays = {k: np.concatenate(v) for k, v in parts.items()}
        return self._arrays

    @property
    def targets(self) -> NDArray[np.float32]:
        """(n, 3) float32: the teacher's Reynolds command in the body frame (FLU), m/s."""
        return self._load_small()["targets"].astype(np.float32, copy=False)

    @property
    def meta(self) -> dict[str, NDArray[np.generic]]:
        """Per-sample arrays: run, agent, time_s, pos/vel (world ENU), q_world_body, etc."""
        return {k: v for k, v in self._load_small().items() if k != "targets"}

    def read_images(self, indices: Sequence[int]) -> NDArray[np.uint8]:
        """(k, 64, 384) uint8: these samples' images, read from their run files.

        For a few samples (figures, spot checks): unlike `images`, it writes no cache.
        """
        runs = self._load_small()["run"]
        keys, first = np.unique(runs, return_index=True)
        start = dict(zip(keys.tolist(), first.tolist(), strict=True))
        wanted: dict[int, list[tuple[int, int]]] = {}
        for j, i in enumerate(indices):
            wanted.setdefault(int(runs[i]), []).append((j, int(i)))
        out = np.empty((len(indices), IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX), dtype=np.uint8)
        for k, picks in wanted.items():
            with np.load(run_path(self.root, self.name, k)) as z:
                images = z["images"]
            for j, i in picks:
                out[j] = images[i - start[k]]
        return out

    @cached_property
    def images(self) -> NDArray[np.uint8]:
        """(n, 64, 384) uint8, read-only memmap of the split's cache (built on first access)."""
        cache = self.root / "cache" / f"{self.name}-{self.dataset_id}.npy"
        if not cache.exists():
            cache.parent.mkdir(exist_ok=True)
            tmp = cache.with_name(cache.name + ".tmp")
            out = np.lib.format.open_memmap(
                tmp,
                mode="w+",
                dtype=np.uint8,
                shape=(self.n_samples, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX),
            )
            at = 0
            for _, path in self._run_files():
                with np.load(path) as z:
                    images = z["images"]
                out[at : at + len(images)] = images
                at += len(images)
            out.flush()
            del out
            os.replace(tmp, cache)
        images = np.load(cache, mmap_mode="r")
        if images.shape[0] != self.n_samples:
            raise DatasetError(f"image cache {cache} does not match the manifest; delete it")
        return images


@dataclass
class Dataset:
    """A completed dataset folder (one with a manifest)."""

    root: Path
    manifest: dict[str, Any]

    @property
    def id(self) -> str:
        return str(self.manifest["id"])

    def split(self, name: str) -> SplitData:
        if name not in SPLITS:
            raise DatasetError(f"split must be one of {', '.join(SPLITS)}, got {name!r}")
        runs = [int(r["run_index"]) for r in self.manifest["splits"][name]["runs"]]
        return SplitData(self.root, name, runs, self.id)


def open_dataset(root: str | Path) -> Dataset:
    """Open a completed dataset; raises `DatasetError` when it is missing or unfinished."""
    root = Path(root)
    path = root / MANIFEST
    if not path.exists():
        hint = (
            " (generation not finished: run the same command again)"
            if (root / SPEC).exists()
            else ""
        )
        raise DatasetError(f"no dataset at {root}: {MANIFEST} is missing{hint}")
    try:
        manifest = json.loads(path.read_text())
    except ValueError as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from exc
    if manifest.get("format") != FORMAT:
        raise DatasetError(f"{path}: format {manifest.get('format')!r}, expected {FORMAT!r}")
    return Dataset(root, manifest)
