"""Top views frame the flock, explain their marks, and point at goals outside the view."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pytest

from sim_harness.sim.controllers import TeacherController
from sim_harness.sim.plots import draw_trajectories
from sim_harness.sim.rollout import fly
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

MARKS = ["first step", "middle step", "last step", "spawn area", "migration point"]


def top_view(config: ScenarioConfig):
    scenario = build_scenario(config)
    log = fly(scenario, TeacherController(scenario.config.flocking))
    fig, ax = plt.subplots()
    draw_trajectories(ax, log)
    return fig, ax, log


@pytest.fixture(scope="module")
def opposing():
    fig, ax, log = top_view(ScenarioConfig(name="opposing", n_agents=9, seed=0, duration_s=2.0))
    yield ax, log
    plt.close(fig)


def test_the_view_frames_the_flock_not_the_goals_30_m_away(opposing) -> None:
    ax, log = opposing
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    east, north = log.pos_world_enu[..., 0], log.pos_world_enu[..., 1]
    assert x0 < east.min() and east.max() < x1 and y0 < north.min() and north.max() < y1
    assert x1 - x0 < 15.0 and y1 - y0 < 15.0  # the goals at +-30 m would need 60 m


def test_goals_outside_the_view_are_arrows_at_its_edge(opposing) -> None:
    ax, _ = opposing
    labels = sorted(t.get_text() for t in ax.texts)
    assert labels == ["goal (+30, +0) m", "goal (-30, +0) m"]
    x0, x1 = ax.get_xlim()
    for text in ax.texts:
        tip_x = text.xy[0]
        assert x0 < tip_x < x1 and min(tip_x - x0, x1 - tip_x) < 0.1 * (x1 - x0)


def test_the_legend_explains_every_mark(opposing) -> None:
    ax, _ = opposing
    shown = [t.get_text() for t in ax.get_legend().get_texts()]
    assert shown == [*MARKS, "second group (other goal)"]


def test_a_goal_inside_the_view_is_drawn_as_a_disc() -> None:
    config = ScenarioConfig(name="common", n_agents=3, seed=0, goal_distance_m=3.0)
    fig, ax, log = top_view(config)
    assert log.stop_reason == "arrived"
    assert not any(t.get_text().startswith("goal") for t in ax.texts)
    assert [t.get_text() for t in ax.get_legend().get_texts()] == MARKS
    plt.close(fig)
