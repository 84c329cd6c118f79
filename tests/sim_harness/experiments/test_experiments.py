"""The experiment suites: what they fly, same seeds for teacher and CNN, in-process or in a pool."""

import json

import numpy as np
import pytest

from companion.errors import ConfigError, ModelError
from sim_harness.experiments.runner import run_dir, run_suite, save_runs
from sim_harness.experiments.suites import EVAL_SEED_BASE, EXPERIMENTS, SUITES, SuiteConfig
from sim_harness.sim.scenarios import build_scenario


def test_suites_fly_the_papers_experiments_on_evaluation_seeds() -> None:
    paper = SuiteConfig(suite="paper")
    assert [e.key for e in paper.experiment_list] == ["common", "opposing"]
    assert paper.seeds == tuple(range(1000, 1005))  # default 5 seeds
    bar = SuiteConfig(suite="bar")
    assert len(bar.seeds) == 20 and min(bar.seeds) >= EVAL_SEED_BASE
    assert {e.key for e in bar.experiment_list} == set(EXPERIMENTS)  # the bar flies all six
    gen = {
        (e.scenario, e.n_agents, e.v_max_mps) for e in SuiteConfig("generalization").experiment_list
    }
    assert {("common", 3, 2.0), ("common", 12, 2.0), ("common", 9, 2.0), ("common", 9, 4.0)} <= gen
    assert ("self-propelled", 9, 2.0) in gen
    # Opposing goals: 5 agents to one point, 4 to the opposite one.
    opposing = build_scenario(EXPERIMENTS["opposing"].scenario_config(1000))
    assert np.bincount(opposing.groups).tolist() == [5, 4]
    assert np.allclose(opposing.goals[0] - opposing.goals[1], [60.0, 0.0, 0.0])
    vmax4 = EXPERIMENTS["vmax4"].scenario_config(1000)
    assert vmax4.flocking.v_max_mps == 4.0 and vmax4.n_agents == 9
    assert vmax4.flocking.k_mig == 2.0  # the flock flies faster, not only its cap
    assert set(SUITES) == {"paper", "generalization", "bar"}


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"suite": "everything"}, "experiments.suite"),
        ({"seed_base": 0}, "experiments.seed_base"),  # training-range seeds are refused
        ({"n_seeds": 0}, "experiments.seeds"),
        ({"workers": 0}, "experiments.workers"),
        ({"low_pass_cutoff_hz": -1.0}, "experiments.low_pass_cutoff_hz"),
        ({"experiments": ("n7",)}, "experiments.experiments"),
        ({"ground_seed": -1}, "experiments.ground"),
    ],
)
def test_bad_suite_config_names_the_field(kwargs, field) -> None:
    with pytest.raises(ConfigError, match=field):
        SuiteConfig(**kwargs)


@pytest.fixture(scope="module")
def small_suite(untrained_policy_path):
    config = SuiteConfig(
        suite="paper",
        model_path=untrained_policy_path,
        n_seeds=2,
        seed_base=1010,
        duration_s=0.4,
    )
    seen = []
    result = run_suite(config, on_run=lambda rec, done, total: seen.append((done, total)))
    return result, seen


def test_teacher_and_cnn_fly_the_same_seeds(small_suite) -> None:
    result, seen = small_suite
    keys = [(r.experiment, r.controller, r.seed) for r in result.runs]
    assert keys == [
        (e, c, s) for e in ("common", "opposing") for c in ("teacher", "cnn") for s in (1010, 1011)
    ]
    assert seen == [(k, 8) for k in range(1, 9)]
    for e in ("common", "opposing"):
        for t, c in zip(result.logs(e, "teacher"), result.logs(e, "cnn"), strict=True):
            assert t.scenario.config == c.scenario.config
            np.testing.assert_array_equal(t.pos_world_enu[0], c.pos_world_enu[0])
            # Same start, different controllers: the flights differ afterwards.
            assert not np.array_equal(t.pos_world_enu[-1], c.pos_world_enu[-1])
    for r in result.runs:
        assert r.log.n_steps == 5  # 0.4 s at 10 Hz, plus the final state
        rendered = r.log.stage_time_s["render"] > 0
        assert rendered == (r.controller == "cnn")
    assert len(result.model_sha256) == 64
    assert result.model_metadata["output"]["frame"] == "body_flu"


def test_runs_are_saved_per_experiment_controller_and_seed(small_suite, tmp_path) -> None:
    result, _ = small_suite
    save_runs(result, tmp_path)
    for r in result.runs:
        folder = run_dir(tmp_path, r)
        assert folder == tmp_path / "runs" / r.experiment / r.controller / f"seed-{r.seed}"
        assert json.loads((folder / "summary.json").read_text()) == r.summary
        assert (folder / "steps.npz").stat().st_size > 0


def test_a_pool_of_workers_gives_the_same_flights(untrained_policy_path, small_suite) -> None:
    result, _ = small_suite
    config = SuiteConfig(
        suite="paper",
        model_path=untrained_policy_path,
        n_seeds=1,
        seed_base=1010,
        duration_s=0.4,
        workers=2,
        experiments=("common",),
    )
    pooled = run_suite(config)
    assert [(r.controller, r.seed) for r in pooled.runs] == [("teacher", 1010), ("cnn", 1010)]
    for r in pooled.runs:
        (same,) = [s for s in result.records("common", r.controller) if s.seed == r.seed]
        np.testing.assert_array_equal(r.log.pos_world_enu, same.log.pos_world_enu)


def test_the_shipped_low_pass_is_the_default_and_a_cutoff_turns_it_on() -> None:
    import argparse

    from sim_harness.experiments.cli import add_experiment_commands
    from sim_harness.experiments.suites import SHIPPED_LOW_PASS_HZ

    assert SuiteConfig().low_pass_cutoff_hz == SHIPPED_LOW_PASS_HZ
    assert SHIPPED_LOW_PASS_HZ is None  # chosen on training seeds (models/README.md)
    parser = argparse.ArgumentParser()
    add_experiment_commands(parser.add_subparsers())
    assert parser.parse_args(["demo"]).low_pass is None
    assert parser.parse_args(["experiments", "--low-pass", "2"]).low_pass == 2.0
    assert parser.parse_args(["experiments", "--low-pass", "off"]).low_pass is None
    assert parser.parse_args(["experiments", "--low-pass", "1.5"]).low_pass == 1.5
    with pytest.raises(SystemExit):
        parser.parse_args(["experiments", "--low-pass", "fast"])


def test_a_missing_model_fails_before_any_flight(tmp_path) -> None:
    flown = []
    config = SuiteConfig(model_path=tmp_path / "none.pt", n_seeds=1, duration_s=0.2)
    with pytest.raises(ModelError, match="none.pt"):
        run_suite(config, on_run=lambda *a: flown.append(a))
    assert flown == []


def test_the_faster_flock_flies_faster_than_the_common_goal() -> None:
    """vmax4 must test a faster flock: the teacher cruises near k_mig = 2 m/s, not near 1."""
    import numpy as np

    from sim_harness.sim.controllers import TeacherController
    from sim_harness.sim.rollout import fly
    from sim_harness.sim.scenarios import build_scenario

    speeds = {}
    for key in ("common", "vmax4"):
        config = EXPERIMENTS[key].scenario_config(1000, duration_s=8.0)
        scenario = build_scenario(config)
        log = fly(scenario, TeacherController(config.flocking))
        cruise = log.vel_world_enu[len(log.vel_world_enu) // 2 :]  # after the start transient
        speeds[key] = float(np.linalg.norm(cruise.mean(axis=1), axis=-1).mean())
    assert speeds["common"] < 1.9
    assert speeds["vmax4"] > 1.6 and speeds["vmax4"] > 1.5 * speeds["common"], speeds


def test_an_unseen_ground_changes_what_the_cnn_sees_and_not_the_teacher() -> None:
    from sim_harness.experiments.suites import SHIPPED_MODEL_PATH

    flights = {}
    for ground in (None, 3):
        config = SuiteConfig(
            suite="paper",
            model_path=SHIPPED_MODEL_PATH,
            n_seeds=1,
            seed_base=1010,
            duration_s=0.6,
            experiments=("common",),
            renderer="raycast-aa",
            ground_seed=ground,
        )
        flights[ground] = {r.controller: r.log for r in run_suite(config).runs}
    teacher, other_teacher = flights[None]["teacher"], flights[3]["teacher"]
    np.testing.assert_array_equal(teacher.pos_world_enu, other_teacher.pos_world_enu)
    cnn, other_cnn = flights[None]["cnn"], flights[3]["cnn"]
    np.testing.assert_array_equal(cnn.pos_world_enu[0], other_cnn.pos_world_enu[0])
    seen, unseen = cnn.setpoint_world_enu[:-1], other_cnn.setpoint_world_enu[:-1]  # last row NaN
    assert np.isfinite(seen).all() and np.abs(seen - unseen).max() > 1e-3


def test_the_unseen_ground_is_a_seeded_scene() -> None:
    from sim_harness.sim.scene import SceneSpec, unseen_scene

    assert unseen_scene(None) is None
    assert unseen_scene(4) == unseen_scene(4) != unseen_scene(5)
    assert unseen_scene(4) != SceneSpec()
