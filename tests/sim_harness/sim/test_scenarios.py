"""Scenarios: the paper's spawn, goals and groups; seeded; bad input names the field."""

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.flocking import FlockingParams
from sim_harness.sim.metrics import pair_distances
from sim_harness.sim.scenarios import SPAWN_CENTER, ScenarioConfig, build_scenario


@pytest.mark.parametrize("n", [3, 9, 12, 30])
def test_spawn_in_the_cube_pairwise_apart(n: int) -> None:
    sc = build_scenario(ScenarioConfig(n_agents=n, seed=3))
    half = sc.config.spawn_side / 2
    assert np.all(np.abs(sc.initial_pos_world_enu - SPAWN_CENTER) <= half)
    assert pair_distances(sc.initial_pos_world_enu).min() >= 1.5
    assert sc.config.spawn_side == pytest.approx(4.0 if n <= 9 else 4.0 * (n / 9) ** (1 / 3))


def test_same_seed_same_scenario_other_seed_other_spawn() -> None:
    a = build_scenario(ScenarioConfig(seed=5))
    b = build_scenario(ScenarioConfig(seed=5))
    c = build_scenario(ScenarioConfig(seed=6))
    np.testing.assert_array_equal(a.initial_pos_world_enu, b.initial_pos_world_enu)
    assert not np.allclose(a.initial_pos_world_enu, c.initial_pos_world_enu)


def test_common_goal_for_everyone() -> None:
    sc = build_scenario(ScenarioConfig(name="common", goal_distance_m=25.0))
    np.testing.assert_allclose(sc.migration_points, np.tile([25.0, 0.0, 5.0], (9, 1)))


@pytest.mark.parametrize(("n", "first"), [(9, 5), (3, 2), (12, 7)])
def test_opposing_goals_split_five_to_four(n: int, first: int) -> None:
    sc = build_scenario(ScenarioConfig(name="opposing", n_agents=n))
    assert (sc.groups == 0).sum() == first and (sc.groups == 1).sum() == n - first
    np.testing.assert_allclose(sc.goals[0] - SPAWN_CENTER, -(sc.goals[1] - SPAWN_CENTER))
    np.testing.assert_allclose(
        sc.migration_points[sc.groups == 1], np.tile(sc.goals[1], (n - first, 1))
    )
    assert list(sc.arrival_goals) == [0]  # the majority's goal


def test_self_propelled_has_no_migration_point() -> None:
    sc = build_scenario(ScenarioConfig(name="self-propelled"))
    assert np.all(np.isnan(sc.migration_points)) and not sc.has_goal


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"n_agents": 0}, "scenario.n_agents"),
        ({"name": "circle"}, "scenario"),
        ({"seed": -1}, "scenario.seed"),
        ({"goal_distance_m": -5.0}, "scenario.goal_distance_m"),
        ({"duration_s": 0.0}, "scenario.duration_s"),
        ({"arrival_radius_m": float("nan")}, "scenario.arrival_radius_m"),
    ],
)
def test_bad_config_names_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        ScenarioConfig(**kwargs)


def test_bad_flocking_gain_names_the_field() -> None:
    with pytest.raises(ConfigError, match="flocking.k_coh"):
        ScenarioConfig(flocking=FlockingParams(k_coh=-1.0))


def test_impossible_spawn_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="spawn_side_m"):
        build_scenario(ScenarioConfig(n_agents=20, spawn_side_m=2.0))
