"""Dataset aggregation (DAgger, Ross et al. 2011): samples from the states the CNN flies into.

The paper's dataset (`generate`) records random *linear* trajectories. A CNN trained on it meets
other states when it flies the flock, most of all with opposing goals, where the two groups pull
apart and the learned cohesion must hold them (docs/BENCHMARKS.md, "Where the CNN fails"). One
aggregation round flies the current exported policy through the experiment scenarios on training
seeds (0 and up; evaluation uses 1000 and up, so the bar's flights are never seen) and labels every
state it visits with the teacher's Reynolds command, exactly as `generate` labels its own:

- the images are the ones the CNN was given (rendered at capture time, same renderer);
- the target is the teacher's separation + cohesion from the true positions, rotated into the
  body frame with the capture-time attitude (`runs.teacher_targets`);
- a flight stops as a dataset run stops (`runs.termination`): dispersion (> 7 m, the paper's
  dataset domain), arrival, ground or the time limit (15 s); the collision rule is 0.5 m instead
  of 1 m (`default_rules`), so the near misses the CNN flies into are labelled too. A round can
  widen the dispersion rule (up to r_max) and fly longer, to label the stretched flocks of a
  CNN whose cohesion is too weak (`--dispersion-m 12 --max-run-s 30`).
- The dataset's arrival rule (an agent within 1 m of its migration point) ends a flight about
  0.3-0.5 s before the flock arrives as the experiments define it (each goal group's centroid
  within 2 m), and that is where a flock converging on its point bunches: the faster flock's and
  N = 12's closest pairs fall in those last steps (`benchmarks/teacher_envelope.py`). A round flown
  with `after_arrival_s` (`--after-arrival-s S`) drops that rule and flies on through the flock's
  arrival for S more seconds, so the bunching is labelled too.

The result is a normal dataset folder (same store, manifest and `open_dataset`); its manifest
says `"kind": "aggregated"` and names the policy (SHA-256), the experiments and the seeds. Run k
flies experiment `experiments[k % len(experiments)]` with scenario seed `seed_base + k`; runs with
k % 10 == 8 go to the validation split, k % 10 == 9 to the test split (repeat an experiment in
the list to fly it more often). Runs are stored atomically
as they finish, so an interrupted aggregation resumes with the same command. Training uses it with
`swarm-sim train --extra-train DIR` (added to the base dataset's training split).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.validation import require_int_range, require_range
from sim_harness.dataset.generate import check_or_write_spec, finalize, store_run
from sim_harness.dataset.runs import (
    RunData,
    RunTiming,
    sample_arrays,
    teacher_targets,
    termination,
)
from sim_harness.dataset.spec import SPLITS, DatasetSpec
from sim_harness.dataset.store import (
    Dataset,
    encode_run,
    remove_partial_files,
    stored_runs,
    write_run_bytes,
)
from sim_harness.errors import ConfigError
from sim_harness.experiments.suites import EVAL_SEED_BASE, EXPERIMENTS, SHIPPED_MODEL_PATH
from sim_harness.experiments.vision_controller import (
    BatchPolicy,
    VisionControlConfig,
    VisionController,
    load_policy,
)
from sim_harness.experiments.worker_policy import PolicySource, adopt, release, worker_policy
from sim_harness.sim.executor import ClusterChoice, Task, TaskPool, announce, open_pool
from sim_harness.sim.progress import ProgressBar, progress_bar
from sim_harness.sim.renderers import make_renderer, warn_if_trained_elsewhere
from sim_harness.sim.rollout import fly, has_arrived
from sim_harness.sim.scenarios import Scenario, build_scenario

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
StopRule = Callable[[FloatArray, float], str | None]
# Opposing-goal flights end early (dispersion), so they are flown twice as often.
DEFAULT_EXPERIMENTS: tuple[str, ...] = ("common", "opposing", "opposing", "self-propelled")


def default_rules(dispersion_m: float = 7.0, max_run_s: float = 15.0) -> DatasetSpec:
    """The dataset's stop rules, except: a flight ends at 0.5 m (drones ~0.5 m across touch),
    not 1 m, since a CNN flight that dips under 1 m is exactly what should be labelled; and
    after 15 s, since later states of a common-goal flight repeat earlier ones.

    `dispersion_m` above the paper's 7 m labels the stretched flocks a CNN with weak cohesion
    drifts into (opposing goals); it must stay under the perception radius r_max, where the
    teacher still sees every agent. Fly such rounds longer (`max_run_s`): the stretch is slow."""
    return DatasetSpec(collision_m=0.5, dispersion_m=dispersion_m, max_run_s=max_run_s)


@dataclass(frozen=True)
class AggregateConfig:
    """One aggregation round: which policy flies, where, how many runs."""

    model_path: Path = SHIPPED_MODEL_PATH
    runs: int = 60
    experiments: tuple[str, ...] = DEFAULT_EXPERIMENTS
    seed_base: int = 0
    workers: int = 1
    rules: DatasetSpec = field(default_factory=default_rules)  # stop rules, flocking gains
    # None: a flight ends at the dataset's arrival rule (rounds 1-57); S >= 0: it flies on until
    # S seconds after the flock's arrival (the experiments' rule), the dataset's rule dropped
    after_arrival_s: float | None = None

    def __post_init__(self) -> None:
        require_int_range("aggregate.runs", self.runs, 10, 100_000)
        require_int_range("aggregate.workers", self.workers, 1, 256)
        require_int_range("aggregate.seed_base", self.seed_base, 0, EVAL_SEED_BASE - 1)
        if self.after_arrival_s is not None:
            require_range("aggregate.after_arrival_s", self.after_arrival_s, 0.0, 60.0)
        if self.seed_base + self.runs > EVAL_SEED_BASE:
            raise ConfigError(
                f"aggregate.runs: seeds {self.seed_base}..{self.seed_base + self.runs - 1} reach "
                f"the evaluation seeds (>= {EVAL_SEED_BASE}); use at most "
                f"{EVAL_SEED_BASE - self.seed_base} runs"
            )
        r_max = self.rules.flocking.r_max_m
        if self.rules.dispersion_m >= r_max:
            raise ConfigError(
                f"aggregate.dispersion_m must be < the perception radius r_max ({r_max:g} m), "
                f"got {self.rules.dispersion_m:g}"
            )
        if not self.experiments:
            raise ConfigError("aggregate.experiments: name at least one experiment")
        for key in self.experiments:
            if key not in EXPERIMENTS:
                raise ConfigError(
                    f"aggregate.experiments: unknown experiment {key!r}; choose from "
                    f"{', '.join(EXPERIMENTS)}"
                )

    def split_of(self, k: int) -> str:
        return {8: "val", 9: "test"}.get(k % 10, "train")

    def experiment_of(self, k: int) -> str:
        return self.experiments[k % len(self.experiments)]

    def describe(self, model_sha256: str) -> dict[str, Any]:
        described: dict[str, Any] = {
            "kind": "aggregated",
            "policy": {"path": str(self.model_path), "sha256": model_sha256},
            "experiments": list(self.experiments),
            "runs": self.runs,
            "seed_base": self.seed_base,
            "splits": "run k: val if k % 10 == 8, test if k % 10 == 9, else train",
        }
        if self.after_arrival_s is not None:  # absent for the rounds flown before it existed
            described["after_arrival_s"] = self.after_arrival_s
        return described


class _Recorder:
    """Wraps the CNN controller: keeps every image it is given and the teacher's label for it."""

    def __init__(self, inner: VisionController, rules: DatasetSpec) -> None:
        self.inner = inner
        self.rules = rules
        self.name = inner.name
        self.senses = inner.senses
        self.images: list[NDArray[np.uint8]] = []
        self.rows: dict[str, list[FloatArray]] = {}

    def reset(self, n_agents: int) -> None:
        self.inner.reset(n_agents)

    def stage_time_s(self) -> dict[str, float]:
        return self.inner.stage_time_s()

    def command(self, observation: Any) -> FloatArray:
        setpoint = self.inner.command(observation)
        own = observation.own
        n = own.pos_world_enu.shape[0]
        teacher = teacher_targets(own.pos_world_enu, own.q_world_body, self.rules.flocking)
        self.images.append(np.array(observation.images, dtype=np.uint8))
        for key, value in (
            ("rey_body", teacher["rey_body"]),
            ("rey_world", teacher["rey_world"]),
            ("pos", own.pos_world_enu),
            ("vel", own.vel_world_enu),
            ("q", own.q_world_body),
            ("t", np.full(n, own.time_s)),
            ("n_nb", teacher["n_neighbours"]),
            ("nearest", teacher["nearest_m"]),
            ("cmd", setpoint),
        ):
            self.rows.setdefault(key, []).append(np.array(value, dtype=np.float64))
        return setpoint


def stop_rule(config: AggregateConfig, scenario: Scenario) -> StopRule:
    """When one of the round's flights ends (`fly`'s `stop_when`, flown with `stop_at_arrival`
    False: the rule owns the arrival): the dataset's rules or the flock's arrival, whichever comes
    first; with `after_arrival_s`, the rules less the dataset's arrival, and S seconds after the
    flock's arrival."""
    rules, mig, fly_on = config.rules, scenario.migration_points, config.after_arrival_s
    arrived_at: list[float] = []  # when the flock first arrived (the experiments' rule)

    def stop_when(pos: FloatArray, t_s: float) -> str | None:
        if not arrived_at and has_arrived(scenario, pos):
            arrived_at.append(t_s)
        if arrived_at and t_s >= arrived_at[0] + (fly_on or 0.0) - 1e-9:
            return "arrival"
        return termination(rules, pos, mig, t_s, arrival=fly_on is None)

    return stop_when


def fly_and_record(config: AggregateConfig, k: int, policy: BatchPolicy) -> RunData:
    """Run k of the round: the CNN flies its scenario; every visited state becomes samples."""
    experiment = EXPERIMENTS[config.experiment_of(k)]
    scenario_config = experiment.scenario_config(config.seed_base + k)
    scenario = build_scenario(scenario_config)
    rules = config.rules
    law = VisionControlConfig.from_flocking(scenario_config.flocking)
    recorder = _Recorder(VisionController(policy, law, rules.rates.control_dt_s), rules)
    mig = scenario.migration_points
    renderer = make_renderer(rules.renderer)
    flight = fly(
        scenario,
        recorder,
        rules.rates,
        renderer=renderer,
        stop_when=stop_rule(config, scenario),
        stop_at_arrival=False,
    )
    n_steps, n = len(recorder.images), scenario.n_agents
    cmd = recorder.rows.pop("cmd")
    arrays = sample_arrays(recorder.rows, n_steps, n, np.concatenate(cmd))
    stages = flight.stage_time_s
    timing = RunTiming(  # the teacher labels inside the controller's step, after the CNN
        render_s=stages.get("render", 0.0),
        physics_s=stages.get("physics", 0.0),
        teacher_s=max(stages.get("control", 0.0) - stages.get("inference", 0.0), 0.0),
    )
    # the dataset's (3,) migration point field: agent 0's (NaN without one)
    return RunData(
        config.split_of(k),
        k,
        flight.stop_reason,
        np.asarray(mig[0], dtype=np.float64),
        np.concatenate(recorder.images),
        arrays,
        timing,
    )


def _make_run(
    worker_root: Path | None, config: AggregateConfig, k: int, source: PolicySource
) -> tuple[int, bytes | None]:
    """Fly run k (in a worker): its size, and its file's bytes for the driver to store, or None
    when written here under `worker_root` (a folder it shares with the driver)."""
    run = fly_and_record(config, k, worker_policy(source))
    data = encode_run(run)
    if worker_root is None:
        return run.n_samples, data
    write_run_bytes(worker_root, run.split, k, data)
    return run.n_samples, None


def _fly_rounds(
    root: Path,
    config: AggregateConfig,
    todo: list[int],
    pool: TaskPool,
    worker_root: Path | None,
    bar: ProgressBar[Any],
) -> None:
    """Fly runs `todo` on `pool`, at most `pool.info.slots` in flight, storing each as it ends."""
    source = pool.share(PolicySource.read(config.model_path, embed=not pool.same_files))
    pending = list(reversed(todo))
    in_flight: dict[Task[tuple[int, bytes | None]], int] = {}
    while pending or in_flight:
        while pending and len(in_flight) < pool.info.slots:
            k = pending.pop()
            task = pool.submit(
                _make_run, worker_root, config, k, source, label=f"aggregate-run-{k}"
            )
            in_flight[task] = k
        for task in pool.wait(list(in_flight)):
            k = in_flight.pop(task)
            n_samples, data = task.result()
            store_run(root, config.split_of(k), k, data)
            bar.update()
            bar.set_postfix(samples=n_samples)


def aggregate(
    root: str | Path,
    config: AggregateConfig,
    progress: bool = True,
    command: str = "",
    cluster: ClusterChoice | None = None,
) -> Dataset:
    """Fly (or resume) one aggregation round into `root`; returns the dataset when complete.

    `cluster`: fly on Ray (runs returned to this process, or written by the workers under
    `cluster.shared_dir`) instead of `config.workers` local processes; the same dataset.
    """
    root = Path(root)
    policy = load_policy(config.model_path, threads=1)  # refuse a bad file before any flight
    try:
        warn_if_trained_elsewhere(policy.metadata, config.rules.renderer)
        adopt(policy)  # runs flown in this process (one worker) use it
        return _aggregate(root, config, policy.sha256, progress, command, cluster)
    finally:
        release(policy)
        policy.close()


def _aggregate(
    root: Path,
    config: AggregateConfig,
    sha: str,
    progress: bool,
    command: str,
    cluster: ClusterChoice | None,
) -> Dataset:
    """`aggregate` once the policy (SHA-256 `sha`) has been loaded and checked."""
    rules = config.rules
    check_or_write_spec(root, rules)
    described = config.describe(sha)
    marker = root / "aggregation.json"
    if marker.exists():
        previous = json.loads(marker.read_text())
        if previous != described:
            changed = sorted(k for k in described if previous.get(k) != described[k])
            raise ConfigError(
                f"{root} holds an aggregation with other settings ({', '.join(changed)}); "
                "use another folder or the same command"
            )
    else:
        marker.write_text(json.dumps(described, indent=2) + "\n")
    remove_partial_files(root)
    done = {k for split in SPLITS for k in stored_runs(root, split)}
    todo = [k for k in range(config.runs) if k not in done]
    with open_pool(config.workers, cluster) as pool:
        announce(pool, progress)
        worker_root = root if pool.same_files else (cluster.shared_dir if cluster else None)
        with progress_bar(
            total=config.runs, initial=len(done), desc="aggregate", enabled=progress, unit="run"
        ) as bar:
            _fly_rounds(root, config, todo, pool, worker_root, bar)
    runs = {split: sorted(stored_runs(root, split)) for split in SPLITS}
    extra = {"aggregation": described}
    return finalize(root, rules, runs, command, extra=extra, id_extra=described)
