"""`benchmarks/boost_answer.py`: the law it scores flights against is the one the students are
trained on, and its tables put each value in the right bin. Pure logic."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import boost_answer as ba

from companion.flocking import FlockingParams, flocking_command
from companion.frames import quat_to_rotmat
from sim_harness.learning.relabel import cautious_targets


def _flock(n: int = 9, seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-2.5, 2.5, size=(n, 3))
    pos[1] = pos[0] + [1.25, 0.1, 0.0]  # inside the 1.35 m boost
    q = rng.normal(size=(n, 4))
    return pos, q / np.linalg.norm(q, axis=1, keepdims=True)


def test_the_flights_law_is_the_training_labels_law() -> None:
    pos, q = _flock()
    params = FlockingParams()
    rot = quat_to_rotmat(q)
    stored = np.einsum("nji,nj->ni", rot, flocking_command(pos, None, params).reynolds)
    meta = {
        "pos_world_enu": pos.astype(np.float32),
        "q_world_body": q.astype(np.float32),
        "run": np.zeros(len(pos), dtype=np.int64),
        "time_s": np.zeros(len(pos), dtype=np.float32),
    }
    labels = cautious_targets(stored.astype(np.float32), meta, 1.15, near_scale=2.0, near_m=1.35)
    world = ba.taught_law_world(pos, params, 1.15, 2.0, 1.35)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rot, labels), world, atol=1e-4)
    # unscaled and unboosted, it is the paper's separation + cohesion
    plain = ba.taught_law_world(pos, params, 1.0, 1.0, 1.35)
    np.testing.assert_allclose(plain, flocking_command(pos, None, params).reynolds, atol=1e-12)
    # the pair inside the boost flees harder than the paper's law has it
    away = (pos[0] - pos[1]) / np.linalg.norm(pos[0] - pos[1])
    assert (world[0] - world[1]) @ away > (plain[0] - plain[1]) @ away + 1.0
    # `--separation-radius 2`: the labels of `swarm-sim train --separation-radius 2`
    near_only = cautious_targets(
        stored.astype(np.float32), meta, 1.15, near_scale=2.0, near_m=1.35, reach_m=2.0
    )
    reached = ba.taught_law_world(pos, params, 1.15, 2.0, 1.35, 2.0)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", rot, near_only), reached, atol=1e-4)
    assert np.abs(reached - world).max() > 0.01


def test_away_from_the_nearest_neighbour_in_the_body_frame() -> None:
    pos, q = _flock()
    meta = {"agent": np.arange(len(pos)), "pos_world_enu": pos, "q_world_body": q}
    away = ba.away_from_nearest_body(meta, np.array([0, 1]))
    rot = quat_to_rotmat(q)
    expected_0 = (pos[0] - pos[1]) / np.linalg.norm(pos[0] - pos[1])
    np.testing.assert_allclose(rot[0] @ away[0], expected_0, atol=1e-12)
    np.testing.assert_allclose(rot[1] @ away[1], -expected_0, atol=1e-12)


def test_the_tables_bin_by_distance_and_divide_policy_by_law() -> None:
    distance = np.array([1.05, 1.07, 1.32, 1.9])
    rows = ba.binned(
        distance, {"policy": np.array([1.0, 2.0, 0.5, 9.0]), "law": np.array([2.0, 2.0, 2.0, 9.0])}
    )
    assert [r["distance_m"] for r in rows] == [[1.0, 1.1], [1.3, 1.35]]  # 1.9 m: outside
    assert rows[0]["count"] == 2 and rows[0]["policy"] == 1.5 and rows[0]["ratio"] == 0.75
    assert rows[1]["ratio"] == 0.25
