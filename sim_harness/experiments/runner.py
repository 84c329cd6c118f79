"""Flying the experiment suites (`sim_harness.experiments.suites`): teacher and CNN, same seeds.

Every experiment of the suite is flown by both controllers over the suite's seeds. Flights run in
this process (`workers=1`), in a pool of spawned processes, or on a Ray cluster (`cluster`); each
worker loads the policy once with one torch thread (`worker_policy`). Results are ordered by
experiment, controller and seed, whatever the order in which the flights finish.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.policy import Policy
from sim_harness.experiments.suites import CONTROLLERS, EXPERIMENTS, LABELS, SuiteConfig
from sim_harness.experiments.vision_controller import (
    VisionControlConfig,
    VisionController,
    load_policy,
)
from sim_harness.experiments.worker_policy import PolicySource, adopt, release, worker_policy
from sim_harness.sim.controllers import Controller, TeacherController
from sim_harness.sim.executor import ClusterChoice, Task, TaskPool, announce, open_pool
from sim_harness.sim.renderers import make_renderer, warn_if_trained_elsewhere
from sim_harness.sim.rollout import FlightLog, fly, save_flight, summarize
from sim_harness.sim.scenarios import build_scenario
from sim_harness.sim.scene import unseen_scene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunRecord:
    """One flight of the suite."""

    experiment: str
    controller: str
    seed: int
    log: FlightLog
    summary: dict[str, Any]


@dataclass
class SuiteResult:
    """Every flight of a suite, plus what identifies the model that flew the CNN runs."""

    config: SuiteConfig
    runs: list[RunRecord]
    model_sha256: str
    model_metadata: dict[str, Any]
    wall_time_s: float = 0.0

    def records(self, experiment: str, controller: str) -> list[RunRecord]:
        """The runs of one experiment and controller, in seed order."""
        return [r for r in self.runs if r.experiment == experiment and r.controller == controller]

    def logs(self, experiment: str, controller: str) -> list[FlightLog]:
        return [r.log for r in self.records(experiment, controller)]


@dataclass(frozen=True)
class Job:
    """One flight to fly: an experiment key, a controller ("teacher" or "cnn") and a seed."""

    experiment: str
    controller: str
    seed: int


def _jobs(config: SuiteConfig) -> list[Job]:
    return [
        Job(e.key, c, seed)
        for e in config.experiment_list
        for c in CONTROLLERS
        for seed in config.seeds
    ]


def _controller(job: Job, config: SuiteConfig, policy: Policy | None) -> Controller:
    flocking = EXPERIMENTS[job.experiment].scenario_config(job.seed).flocking
    if job.controller == "teacher":
        return TeacherController(flocking)
    if policy is None:
        raise RuntimeError("a CNN flight needs the policy")
    law = VisionControlConfig.from_flocking(
        flocking, config.low_pass_cutoff_hz, config.output_jitter_mps, job.seed
    )
    return VisionController(policy, law, config.rates.control_dt_s)


def fly_job(
    job: Job,
    config: SuiteConfig,
    policy: Policy | None,
    progress: bool = False,
    progress_lines: bool | None = None,
) -> RunRecord:
    """Fly one (experiment, controller, seed) of the suite, with a progress bar if `progress`."""
    experiment = EXPERIMENTS[job.experiment]
    scenario = build_scenario(experiment.scenario_config(job.seed, config.duration_s))
    flight = fly(
        scenario,
        _controller(job, config, policy),
        config.rates,
        renderer=(
            make_renderer(config.renderer, unseen_scene(config.ground_seed))
            if job.controller == "cnn"
            else None
        ),
        progress=progress,
        progress_label=f"{job.experiment} / {LABELS[job.controller]} / seed {job.seed}",
        progress_lines=progress_lines,
    )
    return RunRecord(job.experiment, job.controller, job.seed, flight, summarize(flight))


def _fly_in_worker(
    job: Job, config: SuiteConfig, source: PolicySource, progress: bool, lines: bool | None
) -> RunRecord:
    policy = worker_policy(source) if job.controller == "cnn" else None
    return fly_job(job, config, policy, progress, progress_lines=lines)


def _run_jobs(
    jobs: list[Job], config: SuiteConfig, pool: TaskPool, progress: bool
) -> Iterator[tuple[Job, RunRecord]]:
    """Fly `jobs` on `pool`, at most `pool.info.slots` at a time; yields them as they finish."""
    source = pool.share(PolicySource.read(config.model_path, embed=not pool.same_files))
    # Parallel workers share the terminal: redrawn bars would overwrite each other, so lines.
    lines = None if pool.info.slots == 1 else True
    todo = list(reversed(jobs))
    in_flight: dict[Task[RunRecord], Job] = {}
    while todo or in_flight:
        while todo and len(in_flight) < pool.info.slots:
            job = todo.pop()
            label = f"{job.experiment}-{job.controller}-seed-{job.seed}"
            task = pool.submit(_fly_in_worker, job, config, source, progress, lines, label=label)
            in_flight[task] = job
        for task in pool.wait(list(in_flight)):
            yield in_flight.pop(task), task.result()


def run_suite(
    config: SuiteConfig,
    on_run: Callable[[RunRecord, int, int], None] | None = None,
    progress: bool = False,
    cluster: ClusterChoice | None = None,
) -> SuiteResult:
    """Fly every experiment of the suite with both controllers; `on_run(record, done, total)`.

    `progress`: each flight shows its progress (a bar, or plain lines off a terminal).
    `cluster`: fly on Ray instead of `config.workers` local processes (same flights).

    Raises `companion.errors.ModelError` if the model file is missing or fails verification
    (before any flight).
    """
    started = time.perf_counter()
    policy = load_policy(config.model_path, threads=1)
    warn_if_trained_elsewhere(policy.metadata, config.renderer)
    adopt(policy)  # flights run in this process (one worker) use it
    try:
        jobs = _jobs(config)
        records: dict[Job, RunRecord] = {}
        with open_pool(config.workers, cluster) as pool:
            announce(pool)
            flights = _run_jobs(jobs, config, pool, progress)
            for done, (job, record) in enumerate(flights, start=1):
                records[job] = record
                if on_run is not None:
                    on_run(record, done, len(jobs))
        return SuiteResult(
            config=config,
            runs=[records[job] for job in jobs],
            model_sha256=policy.sha256,
            model_metadata=policy.metadata,
            wall_time_s=time.perf_counter() - started,
        )
    finally:
        release(policy)
        policy.close()


def run_dir(out_dir: Path, record: RunRecord) -> Path:
    """Where one run's log lives: `<out>/runs/<experiment>/<controller>/seed-<seed>`."""
    return out_dir / "runs" / record.experiment / record.controller / f"seed-{record.seed}"


def save_runs(result: SuiteResult, out_dir: Path) -> None:
    """Every run's `steps.npz`, `summary.json` and `timing.json` (see `rollout.save_flight`)."""
    for record in result.runs:
        save_flight(record.log, run_dir(out_dir, record))
