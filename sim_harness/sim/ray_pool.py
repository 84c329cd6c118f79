"""The Ray implementation of `sim_harness.sim.executor.TaskPool` (the optional `cluster` extra).

Imported only when a command is given `--ray`. Each task asks for one CPU; the pool keeps twice
the cluster's CPUs in flight. A task whose worker dies (process killed, node lost) is run again by
Ray, up to `MAX_RETRIES` times: a run is a pure function of its seed, so a retried run gives the
same bytes. An exception raised by the task itself is not retried: it is raised in the driver.

`--ray local` starts a Ray instance on this machine bound to 127.0.0.1 only (Ray otherwise binds
every interface): no dashboard, no usage statistics.
"""

from __future__ import annotations

import logging
import os
import signal
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any, Generic, TypeVar

from sim_harness.errors import SimError
from sim_harness.sim.executor import INSTALL_HINT, ClusterChoice, PoolInfo, Task

log = logging.getLogger(__name__)

R = TypeVar("R")
MAX_RETRIES = 3  # attempts after the first, for a worker that died (not for a task's exception)
SLOTS_PER_CPU = 2
# Test-only fault injection: "LABEL@DIR" makes the first attempt of the task labelled LABEL kill
# its own worker process (SIGKILL), leaving DIR/LABEL as the mark that it did. Unset: no effect.
KILL_ONCE_ENV = "SWARM_SIM_TEST_KILL_ONCE"


class ClusterError(SimError):
    """Ray is missing, the cluster cannot be reached, or a run failed on every attempt."""


def _import_ray(loopback_only: bool) -> Any:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if loopback_only:
        # Read once, when ray is imported: 0 makes a new instance bind 127.0.0.1 only.
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray: {INSTALL_HINT}") from None
    if loopback_only:
        from ray._private import ray_constants

        if ray_constants.ENABLE_RAY_CLUSTER:
            raise ClusterError(
                "--ray local: ray was imported before the pool could bind it to 127.0.0.1; "
                "start a cluster with `ray start --head` and use --ray auto"
            )
    return ray


def _kill_first_attempt(label: str) -> None:
    spec = os.environ.get(KILL_ONCE_ENV, "")
    target, _, folder = spec.partition("@")
    if not spec or target != label or not folder:
        return
    try:
        fd = os.open(Path(folder) / label.replace("/", "_"), os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return  # a retry: run normally
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)


def _run_task(fn: Callable[..., Any], label: str, *args: Any) -> Any:
    _kill_first_attempt(label)
    return fn(*args)


class _RayTask(Generic[R]):
    def __init__(self, pool: RayPool, ref: Any, label: str) -> None:
        self._pool, self.ref, self.label = pool, ref, label

    def result(self) -> R:
        return self._pool._get(self)  # type: ignore[no-any-return]


class RayPool:
    """Tasks on a Ray cluster. `same_files` is False: workers may run on other machines."""

    same_files = False

    def __init__(self, choice: ClusterChoice) -> None:
        local = choice.address == "local"
        self._ray = ray = _import_ray(loopback_only=local)
        kwargs: dict[str, Any] = {
            "include_dashboard": False,
            "configure_logging": False,
            "logging_level": logging.WARNING,
        }
        if local:
            kwargs.update(address="local", num_cpus=choice.num_cpus)
            kwargs["_node_ip_address"] = "127.0.0.1"
        else:
            kwargs["address"] = choice.address
        try:
            context = ray.init(**kwargs)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise ClusterError(
                f"--ray {choice.address}: cannot start or reach the cluster ({exc})"
            ) from None
        self._remote = ray.remote(max_retries=MAX_RETRIES, retry_exceptions=False)(_run_task)
        nodes = [n for n in ray.nodes() if n.get("Alive")]
        cpus = int(ray.cluster_resources().get("CPU", 0))
        address = context.address_info.get("gcs_address", choice.address)
        self.info = PoolInfo("ray", len(nodes), cpus, max(SLOTS_PER_CPU * cpus, 1), address)
        log.info("%s", self.info.describe())

    def share(self, value: Any) -> Any:
        return self._ray.put(value)  # a top-level task argument: the task receives the value

    def submit(self, fn: Callable[..., R], *args: Any, label: str = "") -> Task[R]:
        return _RayTask(self, self._remote.remote(fn, label, *args), label)

    def wait(self, tasks: Collection[Task[R]]) -> list[Task[R]]:
        by_ref = {t.ref: t for t in tasks if isinstance(t, _RayTask)}
        ready, _ = self._ray.wait(list(by_ref), num_returns=1)
        more, _ = self._ray.wait(list(by_ref), num_returns=len(by_ref), timeout=0)
        return [by_ref[r] for r in {*ready, *more}]

    def _get(self, task: _RayTask[Any]) -> Any:
        exceptions = self._ray.exceptions
        try:
            return self._ray.get(task.ref)
        except exceptions.RayTaskError as exc:
            cause = exc.cause
            if isinstance(cause, Exception):
                raise cause from None
            raise
        except (exceptions.WorkerCrashedError, exceptions.NodeDiedError) as exc:
            raise ClusterError(
                f"{task.label or 'a task'}: its worker died on each of {MAX_RETRIES + 1} "
                f"attempt(s) ({type(exc).__name__})"
            ) from None

    def close(self) -> None:
        self._ray.shutdown()
