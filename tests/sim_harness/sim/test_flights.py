"""Position-based flights of the paper, flown end to end in pybullet with the teacher."""

import json
from dataclasses import fields

import numpy as np
import pytest

from companion.flocking import FlockingParams
from sim_harness.errors import ControllerError
from sim_harness.sim.controllers import Observation, TeacherController
from sim_harness.sim.rollout import fly, save_flight, summarize
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def common_flight():
    sc = build_scenario(ScenarioConfig(name="common", n_agents=9, seed=0))
    return fly(sc, TeacherController(sc.config.flocking))


@pytest.fixture(scope="module")
def opposing_flight():
    sc = build_scenario(ScenarioConfig(name="opposing", n_agents=9, seed=0))
    return fly(sc, TeacherController(sc.config.flocking))


def test_common_goal_flock_arrives_without_collision(common_flight) -> None:
    summary = summarize(common_flight)
    assert summary["arrived"] and summary["stop_reason"] == "arrived"
    assert 20.0 < summary["arrival_time_s"] < 60.0  # 30 m at about the 1 m/s migration speed
    assert summary["collision_free"] and summary["d_min_m"] > 1.0
    assert summary["physical_contacts"] == 0
    assert not summary["flock_split"]
    # The log is per control tick and the centroid really ends near the goal.
    centroid = common_flight.pos_world_enu[-1].mean(axis=0)
    assert np.linalg.norm(centroid - common_flight.scenario.goals[0]) <= 2.0
    assert common_flight.d_min_m.min() == pytest.approx(summary["d_min_m"])


def test_common_goal_flock_aligns(common_flight) -> None:
    second_half = common_flight.order[len(common_flight.order) // 2 :]
    assert np.nanmean(second_half) > 0.9


def test_opposing_goals_flock_stays_together(opposing_flight) -> None:
    summary = summarize(opposing_flight)
    assert np.all(opposing_flight.d_max_m < FlockingParams().r_max_m)
    assert not summary["flock_split"]
    assert summary["physical_contacts"] == 0
    # Both groups pull apart, yet the flock moves as one towards the larger group's goal.
    centroid = opposing_flight.pos_world_enu[:, :, 0].mean(axis=1)
    assert centroid[-1] > centroid[0] + 2.0


def test_same_seed_gives_the_identical_summary(common_flight, tmp_path) -> None:
    sc = build_scenario(ScenarioConfig(name="common", n_agents=9, seed=0))
    again = fly(sc, TeacherController(sc.config.flocking))
    assert summarize(again) == summarize(common_flight)
    np.testing.assert_array_equal(again.pos_world_enu, common_flight.pos_world_enu)
    # And what is written to disk reads back.
    paths = save_flight(again, tmp_path)
    assert json.loads(paths["summary"].read_text()) == summarize(common_flight)
    with np.load(paths["steps"]) as steps:
        np.testing.assert_array_equal(steps["pos_world_enu"], common_flight.pos_world_enu)
        assert steps["setpoint_world_enu"].shape == common_flight.pos_world_enu.shape
        assert np.all(np.isnan(steps["setpoint_world_enu"][-1]))
        assert np.isfinite(steps["setpoint_world_enu"][:-1]).all()


def test_self_propelled_flock_runs_to_the_time_limit() -> None:
    sc = build_scenario(ScenarioConfig(name="self-propelled", duration_s=10.0))
    summary = summarize(fly(sc, TeacherController(sc.config.flocking)))
    assert summary["stop_reason"] == "time_limit" and not summary["arrived"]
    assert summary["duration_s"] == pytest.approx(10.0)
    assert summary["collision_free"]


class _Recorder:
    """Wraps the teacher and keeps what it was given."""

    name = "recorder"

    def __init__(self, senses: frozenset[str]) -> None:
        self.senses = senses
        self.inner = TeacherController(FlockingParams())
        self.seen: list[Observation] = []

    def reset(self, n_agents: int) -> None:
        self.seen.clear()

    def command(self, observation: Observation) -> np.ndarray:
        self.seen.append(observation)
        if observation.neighbours is None:
            return np.zeros_like(observation.own.pos_world_enu)
        return self.inner.command(observation)


def test_controller_gets_only_the_senses_it_declares() -> None:
    sc = build_scenario(ScenarioConfig(duration_s=1.0))
    blind = _Recorder(frozenset())
    fly(sc, blind)
    assert len(blind.seen) == 10
    assert all(obs.neighbours is None for obs in blind.seen)
    # What remains is each agent's own state, one row per agent.
    own_fields = {f.name for f in fields(blind.seen[0].own)}
    assert own_fields == {
        "time_s",
        "pos_world_enu",
        "vel_world_enu",
        "q_world_body",
        "migration_point_world_enu",
    }


def test_neighbour_sense_respects_the_perception_radius() -> None:
    cfg = ScenarioConfig(flocking=FlockingParams(r_max_m=2.0), duration_s=0.5)
    recorder = _Recorder(frozenset({"neighbours"}))
    fly(build_scenario(cfg), recorder)
    obs = recorder.seen[0]
    pos = obs.own.pos_world_enu
    dist = np.linalg.norm(pos[None] - pos[:, None], axis=-1)
    expected = (dist < 2.0) & ~np.eye(len(pos), dtype=bool)
    np.testing.assert_array_equal(obs.neighbours.perceived, expected)
    assert np.all(obs.neighbours.offsets_world_enu[~expected] == 0.0)


def test_controller_returning_nan_is_refused() -> None:
    class Broken:
        name = "broken"
        senses = frozenset()

        def reset(self, n_agents: int) -> None:
            pass

        def command(self, observation: Observation) -> np.ndarray:
            return np.full_like(observation.own.pos_world_enu, np.nan)

    with pytest.raises(ControllerError, match="broken"):
        fly(build_scenario(ScenarioConfig(duration_s=1.0)), Broken())


def test_physical_contact_during_a_flight_is_reported() -> None:
    class Rammer:
        """Drives agent 0 straight at agent 1; everyone else hovers."""

        name = "rammer"
        senses = frozenset()

        def reset(self, n_agents: int) -> None:
            pass

        def command(self, observation: Observation) -> np.ndarray:
            pos = observation.own.pos_world_enu
            cmd = np.zeros_like(pos)
            cmd[0] = 2.0 * (pos[1] - pos[0]) / np.linalg.norm(pos[1] - pos[0])
            return cmd

    log = fly(build_scenario(ScenarioConfig(n_agents=3, duration_s=8.0)), Rammer())
    summary = summarize(log)
    assert summary["physical_contacts"] > 0
    assert summary["contact_pairs"] == [[0, 1]]
    assert not summary["collision_free"]
    assert [0, 1] in summary["pairs_below_threshold"]
