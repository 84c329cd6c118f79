"""Flocking metrics of the paper: distance extremes, order parameter, collisions, arrival."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from sim_harness.sim.metrics import (
    COLLISION_THRESHOLD_M,
    close_pairs,
    distance_extremes,
    group_centroid_distances,
    order_parameter,
    pair_distances,
)

TOL = 1e-12
PROPERTY = settings(max_examples=50, deadline=None)

# 3-4-5 right triangle in the plane z = 1.
TRIANGLE = np.array([[0.0, 0.0, 1.0], [3.0, 0.0, 1.0], [0.0, 4.0, 1.0]])


# --------------------------------------------------------------------------------------------
# Distances
# --------------------------------------------------------------------------------------------


def test_pair_distances_of_a_3_4_5_triangle() -> None:
    # Pairs in (0,1), (0,2), (1,2) order: 3, 4, 5.
    np.testing.assert_allclose(pair_distances(TRIANGLE), [3.0, 4.0, 5.0], atol=TOL)


def test_distance_extremes_of_a_3_4_5_triangle() -> None:
    d_min, d_max = distance_extremes(TRIANGLE)
    assert float(d_min) == pytest.approx(3.0, abs=TOL)
    assert float(d_max) == pytest.approx(5.0, abs=TOL)


def test_distance_extremes_with_a_time_axis() -> None:
    # Step 0: the triangle; step 1: the triangle scaled by 2; step 2: shifted (same distances).
    shift = np.array([10.0, -5.0, 3.0])
    traj = np.stack([TRIANGLE, 2.0 * TRIANGLE, TRIANGLE + shift])
    assert traj.shape == (3, 3, 3)
    assert pair_distances(traj).shape == (3, 3)
    d_min, d_max = distance_extremes(traj)
    assert d_min.shape == (3,)
    assert d_max.shape == (3,)
    np.testing.assert_allclose(d_min, [3.0, 6.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(d_max, [5.0, 10.0, 5.0], atol=1e-9)


def test_distance_extremes_with_coincident_agents() -> None:
    d_min, d_max = distance_extremes([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [1.0, 1.0, 3.0]])
    assert float(d_min) == 0.0
    assert float(d_max) == pytest.approx(2.0)


@pytest.mark.parametrize("n", [0, 1])
def test_distance_extremes_fewer_than_two_agents_is_nan(n: int) -> None:
    d_min, d_max = distance_extremes(np.zeros((n, 3)))
    assert np.isnan(d_min)
    assert np.isnan(d_max)
    # With a time axis: one NaN per step.
    d_min, d_max = distance_extremes(np.zeros((4, n, 3)))
    assert d_min.shape == (4,)
    assert d_max.shape == (4,)
    assert np.all(np.isnan(d_min))
    assert np.all(np.isnan(d_max))


@PROPERTY
@given(arrays(np.float64, st.tuples(st.integers(2, 8), st.just(3)), elements=st.floats(-50, 50)))
def test_distance_extremes_match_brute_force(positions: np.ndarray) -> None:
    n = positions.shape[0]
    dists = [math.dist(positions[i], positions[j]) for i in range(n) for j in range(n) if i < j]
    d_min, d_max = distance_extremes(positions)
    assert float(d_min) == pytest.approx(min(dists), abs=1e-9)
    assert float(d_max) == pytest.approx(max(dists), abs=1e-9)


# --------------------------------------------------------------------------------------------
# Order parameter
# --------------------------------------------------------------------------------------------


def test_order_parameter_all_aligned_is_one() -> None:
    # Same direction, different speeds.
    v = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [0.5, 0.5, 0.0], [3.0, 3.0, 0.0]])
    assert float(order_parameter(v)) == pytest.approx(1.0, abs=TOL)


def test_order_parameter_two_opposite_is_minus_one() -> None:
    v = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -0.5]])
    assert float(order_parameter(v)) == pytest.approx(-1.0, abs=TOL)


def test_order_parameter_perpendicular_is_zero() -> None:
    v = np.array([[1.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    assert float(order_parameter(v)) == pytest.approx(0.0, abs=TOL)


def test_order_parameter_hovering_agent_contributes_zero() -> None:
    # Two aligned, one hovering: only the ordered pairs (0,1) and (1,0) count, each cos = 1.
    # omega = (2 * 1) / (3 * 2) = 1/3.
    v = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert float(order_parameter(v)) == pytest.approx(1.0 / 3.0, abs=TOL)


def test_order_parameter_all_hovering_is_zero_not_nan() -> None:
    assert float(order_parameter(np.zeros((5, 3)))) == 0.0


def test_order_parameter_min_speed_threshold() -> None:
    # Agent 2 moves at 0.5 m/s: counted by default, ignored with min_speed_mps = 1.
    v = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    # Default: cos = +1 for (0,1),(1,0); -1 for (0,2),(2,0),(1,2),(2,1): (2 - 4) / 6 = -1/3.
    assert float(order_parameter(v)) == pytest.approx(-1.0 / 3.0, abs=TOL)
    # Threshold 1 m/s: agents 0 and 1 at exactly 1 m/s still count (only slower ones are
    # ignored), agent 2 does not: (2 * 1) / 6 = 1/3.
    assert float(order_parameter(v, min_speed_mps=1.0)) == pytest.approx(1.0 / 3.0, abs=TOL)


@pytest.mark.parametrize("n", [0, 1])
def test_order_parameter_fewer_than_two_agents_is_nan(n: int) -> None:
    assert np.isnan(order_parameter(np.ones((n, 3))))
    out = order_parameter(np.ones((3, n, 3)))
    assert out.shape == (3,)
    assert np.all(np.isnan(out))


def test_order_parameter_with_a_time_axis() -> None:
    aligned = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    opposite = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    out = order_parameter(np.stack([aligned, opposite, aligned]))
    assert out.shape == (3,)
    np.testing.assert_allclose(out, [1.0, -1.0, 1.0], atol=TOL)


def brute_force_order(v: np.ndarray, min_speed: float) -> float:
    n = v.shape[0]
    total = 0.0
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            ni, nj = np.linalg.norm(v[i]), np.linalg.norm(v[j])
            if ni < min_speed or nj < min_speed:
                continue
            total += float(v[i] @ v[j]) / (ni * nj)
    return total / (n * (n - 1))


@st.composite
def velocity_sets(draw: st.DrawFn) -> np.ndarray:
    n = draw(st.integers(2, 10))
    v = draw(arrays(np.float64, (n, 3), elements=st.floats(-5.0, 5.0, allow_subnormal=False)))
    # Sometimes some agents hover.
    hovering = draw(arrays(np.bool_, (n,)))
    v[hovering] = 0.0
    return v


@PROPERTY
@given(v=velocity_sets())
def test_order_parameter_matches_brute_force(v: np.ndarray) -> None:
    omega = float(order_parameter(v))
    assert omega == pytest.approx(brute_force_order(v, 1e-3), abs=1e-9)
    assert -1.0 - 1e-9 <= omega <= 1.0 + 1e-9


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1), steps=st.integers(1, 5), n=st.integers(2, 9))
def test_order_parameter_time_axis_matches_per_step(seed: int, steps: int, n: int) -> None:
    v = np.random.default_rng(seed).normal(size=(steps, n, 3))
    out = order_parameter(v)
    assert out.shape == (steps,)
    np.testing.assert_allclose(
        out, [brute_force_order(v[t], 1e-3) for t in range(steps)], atol=1e-9
    )


# --------------------------------------------------------------------------------------------
# Collision pairs
# --------------------------------------------------------------------------------------------


def test_close_pairs_sorted_below_threshold() -> None:
    positions = np.array(
        [
            [0.0, 0.0, 0.0],  # 0
            [10.0, 0.0, 0.0],  # 1
            [0.5, 0.0, 0.0],  # 2: 0.5 m from 0
            [10.0, 0.9, 0.0],  # 3: 0.9 m from 1
            [1.0, 0.0, 0.0],  # 4: exactly 1 m from 0 (not closer), 0.5 m from 2
        ]
    )
    assert COLLISION_THRESHOLD_M == 1.0
    assert close_pairs(positions) == [(0, 2), (1, 3), (2, 4)]
    # A larger threshold catches the pair at exactly 1 m too.
    assert close_pairs(positions, threshold_m=1.01) == [(0, 2), (0, 4), (1, 3), (2, 4)]
    assert close_pairs(positions, threshold_m=0.1) == []


def test_close_pairs_returns_plain_ints() -> None:
    pairs = close_pairs([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert pairs == [(0, 1)]
    assert all(type(i) is int and type(j) is int for i, j in pairs)


def test_close_pairs_single_or_no_agent() -> None:
    assert close_pairs(np.zeros((1, 3))) == []
    assert close_pairs(np.zeros((0, 3))) == []


@PROPERTY
@given(
    positions=arrays(
        np.float64, st.tuples(st.integers(0, 8), st.just(3)), elements=st.floats(-3, 3)
    ),
    threshold=st.floats(0.1, 4.0),
)
def test_close_pairs_match_brute_force(positions: np.ndarray, threshold: float) -> None:
    n = positions.shape[0]
    expected = [
        (i, j)
        for i in range(n)
        for j in range(i + 1, n)
        if np.linalg.norm(positions[j] - positions[i]) < threshold
    ]
    assert close_pairs(positions, threshold) == expected


# --------------------------------------------------------------------------------------------
# Arrival: distance from each goal to its group's centroid
# --------------------------------------------------------------------------------------------


def test_group_centroid_distances_two_groups() -> None:
    positions = np.array(
        [
            [0.0, 0.0, 0.0],  # group 0
            [2.0, 0.0, 0.0],  # group 0 -> centroid (1, 0, 0)
            [10.0, 10.0, 0.0],  # group 1
            [10.0, 12.0, 0.0],  # group 1
            [10.0, 14.0, 0.0],  # group 1 -> centroid (10, 12, 0)
        ]
    )
    groups = np.array([0, 0, 1, 1, 1])
    goals = np.array([[4.0, 4.0, 0.0], [10.0, 12.0, 0.0]])
    # Goal 0: |(4,4,0) - (1,0,0)| = |(3,4,0)| = 5; goal 1: at its group's centroid -> 0.
    np.testing.assert_allclose(group_centroid_distances(positions, groups, goals), [5.0, 0.0])


def test_group_centroid_distances_interleaved_groups_with_time_axis() -> None:
    step = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 2.0, 0.0], [5.0, 0.0, 6.0]])
    groups = np.array([0, 1, 0, 1])  # centroids (0,1,0) and (5,0,3)
    goals = np.array([[0.0, 1.0, 0.0], [5.0, 4.0, 3.0]])
    up = np.array([0.0, 0.0, 1.0])
    traj = np.stack([step, step + up])
    out = group_centroid_distances(traj, groups, goals)
    assert out.shape == (2, 2)
    # Step 0: goal 0 at the centroid (0); goal 1: |(0,4,0)| = 4.
    # Step 1 (everything 1 m up): goal 0: |(0,0,-1)| = 1; goal 1: |(0,4,-1)| = sqrt(17).
    np.testing.assert_allclose(out, [[0.0, 4.0], [1.0, math.sqrt(17.0)]], atol=TOL)


def test_group_centroid_distances_single_common_goal() -> None:
    positions = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]])
    out = group_centroid_distances(positions, [0, 0], [[2.0, 2.0, 2.0]])
    np.testing.assert_allclose(out, [0.0], atol=TOL)
