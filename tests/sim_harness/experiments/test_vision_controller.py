"""The CNN controller: images in, rotated + migrated + capped velocities out, nothing of others."""

import dataclasses
import json
import math

import numpy as np
import pytest

from companion.errors import ConfigError, ModelError
from sim_harness.dataset.runs import teacher_targets
from sim_harness.experiments.vision_controller import (
    VisionControlConfig,
    VisionController,
    load_policy,
)
from sim_harness.sim.controllers import SENSE_CAMERAS, Observation, OwnState, TeacherController
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.rollout import fly, save_flight
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario
from sim_harness.sim.world import World


class RecordingPolicy:
    """The real policy, with every batch it is handed kept for inspection."""

    def __init__(self, policy) -> None:
        self.policy = policy
        self.batches: list[np.ndarray] = []

    def infer_batch(self, images_u8):
        self.batches.append(np.array(images_u8))
        return self.policy.infer_batch(images_u8)


class SpyController:
    """Wraps a controller and keeps every observation the rollout hands it."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.name = inner.name
        self.senses = inner.senses
        self.observations: list[Observation] = []

    def reset(self, n_agents: int) -> None:
        self.inner.reset(n_agents)

    def command(self, observation: Observation):
        self.observations.append(observation)
        return self.inner.command(observation)

    def stage_time_s(self):
        return self.inner.stage_time_s()


@pytest.fixture(scope="module")
def policy(untrained_policy_path):
    with load_policy(untrained_policy_path) as p:
        yield p


def yaw_quat(yaw_rad: float) -> np.ndarray:
    return np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])


def own_state(pos, q, migration) -> OwnState:
    pos = np.asarray(pos, dtype=float)
    return OwnState(
        0.0, pos, np.zeros_like(pos), np.asarray(q, float), np.asarray(migration, float)
    )


def random_images(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, size=(n, 64, 384), dtype=np.uint8)


def test_command_rotates_the_cnn_output_adds_migration_and_caps(policy) -> None:
    recorder = RecordingPolicy(policy)
    ctrl = VisionController(recorder, VisionControlConfig(k_mig=1.0, v_max_mps=2.0))
    ctrl.reset(3)
    images = random_images(3, 0)
    own = own_state(
        [[0, 0, 5], [1, 2, 5], [3, 0, 6]],
        [yaw_quat(0.0), yaw_quat(math.pi / 2), yaw_quat(math.pi)],
        [[10, 0, 5], [1, 2, 1], [np.nan] * 3],  # east, straight down, none
    )
    cmd = ctrl.command(Observation(own=own, images=images))

    assert len(recorder.batches) == 1  # all agents in one call
    np.testing.assert_array_equal(recorder.batches[0], images)
    v = policy.infer_batch(images)
    assert np.all(np.linalg.norm(v, axis=1) > 0.1)  # the model really outputs something
    np.testing.assert_array_equal(ctrl.last_vel_body_flu, v)
    # Body FLU -> world ENU by hand: yaw 90 deg turns forward (x) into north (y), left into west.
    expected = np.array(
        [
            [v[0, 0] + 1.0, v[0, 1], v[0, 2]],
            [-v[1, 1], v[1, 0], v[1, 2] - 1.0],
            [-v[2, 0], -v[2, 1], v[2, 2]],
        ]
    )
    speed = np.linalg.norm(expected, axis=1, keepdims=True)
    expected = np.where(speed > 2.0, expected / speed * 2.0, expected)
    np.testing.assert_allclose(cmd, expected, atol=1e-9)
    assert np.all(np.linalg.norm(cmd, axis=1) <= 2.0 + 1e-9)


def test_an_agents_command_depends_on_its_own_image_and_state_only(policy) -> None:
    ctrl = VisionController(policy, VisionControlConfig())
    ctrl.reset(4)
    images = random_images(4, 1)
    own = own_state(
        [[0, 0, 5], [2, 0, 5], [0, 2, 5], [2, 2, 5]],
        [yaw_quat(0.3 * k) for k in range(4)],
        [[30, 0, 5]] * 4,
    )
    before = ctrl.command(Observation(own=own, images=images))
    # Everything about agents 1..3 changes: images, positions, velocities, attitudes, goals.
    other_images = images.copy()
    other_images[1:] = random_images(3, 2)
    moved = own_state(
        np.vstack([own.pos_world_enu[:1], [[9, 9, 9], [-5, 3, 2], [0, -7, 4]]]),
        np.vstack([own.q_world_body[:1], [yaw_quat(2.0), yaw_quat(-1.0), yaw_quat(0.1)]]),
        np.vstack([own.migration_point_world_enu[:1], [[np.nan] * 3] * 3]),
    )
    moved = dataclasses.replace(moved, vel_world_enu=np.full((4, 3), 3.0))
    after = ctrl.command(Observation(own=moved, images=other_images))
    np.testing.assert_array_equal(after[0], before[0])
    assert not np.allclose(after[1:], before[1:])


def test_low_pass_filter_is_off_by_default_and_smooths_when_on(policy) -> None:
    images = random_images(2, 3)
    own = own_state([[0, 0, 5], [3, 0, 5]], [yaw_quat(0.0)] * 2, [[np.nan] * 3] * 2)
    obs = Observation(own=own, images=images)
    loose = VisionControlConfig(k_mig=0.0, v_max_mps=20.0)
    raw = VisionController(policy, loose)
    raw.reset(2)
    v = policy.infer_batch(images)
    np.testing.assert_allclose(raw.command(obs), v, atol=1e-12)

    filtered = VisionController(
        policy, dataclasses.replace(loose, low_pass_cutoff_hz=1.0), control_dt_s=0.1
    )
    filtered.reset(2)
    alpha = 0.1 / (0.1 + 1.0 / (2.0 * math.pi))
    first = filtered.command(obs)
    second = filtered.command(obs)
    np.testing.assert_allclose(first, alpha * v, atol=1e-12)
    np.testing.assert_allclose(second, (alpha + alpha * (1 - alpha)) * v, atol=1e-12)
    filtered.reset(2)  # a new run starts from rest
    np.testing.assert_allclose(filtered.command(obs), alpha * v, atol=1e-12)


def test_output_jitter_is_bounded_seeded_and_off_by_default(policy) -> None:
    images = random_images(3, 4)
    own = own_state([[0, 0, 5], [3, 0, 5], [0, 3, 5]], [yaw_quat(0.3)] * 3, [[np.nan] * 3] * 3)
    obs = Observation(own=own, images=images)
    loose = VisionControlConfig(k_mig=0.0, v_max_mps=20.0)
    assert loose.output_jitter_mps == 0.0
    clean = VisionController(policy, loose)
    clean.reset(3)
    clean.command(obs)
    v = clean.last_vel_body_flu

    def jittered(seed):
        config = dataclasses.replace(loose, output_jitter_mps=1e-3, jitter_seed=seed)
        controller = VisionController(policy, config)
        controller.reset(3)
        return [(controller.command(obs), controller.last_vel_body_flu)[1] for _ in range(2)]

    first, again, other = jittered(7), jittered(7), jittered(8)
    for step in first:
        assert 0.0 < np.abs(step - v).max() <= 1e-3
    np.testing.assert_array_equal(first[0], again[0])  # the same seed, the same flight
    assert not np.array_equal(first[0], first[1])  # fresh noise each step
    assert not np.array_equal(first[0], other[0])


def test_a_cnn_flight_sees_only_its_own_images_rendered_at_capture_time(policy, tmp_path) -> None:
    scenario = build_scenario(ScenarioConfig(name="common", n_agents=3, seed=1000, duration_s=1.0))
    config = VisionControlConfig.from_flocking(scenario.config.flocking)
    spy = SpyController(VisionController(policy, config))
    log = fly(scenario, spy)

    assert spy.senses == frozenset({SENSE_CAMERAS})
    assert len(spy.observations) == log.n_steps - 1 == 10
    for obs in spy.observations:
        # What reaches the CNN controller: its own state and its own images, nothing else.
        assert obs.neighbours is None
        assert {f.name for f in dataclasses.fields(obs)} == {"own", "neighbours", "images"}
        assert obs.images is not None
        assert obs.images.dtype == np.uint8 and obs.images.shape == (3, 64, 384)
    # The images are the views at the logged pose of that step (capture time).
    for step in (0, 7):
        with World(3) as world:
            expected = PyBulletRenderer().render(
                world, log.pos_world_enu[step], log.q_world_body[step]
            )
        np.testing.assert_array_equal(spy.observations[step].images, expected)
    assert spy.observations[0].images.std() > 1.0  # a scene, not a blank
    assert np.isfinite(log.setpoint_world_enu[:-1]).all()
    assert np.all(np.linalg.norm(log.setpoint_world_enu[:-1], axis=-1) <= 2.0 + 1e-9)
    # Per-stage timings: rendering, inference and physics were all measured.
    for stage in ("render", "inference", "physics", "control"):
        assert log.stage_time_s[stage] > 0.0, stage
    assert log.stage_time_s["inference"] <= log.stage_time_s["control"]
    timing = json.loads(save_flight(log, tmp_path)["timing"].read_text())
    assert timing["stage_time_s"]["render"] == log.stage_time_s["render"]


class PerfectPolicy:
    """A CNN that predicts its dataset label exactly: the teacher's Reynolds term in body FLU.

    Test-only: it is told the true positions (the label needs them) by `LabelledController`.
    """

    def __init__(self) -> None:
        self.labels: np.ndarray | None = None

    def infer_batch(self, images_u8):
        assert self.labels is not None and len(self.labels) == len(images_u8)
        return self.labels


class LabelledController:
    """Gives the perfect policy the dataset's label for the current state; flies the CNN law."""

    def __init__(self, params) -> None:
        self.perfect = PerfectPolicy()
        self.inner = VisionController(self.perfect, VisionControlConfig.from_flocking(params))
        self.params = params
        self.name = "perfect-cnn"
        self.senses = self.inner.senses

    def reset(self, n_agents: int) -> None:
        self.inner.reset(n_agents)

    def command(self, observation: Observation):
        own = observation.own
        self.perfect.labels = teacher_targets(own.pos_world_enu, own.q_world_body, self.params)[
            "rey_body"
        ]
        return self.inner.command(observation)


def test_a_cnn_that_predicts_its_labels_flies_the_teachers_flight() -> None:
    # Dataset labels are R_world_body^T v_rey; the controller applies R_world_body at the same
    # attitude and adds the migration term: frames and conventions line up end to end.
    scenario = build_scenario(
        ScenarioConfig(name="opposing", n_agents=4, seed=1002, duration_s=2.0)
    )
    teacher = fly(scenario, TeacherController(scenario.config.flocking))
    perfect = fly(scenario, LabelledController(scenario.config.flocking))
    np.testing.assert_allclose(perfect.setpoint_world_enu, teacher.setpoint_world_enu, atol=1e-9)
    np.testing.assert_allclose(perfect.pos_world_enu, teacher.pos_world_enu, atol=1e-9)
    assert np.ptp(teacher.q_world_body[:, :, 3]) > 0.05  # the drones really turned


def test_same_seed_same_cnn_flight(policy) -> None:
    scenario = build_scenario(
        ScenarioConfig(name="opposing", n_agents=3, seed=1001, duration_s=0.5)
    )
    config = VisionControlConfig.from_flocking(scenario.config.flocking)
    a = fly(scenario, VisionController(policy, config))
    b = fly(scenario, VisionController(policy, config))
    np.testing.assert_array_equal(a.pos_world_enu, b.pos_world_enu)


def test_the_teacher_is_not_rendered_for(policy) -> None:
    scenario = build_scenario(ScenarioConfig(name="common", n_agents=3, seed=1000, duration_s=0.5))
    spy = SpyController(TeacherController(scenario.config.flocking))
    spy.stage_time_s = lambda: {}
    log = fly(scenario, spy)
    assert all(obs.images is None and obs.neighbours is not None for obs in spy.observations)
    assert log.stage_time_s["render"] == 0.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"low_pass_cutoff_hz": 0.0}, "vision.low_pass_cutoff_hz"),
        ({"k_mig": -1.0}, "vision.k_mig"),
        ({"v_max_mps": 0.0}, "vision.v_max_mps"),
        ({"output_jitter_mps": -1e-6}, "vision.output_jitter_mps"),
    ],
)
def test_bad_control_config_names_the_field(kwargs, field) -> None:
    with pytest.raises(ConfigError, match=field):
        VisionControlConfig(**kwargs)


def test_missing_or_altered_model_is_refused(untrained_policy_path, tmp_path) -> None:
    with pytest.raises(ModelError, match="cannot read model file"):
        load_policy(tmp_path / "nope.pt")
    altered = tmp_path / "altered.pt"
    altered.write_bytes(untrained_policy_path.read_bytes() + b"\0")
    altered.with_suffix(".json").write_text(untrained_policy_path.with_suffix(".json").read_text())
    with pytest.raises(ModelError, match="SHA-256"):
        load_policy(altered)


def test_controller_without_images_fails_clearly(policy) -> None:
    ctrl = VisionController(policy, VisionControlConfig())
    ctrl.reset(1)
    own = own_state([[0, 0, 5]], [yaw_quat(0.0)], [[np.nan] * 3])
    with pytest.raises(Exception, match="cameras"):
        ctrl.command(Observation(own=own))
