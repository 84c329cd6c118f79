"""Close encounters drawn from recorded flocks: the states the teacher's flights almost never hold.

A flight of the teacher ends at the first pair under 1 m (the paper's rule), and the flights of the
CNN that dataset aggregation records rarely dip below it: in the shipped model's data, a few
hundred of 2.4 million samples have a neighbour within 0.8 m. Yet that is exactly where a flock
is judged (two groups of an opposing-goals flock cross 0.5-0.7 m apart in their first seconds) and
where the separation term is steepest (k_sep / d). A network that has barely seen a drone at 0.6 m
answers it as if it were at 0.9 m.

This module makes such states from recorded ones. For some steps of each run of a source dataset
(seeded, distinct steps), it picks an agent i, takes its nearest neighbour j, and moves j to a
distance drawn uniformly in [`min_m`, `max_m`] from i: along their line (`bearing="kept"`), or
towards a corner of i's cube map (`"corner"`), where a close drone is split over three faces and
the shipped network answers it weakest; j keeps its attitude, the rest of the flock stays. The
step is kept only if j stays at least `min_m` from every other drone. Then the whole flock is
drawn again and every drone's label is the teacher's Reynolds command of the new positions
(`runs.teacher_targets`), so every label is exact: nothing is interpolated, only the state is
new. Per step, two samples (i and j) are close ones and the rest of the flock comes along, so a
batch still holds whole flocks (`learning.flock_loss`).

The output is a normal dataset folder with the source's spec and splits (a step of a validation
run stays in validation). Its manifest records the source (`close_range_from`) and the draw
(`close_range`). Runs are written one file at a time, atomically: an interrupted draw resumes
with the same command.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from companion.frames import quat_to_rotmat
from companion.validation import require_int_range, require_range
from sim_harness.dataset.generate import check_or_write_spec, finalize
from sim_harness.dataset.rerender import IMAGE_KEYS, SCALAR_KEYS, each_missing_run, flock_steps
from sim_harness.dataset.runs import RunData, teacher_targets
from sim_harness.dataset.spec import SPLITS, DatasetSpec
from sim_harness.dataset.store import (
    Dataset,
    encode_run,
    open_dataset,
    remove_partial_files,
    run_path,
    write_run_bytes,
)
from sim_harness.errors import DatasetError
from sim_harness.sim.renderers import make_renderer
from sim_harness.sim.world import World

FloatArray = NDArray[np.float64]

# How many agents of a step are tried as the near one before the step is given up
_TRIES_PER_STEP = 4
# `bearing="corner"`: the largest component of the neighbour's direction in the near drone's body
# frame stays below this (1 at a face's centre, 1/sqrt(3) = 0.577 at a cube corner)
CORNER_FACENESS = 0.75
BEARINGS = ("kept", "corner")


@dataclass(frozen=True)
class CloseRangeDraw:
    """What is drawn: `steps_per_run` steps a run, one pair brought to [min_m, max_m] m in each."""

    steps_per_run: int = 30
    min_m: float = 0.4
    max_m: float = 1.1
    seed: int = 0
    bearing: str = "kept"  # kept: along the recorded line; corner: towards a cube-map corner

    def __post_init__(self) -> None:
        require_int_range("close-range.steps_per_run", self.steps_per_run, 1, 100_000)
        require_range("close-range.min_m", self.min_m, 0.2, 5.0)
        require_range("close-range.max_m", self.max_m, 0.2, 5.0)
        if self.max_m <= self.min_m:
            raise ConfigError(
                f"close-range.max_m: must be above close-range.min_m ({self.min_m} m), "
                f"got {self.max_m} m"
            )
        require_int_range("close-range.seed", self.seed, 0)
        if self.bearing not in BEARINGS:
            raise ConfigError(
                f"close-range.bearing: unknown bearing {self.bearing!r}; choose one of "
                f"{', '.join(BEARINGS)}"
            )


def corner_direction(rng: np.random.Generator) -> FloatArray:
    """A unit vector drawn uniformly over the cube-corner regions of the sphere (largest component
    below `CORNER_FACENESS`): where a close drone is split across three faces of the cube map."""
    while True:
        u = rng.normal(size=3)
        norm = float(np.linalg.norm(u))
        if norm > 1e-9 and np.abs(u).max() / norm < CORNER_FACENESS:
            return np.asarray(u / norm, dtype=np.float64)


def move_nearest_closer(
    pos: FloatArray,
    rng: np.random.Generator,
    min_m: float,
    max_m: float,
    q_world_body: FloatArray | None = None,
) -> tuple[FloatArray, int, int] | None:
    """`pos` (N, 3) with one agent's nearest neighbour moved to a distance drawn in [min_m, max_m],
    and (i, j); None if no try keeps j at least `min_m` from every other. The neighbour keeps its
    bearing, or, given the attitudes `q_world_body` (N, 4), takes one drawn towards a corner of
    agent i's cube map (`corner_direction`, in i's body frame)."""
    n = len(pos)
    for _ in range(_TRIES_PER_STEP):
        i = int(rng.integers(n))
        offsets = pos - pos[i]
        dist = np.linalg.norm(offsets, axis=1)
        dist[i] = np.inf
        j = int(np.argmin(dist))
        d = float(rng.uniform(min_m, max_m))
        if not math.isfinite(dist[j]) or dist[j] < 1e-6:
            continue
        if q_world_body is None:
            direction = offsets[j] / dist[j]
        else:
            direction = quat_to_rotmat(q_world_body[i]) @ corner_direction(rng)
        moved = pos.copy()
        moved[j] = pos[i] + direction * d
        others = np.linalg.norm(np.delete(moved, [i, j], axis=0) - moved[j], axis=1)
        if others.size and others.min() < min_m:
            continue
        return moved, i, j
    return None


def close_range_run(
    source: Path,
    split: str,
    run_index: int,
    renderer_name: str,
    flocking: FlockingParams,
    draw: CloseRangeDraw,
) -> bytes:
    """The bytes of run `run_index` of `split`: up to `draw.steps_per_run` distinct steps of the
    source run, each with one close pair made and the whole flock drawn and labelled again."""
    min_m, max_m = draw.min_m, draw.max_m
    with np.load(run_path(source, split, run_index)) as z:
        arrays = {k: z[k] for k in z.files}
    n_steps, n_agents = flock_steps(arrays["agent"], f"run {split}/{run_index} of {source}")
    pos = arrays["pos_world_enu"].astype(np.float64).reshape(n_steps, n_agents, 3)
    q = arrays["q_world_body"].astype(np.float64).reshape(n_steps, n_agents, 4)
    rng = np.random.default_rng([draw.seed, SPLITS.index(split), run_index])
    chosen = np.sort(rng.choice(n_steps, size=min(draw.steps_per_run, n_steps), replace=False))
    renderer = make_renderer(renderer_name)
    kept: list[int] = []
    images, new_pos, labels = [], [], []
    with World(n_agents) as world:
        for k in chosen:
            moved = move_nearest_closer(
                pos[k], rng, min_m, max_m, q[k] if draw.bearing == "corner" else None
            )
            if moved is None:
                continue
            kept.append(int(k))
            new_pos.append(moved[0])
            labels.append(teacher_targets(moved[0], q[k], flocking))
            images.append(renderer.render(world, moved[0], q[k]))
    if not kept:
        raise DatasetError(
            f"run {split}/{run_index} of {source}: no step could be given a pair in "
            f"[{min_m}, {max_m}] m without a third drone closer than {min_m} m"
        )
    rows = np.concatenate([np.arange(k * n_agents, (k + 1) * n_agents) for k in kept])
    per_sample = {k: v[rows] for k, v in arrays.items() if k not in IMAGE_KEYS + SCALAR_KEYS}
    per_sample["pos_world_enu"] = np.concatenate(new_pos).astype(np.float32)
    per_sample["targets"] = np.concatenate([t["rey_body"] for t in labels]).astype(np.float32)
    per_sample["rey_world_enu"] = np.concatenate([t["rey_world"] for t in labels]).astype(
        np.float32
    )
    per_sample["n_neighbours"] = np.concatenate([t["n_neighbours"] for t in labels]).astype(
        np.int16
    )
    per_sample["nearest_m"] = np.concatenate([t["nearest_m"] for t in labels]).astype(np.float32)
    run = RunData(
        split,
        run_index,
        str(arrays["termination"]),
        np.asarray(arrays["migration_point_world_enu"], dtype=np.float64),
        np.concatenate(images),
        per_sample,
    )
    return encode_run(run)


def _draw_and_store(
    out: Path,
    source: Path,
    draw: CloseRangeDraw,
    renderer_name: str,
    flocking: FlockingParams,
    split: str,
    run_index: int,
) -> None:
    run = close_range_run(source, split, run_index, renderer_name, flocking, draw)
    write_run_bytes(out, split, run_index, run)


def close_range(
    source: str | Path,
    out: str | Path,
    draw: CloseRangeDraw | None = None,
    workers: int | None = None,
    progress: bool = True,
    command: str = "",
) -> Dataset:
    """Draw close encounters from every run of the complete dataset at `source` into `out`
    (resumable), as `draw` says (default: `CloseRangeDraw()`)."""
    source, out = Path(source), Path(out)
    draw = draw or CloseRangeDraw()
    if out.resolve() == source.resolve():
        raise DatasetError(
            f"{out}: write the close-range dataset to another folder than its source"
        )
    original = open_dataset(source)
    manifest = original.manifest
    if "scene_variation" in manifest:
        raise DatasetError(
            f"{source}: its runs are drawn against varied scenes; draw close encounters from a "
            "dataset in the default scene (and vary that one with `dataset rerender`)"
        )
    spec = DatasetSpec.from_dict(manifest["spec"])
    renderer_name = str(manifest.get("renderer", spec.renderer))
    check_or_write_spec(out, spec)
    remove_partial_files(out)
    runs = {split: [r["run_index"] for r in manifest["splits"][split]["runs"]] for split in SPLITS}
    args = (out, source, draw, renderer_name, spec.flocking)
    each_missing_run(out, runs, _draw_and_store, args, workers, progress, "close range")
    extra: dict[str, Any] = {
        "close_range_from": {"id": manifest["id"], "root": str(source)},
        "close_range": asdict(draw),
    }
    if "aggregation" in manifest:
        extra["aggregation"] = manifest["aggregation"]
    return finalize(out, spec, runs, command, extra=extra, id_extra=extra)
