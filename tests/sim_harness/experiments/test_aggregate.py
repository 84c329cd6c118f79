"""Dataset aggregation: the CNN flies, the teacher labels what it visits; fine-tuning on it."""

import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from companion.flocking import pairwise_offsets
from sim_harness.dataset.runs import teacher_targets
from sim_harness.dataset.spec import DatasetSpec
from sim_harness.dataset.store import open_dataset
from sim_harness.errors import ConfigError
from sim_harness.experiments.aggregate import (
    AggregateConfig,
    aggregate,
    default_rules,
    stop_rule,
)
from sim_harness.experiments.suites import EXPERIMENTS
from sim_harness.learning.batches import subset
from sim_harness.learning.checkpoint import load_checkpoint
from sim_harness.learning.export import load_eager_model
from sim_harness.learning.train import TrainConfig, train, validation_loss
from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.rollout import FlightLog, fly, has_arrived
from sim_harness.sim.scenarios import Scenario, build_scenario


def short_rules() -> DatasetSpec:
    return DatasetSpec(collision_m=0.5, max_run_s=0.8)  # 8 control steps per flight at most


@pytest.fixture(scope="module")
def aggregated(untrained_policy_path, tmp_path_factory) -> tuple[Path, AggregateConfig]:
    root = tmp_path_factory.mktemp("agg") / "round1"
    config = AggregateConfig(model_path=untrained_policy_path, runs=10, rules=short_rules())
    aggregate(root, config, progress=False, command="pytest aggregate")
    return root, config


def test_runs_are_split_by_index_and_the_manifest_names_the_policy(aggregated) -> None:
    root, config = aggregated
    dataset = open_dataset(root)
    manifest = dataset.manifest
    assert [r["run_index"] for r in manifest["splits"]["train"]["runs"]] == list(range(8))
    assert [r["run_index"] for r in manifest["splits"]["val"]["runs"]] == [8]
    assert [r["run_index"] for r in manifest["splits"]["test"]["runs"]] == [9]
    info = manifest["aggregation"]
    assert info["kind"] == "aggregated" and info["seed_base"] == 0
    assert info["experiments"] == ["common", "opposing", "opposing", "self-propelled"]
    policy_bytes = Path(config.model_path).read_bytes()
    assert info["policy"]["sha256"] == hashlib.sha256(policy_bytes).hexdigest()
    train_split = dataset.split("train")
    assert train_split.images.shape == (train_split.n_samples, 64, 384)
    assert train_split.n_samples > 0 and train_split.n_samples % 9 == 0  # whole steps of 9


def test_every_label_is_the_teachers_command_for_the_recorded_state(aggregated) -> None:
    root, config = aggregated
    split = open_dataset(root).split("train")
    meta = split.meta
    run, time_s = meta["run"], meta["time_s"]
    for r in np.unique(run):
        for t in np.unique(time_s[run == r]):
            rows = np.flatnonzero((run == r) & (time_s == t))
            pos = meta["pos_world_enu"][rows].astype(np.float64)
            q = meta["q_world_body"][rows].astype(np.float64)
            expected = teacher_targets(pos, q, config.rules.flocking)["rey_body"]
            np.testing.assert_allclose(split.targets[rows], expected, atol=2e-3)
            d = np.linalg.norm(pairwise_offsets(pos), axis=-1)[np.triu_indices(len(rows), 1)]
            # nothing outside the stop rules is recorded (float32 positions: small tolerance)
            assert d.min() >= config.rules.collision_m - 1e-3
            assert d.max() <= config.rules.dispersion_m + 1e-3


def test_resuming_is_a_no_op_and_other_settings_are_refused(aggregated) -> None:
    root, config = aggregated
    before = open_dataset(root).manifest["id"]
    again = aggregate(root, config, progress=False, command="pytest aggregate again")
    assert again.manifest["id"] == before
    other = AggregateConfig(
        model_path=config.model_path, runs=10, experiments=("common",), rules=short_rules()
    )
    with pytest.raises(ConfigError, match="experiments"):
        aggregate(root, other, progress=False)


@pytest.mark.parametrize(
    "overrides,field",
    [
        ({"seed_base": 995, "runs": 10}, "aggregate.runs"),
        ({"seed_base": 1000}, "aggregate.seed_base"),
        ({"experiments": ("common", "loop")}, "aggregate.experiments"),
        ({"runs": 3}, "aggregate.runs"),
        ({"rules": default_rules(dispersion_m=20.0)}, "aggregate.dispersion_m"),
        ({"after_arrival_s": -0.5}, "aggregate.after_arrival_s"),
    ],
)
def test_bad_settings_name_the_field(overrides, field) -> None:
    with pytest.raises(ConfigError, match=field):
        AggregateConfig(**overrides)


def _teacher_flight(config: AggregateConfig, seed: int = 300) -> tuple[FlightLog, Scenario]:
    """The faster flock flown by the teacher (no cameras: quick) under a round's stop rule."""
    scenario_config = EXPERIMENTS["vmax4"].scenario_config(seed)
    scenario = build_scenario(scenario_config)
    log = fly(
        scenario,
        TeacherController(scenario_config.flocking),
        stop_when=stop_rule(config, scenario),
        stop_at_arrival=False,
    )
    return log, scenario


def test_after_arrival_labels_the_bunching_the_datasets_arrival_rule_cuts_off() -> None:
    cut, scenario = _teacher_flight(AggregateConfig())
    assert cut.stop_reason == "arrival"  # an agent within 1 m of the point ...
    assert not has_arrived(scenario, cut.pos_world_enu[-1])  # ... before the flock arrives
    on, _ = _teacher_flight(AggregateConfig(after_arrival_s=0.3, rules=default_rules(max_run_s=40)))
    arrived = [has_arrived(scenario, p) for p in on.pos_world_enu]
    t_arrival = on.time_s[arrived.index(True)]
    assert on.stop_reason == "arrival"
    assert on.time_s[-1] == pytest.approx(t_arrival + 0.3, abs=0.11)  # within a control step
    # the flock converging on its point comes closer than anything the cut flight recorded
    assert np.nanmin(on.d_min_m) < np.nanmin(cut.d_min_m) - 0.1
    # the other rules still hold: a pair under the collision rule ends the flight
    tight = AggregateConfig(after_arrival_s=5.0, rules=default_rules(max_run_s=40.0))
    tight = dataclasses.replace(tight, rules=dataclasses.replace(tight.rules, collision_m=1.2))
    log, _ = _teacher_flight(tight)
    assert log.stop_reason == "collision" and np.nanmin(log.d_min_m) < 1.2


def test_the_round_records_its_after_arrival_setting_only_when_set() -> None:
    assert "after_arrival_s" not in AggregateConfig().describe("sha")  # rounds 1-57 resume as-is
    assert AggregateConfig(after_arrival_s=2.0).describe("sha")["after_arrival_s"] == 2.0


def test_default_rules_label_near_misses_but_stay_in_the_dataset_domain() -> None:
    rules = default_rules()
    assert rules.collision_m == 0.5 and rules.dispersion_m == 7.0
    stretched = default_rules(dispersion_m=12.0, max_run_s=30.0)
    assert (stretched.dispersion_m, stretched.max_run_s, stretched.collision_m) == (12.0, 30.0, 0.5)
    with pytest.raises(ConfigError, match="dispersion_m"):
        default_rules(dispersion_m=0.4)


def test_the_cli_refuses_a_dispersion_beyond_r_max_before_writing(tmp_path, capsys) -> None:
    from sim_harness.cli import main

    out = tmp_path / "a"
    assert main(["dataset", "aggregate", "--out", str(out), "--dispersion-m", "21"]) == 2
    assert "aggregate.dispersion_m must be < the perception radius r_max" in capsys.readouterr().err
    assert not out.exists()


def test_the_cli_refuses_a_negative_after_arrival_before_writing(tmp_path, capsys) -> None:
    from sim_harness.cli import main

    out = tmp_path / "a"
    assert main(["dataset", "aggregate", "--out", str(out), "--after-arrival-s", "-1"]) == 2
    assert "aggregate.after_arrival_s: -1 is outside the allowed range" in capsys.readouterr().err
    assert not out.exists()


def test_fine_tuning_starts_from_the_given_weights_and_adds_the_aggregated_split(
    aggregated, smoke_dataset, untrained_policy_path, tmp_path
) -> None:
    root, _ = aggregated
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "finetune",
        max_epochs=1,
        batch_size=32,
        limit_val=32,
        progress=False,
        extra_train=(root,),
        init_from=untrained_policy_path,
    )
    result = train(config)
    state = load_checkpoint(result.out_dir / "last.ckpt")
    assert state["init_from"] == str(untrained_policy_path)
    assert state["config"]["extra_train"] == [str(root)]
    init, _ = load_eager_model(untrained_policy_path)
    val = subset(open_dataset(smoke_dataset).split("val"), 32, config.seed + 1, 2**30)
    expected = validation_loss(init, val, 512, torch.device("cpu"))
    assert result.initial_val_loss == pytest.approx(expected, rel=1e-5)
    assert state["model_config"]["pixel_mean"] == pytest.approx(120.0)
    n_base = open_dataset(smoke_dataset).split("train").n_samples
    n_extra = open_dataset(root).split("train").n_samples
    log = [json.loads(line) for line in (result.out_dir / "metrics.jsonl").read_text().splitlines()]
    assert log[0]["epoch"] == 1
    assert state["train_samples"] == n_base + n_extra


def test_an_aggregated_folder_named_twice_is_loaded_once_and_shown_twice_per_epoch(
    aggregated, smoke_dataset, tmp_path
) -> None:
    root, _ = aggregated
    config = TrainConfig(
        dataset=smoke_dataset,
        out_dir=tmp_path / "weighted",
        max_epochs=1,
        batch_size=32,
        limit_val=32,
        progress=False,
        extra_train=(root, root),
    )
    state = load_checkpoint(train(config).out_dir / "last.ckpt")
    n_base = open_dataset(smoke_dataset).split("train").n_samples
    n_extra = open_dataset(root).split("train").n_samples
    assert state["train_samples"] == n_base + n_extra
    assert state["epoch_samples"] == n_base + 2 * n_extra


def test_init_from_and_resume_exclude_each_other(smoke_dataset, tmp_path) -> None:
    with pytest.raises(ConfigError, match="init_from"):
        TrainConfig(smoke_dataset, tmp_path, resume=True, init_from=tmp_path / "x.pt")
