"""The error models of `benchmarks/crossing_sensitivity.py` and the split of
`benchmarks/separation_balance.py`: pure logic, checked against the flocking law itself."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import crossing_sensitivity as cs
import separation_balance as sb

from companion.flocking import FlockingParams, flocking_command, pairwise_offsets
from sim_harness.sim.controllers import NeighbourSensing, Observation, OwnState


def _flock(seed: int = 3, n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-2.0, 2.0, size=(n, 3))
    q = rng.normal(size=(n, 4))
    return pos, q / np.linalg.norm(q, axis=1, keepdims=True)


def _observation(pos: np.ndarray, goal: np.ndarray) -> Observation:
    n = len(pos)
    own = OwnState(0.0, pos, np.zeros_like(pos), np.tile([1.0, 0, 0, 0], (n, 1)), goal)
    sensing = NeighbourSensing(pairwise_offsets(pos), ~np.eye(n, dtype=bool))
    return Observation(own, neighbours=sensing)


def test_an_exact_student_is_the_teacher_and_a_weak_one_holds_closer() -> None:
    params = FlockingParams(v_max_mps=50.0)  # no cap: the parts stay visible
    pos, _ = _flock()
    pos[1] = pos[0] + [0.7, 0.0, 0.0]  # one pair inside the near radius
    goal = np.tile([30.0, 0.0, 5.0], (len(pos), 1))
    teacher = flocking_command(pos, goal, params).final
    obs = _observation(pos, goal)
    for kind in ("near", "far", "rey", "sep"):
        exact = cs.StudentController(params, {kind: 1.0}, seed=0).command(obs)
        np.testing.assert_allclose(exact, teacher, atol=1e-12)
    # `sepS` is the law with the separation gain k_sep x S
    cautious = cs.StudentController(params, {"sep": 1.3}, seed=0).command(obs)
    stronger = FlockingParams(v_max_mps=50.0, k_sep=params.k_sep * 1.3)
    np.testing.assert_allclose(cautious, flocking_command(pos, goal, stronger).final, atol=1e-12)
    weak = cs.StudentController(params, {"near": 0.5}, seed=0).command(obs)
    away = (pos[0] - pos[1]) / np.linalg.norm(pos[0] - pos[1])
    # agent 0 flees agent 1 less when the near pair weighs half
    assert weak[0] @ away < teacher[0] @ away - 0.1
    noisy = cs.StudentController(params, {"noise": 0.2}, seed=4)
    first = noisy.command(obs)
    noisy.reset(len(pos))
    np.testing.assert_array_equal(noisy.command(obs), first)  # seeded: a run is repeatable
    assert not np.allclose(first, teacher)


def test_variant_names_are_checked() -> None:
    assert cs.parse_variant("far0.9") == {"far": 0.9}
    assert cs.parse_variant("sep1.15+near2") == {"sep": 1.15, "near": 2.0}
    with pytest.raises(ValueError, match="unknown variant 'fast1.1'"):
        cs.parse_variant("fast1.1")
    with pytest.raises(ValueError, match="unknown variant 'near'"):
        cs.parse_variant("near")
    with pytest.raises(ValueError, match="each kind once"):
        cs.parse_variant("near2+near3")


def test_a_joined_student_flies_the_law_training_teaches() -> None:
    """`sep1.15+near2` answers what `swarm-sim train --separation-scale 1.15
    --near-separation-scale 2` labels, agent by agent (identity attitude: body = world)."""
    from sim_harness.learning.relabel import cautious_targets

    params = FlockingParams(v_max_mps=50.0)
    pos, _ = _flock(seed=11, n=7)
    pos[3] = pos[5] + [0.5, 0.4, -0.2]  # a near pair
    pos[6] = pos[5] + [-0.6, 0.3, 0.1]  # and a third drone near one of them
    goal = np.tile([30.0, 0.0, 5.0], (len(pos), 1))
    n = len(pos)
    meta = {
        "run": np.zeros(n, dtype=np.int64),
        "time_s": np.zeros(n),
        "agent": np.arange(n),
        "pos_world_enu": pos,
        "q_world_body": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
    }
    stored = flocking_command(pos, None, params).reynolds
    migration = flocking_command(pos, goal, params).migration
    taught = {}
    for radius in (1.2, 2.0):  # the default reach, and `--near-separation-radius 2`
        taught[radius] = cautious_targets(stored, meta, 1.15, params, near_scale=2.0, near_m=radius)
        variant = cs.parse_variant("sep1.15+near2")
        student = cs.StudentController(params, variant, seed=0, near_m=radius)
        np.testing.assert_allclose(
            student.command(_observation(pos, goal)) - migration, taught[radius], atol=1e-5
        )
    assert np.abs(taught[1.2] - stored).max() > 0.1  # the near drones' labels did change
    assert np.abs(taught[2.0] - taught[1.2]).max() > 0.05  # and the reach matters
    # `--near-ramp-m 0.5`: the law `--near-separation-ramp 0.5` teaches
    ramped = cautious_targets(stored, meta, 1.15, params, near_scale=2.0, near_m=1.2, ramp_m=0.5)
    student = cs.StudentController(params, cs.parse_variant("sep1.15+near2"), 0, 1.2, 0.5)
    np.testing.assert_allclose(
        student.command(_observation(pos, goal)) - migration, ramped, atol=1e-5
    )
    assert np.abs(ramped - taught[1.2]).max() > 0.05  # the ramp weighs the pairs less
    # `--scale-reach-m 1.5`: the law `--separation-radius 1.5` teaches
    reached = cautious_targets(stored, meta, 1.15, params, near_scale=2.0, near_m=1.2, reach_m=1.5)
    student = cs.StudentController(params, cs.parse_variant("sep1.15+near2"), 0, 1.2, 0.0, 1.5)
    np.testing.assert_allclose(
        student.command(_observation(pos, goal)) - migration, reached, atol=1e-5
    )
    assert np.abs(reached - taught[1.2]).max() > 0.05  # the far neighbours are the paper's


def test_the_three_parts_sum_to_the_teachers_body_frame_command() -> None:
    from companion.frames import quat_to_rotmat

    params = FlockingParams()
    pos, q = _flock(seed=7, n=5)
    pos[2] = pos[4] + [0.0, 0.8, 0.3]  # a pair within the near radius, so each part is present
    meta = {
        "agent": np.arange(5),
        "pos_world_enu": pos,
        "q_world_body": q,
    }
    parts = sb.decompose(meta, np.arange(5), params, near_m=1.2)
    rey = flocking_command(pos, None, params).reynolds
    body = np.einsum("nji,nj->ni", quat_to_rotmat(q), rey)  # R^T v per agent
    np.testing.assert_allclose(parts.sum(axis=1), body, atol=1e-12)
    gains = sb.fit(parts.sum(axis=1) * 0.8, parts)
    assert np.abs(parts[:, 0]).max() > 0.5  # the near pair's separation is in the fit
    assert gains["gain_sep_near"] == pytest.approx(0.8)
    assert gains["gain_sep_far"] == pytest.approx(0.8)
    assert gains["gain_coh"] == pytest.approx(0.8)
