"""Draw a dataset's images again with another renderer, from the poses it recorded.

Every sample records its drone's pose (`pos_world_enu`, `q_world_body`), and a run's samples are
step-major with every agent at every step, so each step's whole flock can be put back and drawn
again: the same states and labels, new images. What it is for: a change of renderer (e.g.
`raycast-aa`, which no longer loses far drones between pixels) without flying again; aggregated
datasets, whose states came from a CNN that is gone, can only be redrawn this way.

The result is a normal dataset folder: its spec is the source's with the new renderer, its
manifest records the source (`rerendered_from`) and keeps the source's aggregation record. Runs
are written one file at a time, atomically: an interrupted redraw resumes with the same command.
Poses are stored as float32, so a redrawn image can differ from the source's by a pixel where an
edge falls within a micrometre of a ray: redrawing with the source's own renderer reproduces it
to that.

`vary_scene` (a seed) draws each run against its own ground and sky (`scene.random_scene`, from
SeedSequence([seed, split, run])) instead of the default scene: the same flock over fields the
network has never seen, so that it learns the drones rather than one texture.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.validation import require_int_range
from sim_harness.dataset.generate import check_or_write_spec, finalize
from sim_harness.dataset.runs import RunData
from sim_harness.dataset.spec import SPLITS, DatasetSpec
from sim_harness.dataset.store import (
    Dataset,
    encode_run,
    open_dataset,
    remove_partial_files,
    run_path,
    stored_runs,
    write_run_bytes,
)
from sim_harness.errors import DatasetError
from sim_harness.sim.executor import open_pool
from sim_harness.sim.progress import progress_bar
from sim_harness.sim.renderers import make_renderer, require_renderer
from sim_harness.sim.scene import SCENE_RANGES, SceneSpec, random_scene
from sim_harness.sim.world import World

IMAGE_KEYS = ("images", "pixel_sum", "pixel_sumsq")
SCALAR_KEYS = ("run_index", "termination", "migration_point_world_enu")


def run_scene(vary_scene: int | None, split: str, run_index: int) -> SceneSpec | None:
    """The scene run `run_index` of `split` is drawn against: None (the default) or a random one."""
    if vary_scene is None:
        return None
    return random_scene(np.random.default_rng([vary_scene, SPLITS.index(split), run_index]))


def flock_steps(agent: NDArray[np.generic], what: str) -> tuple[int, int]:
    """(steps, agents) of a run whose samples are every agent at every step, in that order (its
    `agent` column); a DatasetError naming `what` otherwise."""
    agent = np.asarray(agent, dtype=np.intp)
    n_agents = int(agent.max()) + 1 if agent.size else 0
    n_steps, rest = divmod(len(agent), max(n_agents, 1))
    if not n_agents or rest or not np.array_equal(agent, np.tile(np.arange(n_agents), n_steps)):
        raise DatasetError(
            f"{what}: its samples are not every agent at every step, so the flock of a step "
            "cannot be put back"
        )
    return n_steps, n_agents


def redraw_run(
    source: Path, split: str, run_index: int, renderer_name: str, vary_scene: int | None = None
) -> bytes:
    """The bytes of run `run_index` of `split` of the dataset at `source`, its images redrawn."""
    with np.load(run_path(source, split, run_index)) as z:
        arrays = {k: z[k] for k in z.files if k not in IMAGE_KEYS + SCALAR_KEYS}
        termination = str(z["termination"])
        migration = np.asarray(z["migration_point_world_enu"], dtype=np.float64)
    n_steps, n_agents = flock_steps(arrays["agent"], f"run {split}/{run_index} of {source}")
    pos = arrays["pos_world_enu"].astype(np.float64).reshape(n_steps, n_agents, 3)
    q = arrays["q_world_body"].astype(np.float64).reshape(n_steps, n_agents, 4)
    renderer = make_renderer(renderer_name, run_scene(vary_scene, split, run_index))
    with World(n_agents) as world:
        images = np.concatenate([renderer.render(world, pos[k], q[k]) for k in range(n_steps)])
    run = RunData(split, run_index, termination, migration, images, arrays)
    return encode_run(run)


def _redraw_and_store(
    source: Path, out: Path, renderer_name: str, vary: int | None, split: str, run_index: int
) -> None:
    write_run_bytes(
        out, split, run_index, redraw_run(source, split, run_index, renderer_name, vary)
    )


def each_missing_run(
    out: Path,
    runs: dict[str, list[int]],
    work: Callable[..., None],
    args: tuple[Any, ...],
    workers: int | None,
    progress: bool,
    desc: str,
) -> None:
    """Call `work(*args, split, run_index)` in a pool for every run of `runs` (per split) that
    `out` does not hold yet, with a progress bar; the first failure is raised."""
    todo = [(split, k) for split in SPLITS for k in runs[split] if k not in stored_runs(out, split)]
    total = sum(len(v) for v in runs.values())
    with (
        open_pool(workers or os.cpu_count() or 1, None) as pool,
        progress_bar(
            total=total, initial=total - len(todo), desc=desc, enabled=progress, unit="run"
        ) as bar,
    ):
        pending = [pool.submit(work, *args, s, k, label=f"{s} run {k}") for s, k in todo]
        while pending:
            for task in pool.wait(pending):
                task.result()  # raises what the work raised
                pending.remove(task)
                bar.update(1)


def rerender(
    source: str | Path,
    out: str | Path,
    renderer_name: str,
    workers: int | None = None,
    progress: bool = True,
    command: str = "",
    vary_scene: int | None = None,
) -> Dataset:
    """Redraw every run of the complete dataset at `source` into `out` (resumable); with
    `vary_scene` (a seed >= 0), each run against its own random scene."""
    source, out = Path(source), Path(out)
    require_renderer(renderer_name)
    if vary_scene is not None:
        require_int_range("vary-scene", vary_scene, 0)
    original = open_dataset(source)
    manifest = original.manifest
    if out.resolve() == source.resolve():
        raise DatasetError(f"{out}: write the redrawn dataset to another folder than its source")
    spec = dataclasses.replace(DatasetSpec.from_dict(manifest["spec"]), renderer=renderer_name)
    check_or_write_spec(out, spec)
    remove_partial_files(out)
    runs = {split: [r["run_index"] for r in manifest["splits"][split]["runs"]] for split in SPLITS}
    args = (source, out, renderer_name, vary_scene)
    each_missing_run(out, runs, _redraw_and_store, args, workers, progress, "redraw")
    extra: dict[str, Any] = {
        "rerendered_from": {
            "id": manifest["id"],
            "root": str(source),
            "renderer": manifest.get("renderer", "pybullet"),
        }
    }
    if "aggregation" in manifest:
        extra["aggregation"] = manifest["aggregation"]
    if vary_scene is not None:
        extra["scene_variation"] = {"seed": vary_scene, "ranges": SCENE_RANGES}
    return finalize(out, spec, runs, command, extra=extra, id_extra=extra)
