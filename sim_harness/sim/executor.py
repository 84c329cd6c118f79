"""Where the runs of a long job execute: one interface, two pools, chosen from the command line.

A *task* is one run (a dataset run, an aggregation flight, one suite flight): a module-level
function and its arguments. Every job drives its pool the same way: keep up to `pool.info.slots`
tasks in flight (`submit`), block until some finish (`wait`), take their results, submit more.
The bound is the back-pressure: a finished run waits in the driver only until its result is taken.

- `LocalPool`: this machine's processes (spawned), or the calling process itself for one worker.
  The default; Ray is never imported.
- `sim_harness.sim.ray_pool.RayPool`: a Ray cluster (`--ray auto|local|HOST:PORT`), imported only
  when chosen. Its workers may not see this machine's files (`same_files` is False).

`open_pool` picks one from a `ClusterChoice` (None: the local pool).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import sys
from collections.abc import Callable, Collection, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from sim_harness.errors import ConfigError

R = TypeVar("R")
R_co = TypeVar("R_co", covariant=True)

INSTALL_HINT = "pip install -e '.[cluster]'"


class Task(Protocol[R_co]):
    """One submitted task; `result()` blocks until it is done and raises what the task raised."""

    def result(self) -> R_co: ...


@dataclass(frozen=True)
class PoolInfo:
    """What a pool runs on: `kind` "local" or "ray", its nodes and CPUs, tasks kept in flight."""

    kind: str
    nodes: int
    cpus: int
    slots: int
    address: str = ""

    def describe(self) -> str:
        if self.kind == "local":
            return f"local pool: {self.cpus} worker process(es)"
        return (
            f"ray cluster {self.address}: {self.nodes} node(s), {self.cpus} CPU(s), "
            f"up to {self.slots} runs in flight"
        )

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "nodes": self.nodes, "cpus": self.cpus}

    def banner(self) -> str | None:
        """The line a job prints when it starts on this pool (None: the local pool says nothing,
        as before pools were pluggable)."""
        return None if self.kind == "local" else self.describe()


class TaskPool(Protocol):
    """Runs module-level functions somewhere; see the module docstring for the protocol."""

    info: PoolInfo
    same_files: bool  # tasks see this process's files at the same paths (same machine)

    def share(self, value: Any) -> Any:
        """A handle to pass as an argument of many tasks; the task receives `value` itself."""
        ...

    def submit(self, fn: Callable[..., R], *args: Any, label: str = "") -> Task[R]:
        """Start `fn(*args)`; `label` names the run in errors (e.g. "train run 12")."""
        ...

    def wait(self, tasks: Collection[Task[R]]) -> list[Task[R]]:
        """Block until at least one of `tasks` is done; return the done ones."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class ClusterChoice:
    """`--ray ADDRESS` and its options. `address`: "auto" (the cluster this machine belongs to),
    "local" (start one here, loopback only), or the head's HOST:PORT.

    `shared_dir`: the output folder as the workers see it (a shared filesystem): workers write
    their runs there themselves instead of returning them to the driver. `num_cpus`: the CPUs of a
    "local" cluster (default: all of this machine's)."""

    address: str
    shared_dir: Path | None = None
    num_cpus: int | None = None

    def __post_init__(self) -> None:
        if not self.address.strip():
            raise ConfigError("--ray: expected auto, local or the head's HOST:PORT, got ''")
        if self.num_cpus is not None and self.num_cpus < 1:
            raise ConfigError(f"ray.num_cpus must be >= 1, got {self.num_cpus}")


class _Done(Generic[R]):
    """A task the calling process ran at submission (the one-worker pool)."""

    def __init__(self, fn: Callable[..., R], args: tuple[Any, ...]) -> None:
        self._value: R | None = None
        self._error: BaseException | None = None
        try:
            self._value = fn(*args)
        except Exception as exc:  # re-raised by result(), as a pool's future would
            self._error = exc

    def result(self) -> R:
        if self._error is not None:
            raise self._error
        return self._value  # type: ignore[return-value]


class LocalPool:
    """`workers` spawned processes on this machine (2 tasks in flight per process); with one
    worker, tasks run in the calling process, one at a time, as they are submitted."""

    same_files = True

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        self._executor = (
            ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"))
            if workers > 1
            else None
        )
        self.info = PoolInfo("local", 1, workers, 2 * workers if workers > 1 else 1)

    def share(self, value: Any) -> Any:
        return value

    def submit(self, fn: Callable[..., R], *args: Any, label: str = "") -> Task[R]:
        if self._executor is None:
            return _Done(fn, args)
        return self._executor.submit(fn, *args)

    def wait(self, tasks: Collection[Task[R]]) -> list[Task[R]]:
        futures = [t for t in tasks if isinstance(t, Future)]
        done: list[Task[R]] = [t for t in tasks if isinstance(t, _Done)]
        if futures and not done:
            finished, _ = wait(futures, return_when=FIRST_COMPLETED)
            done.extend(finished)
        return done

    def close(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)


@contextmanager
def open_pool(workers: int, cluster: ClusterChoice | None) -> Iterator[TaskPool]:
    """The pool a job runs on: Ray when `cluster` is given, else `workers` local processes."""
    pool: TaskPool
    if cluster is None:
        pool = LocalPool(workers)
    else:
        from sim_harness.sim.ray_pool import RayPool  # only here: Ray is an optional extra

        pool = RayPool(cluster)
    try:
        yield pool
    finally:
        pool.close()


def announce(pool: TaskPool, enabled: bool = True) -> None:
    """Print the pool's start line (a cluster's nodes and CPUs) on stderr."""
    banner = pool.info.banner()
    if enabled and banner:
        print(banner, file=sys.stderr, flush=True)


def add_cluster_options(parser: argparse.ArgumentParser, shared_dir: bool = True) -> None:
    """`--ray ADDRESS` (and `--ray-shared-dir DIR` where the job writes dataset runs)."""
    parser.add_argument(
        "--ray",
        metavar="ADDRESS",
        default=None,
        help="run on a Ray cluster: auto (the cluster this machine joined with `ray start`), "
        f"local (start one here), or the head's HOST:PORT; needs `{INSTALL_HINT}`",
    )
    if shared_dir:
        parser.add_argument(
            "--ray-shared-dir",
            type=Path,
            default=None,
            metavar="DIR",
            help="with --ray: the output folder as the worker nodes see it (a shared "
            "filesystem); workers write runs there instead of sending them to this process",
        )


def cluster_choice(args: argparse.Namespace) -> ClusterChoice | None:
    """The `ClusterChoice` of parsed `add_cluster_options` arguments (None: the local pool)."""
    shared = getattr(args, "ray_shared_dir", None)
    if args.ray is None:
        if shared is not None:
            raise ConfigError("--ray-shared-dir needs --ray ADDRESS")
        return None
    if getattr(args, "workers", None) is not None:
        raise ConfigError(
            "--workers sets the local pool's processes; with --ray the cluster's CPUs set it: "
            "drop one of them"
        )
    return ClusterChoice(args.ray, shared_dir=shared)
