"""Flocking metrics of the paper, per time step and per run.

- d_min, d_max: smallest and largest distance over all pairs i < j (NaN with fewer than 2 agents).
- Order parameter: omega = 1/(N(N-1)) * sum_i sum_{j != i} cos(v_i, v_j). An agent slower than
  `min_speed_mps` has no heading: its pairs contribute 0 (so a hovering flock reads 0, not NaN).
  Computed in O(N) from the unit vectors u: sum_{i != j} u_i.u_j = |sum u|^2 - sum |u|^2.
- Collision events: pairs closer than a threshold (the paper's 1 m).
- Arrival: the centroid of each goal's agents within `arrival_radius_m` of that goal.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

COLLISION_THRESHOLD_M = 1.0


def pair_distances(positions: ArrayLike) -> FloatArray:
    """Distances of all pairs i < j: (..., N, 3) -> (..., N(N-1)/2), in np.triu_indices order."""
    p = np.asarray(positions, dtype=np.float64)
    i, j = np.triu_indices(p.shape[-2], k=1)
    return np.asarray(np.linalg.norm(p[..., j, :] - p[..., i, :], axis=-1))


def distance_extremes(positions: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(d_min, d_max) over pairs i < j; shapes (..., N, 3) -> (...), NaN if N < 2."""
    d = pair_distances(positions)
    if d.shape[-1] == 0:
        nan = np.full(d.shape[:-1], np.nan)
        return nan, nan.copy()
    return d.min(axis=-1), d.max(axis=-1)


def order_parameter(velocities: ArrayLike, min_speed_mps: float = 1e-3) -> FloatArray:
    """Paper's order parameter for velocities (..., N, 3) -> (...); NaN if N < 2."""
    v = np.asarray(velocities, dtype=np.float64)
    n = v.shape[-2]
    if n < 2:
        return np.full(v.shape[:-2], np.nan)
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    unit = np.divide(v, speed, out=np.zeros_like(v), where=speed >= min_speed_mps)
    total = unit.sum(axis=-2)
    cross = np.einsum("...k,...k->...", total, total) - np.einsum("...nk,...nk->...", unit, unit)
    return np.asarray(cross / (n * (n - 1)))


def close_pairs(
    positions: ArrayLike, threshold_m: float = COLLISION_THRESHOLD_M
) -> list[tuple[int, int]]:
    """Agent pairs (i < j) closer than `threshold_m` at one instant: positions (N, 3)."""
    p = np.asarray(positions, dtype=np.float64)
    i, j = np.triu_indices(p.shape[0], k=1)
    close = pair_distances(p) < threshold_m
    return [(int(a), int(b)) for a, b in zip(i[close], j[close], strict=True)]


def group_centroid_distances(
    positions: ArrayLike, groups: ArrayLike, goals: ArrayLike
) -> FloatArray:
    """Distance from each goal to the centroid of the agents assigned to it.

    positions (..., N, 3); groups (N,) ints indexing `goals` (G, 3). Returns (..., G).
    """
    p = np.asarray(positions, dtype=np.float64)
    g = np.asarray(groups)
    targets = np.asarray(goals, dtype=np.float64)
    out = np.empty((*p.shape[:-2], targets.shape[0]))
    for k in range(targets.shape[0]):
        centroid = p[..., g == k, :].mean(axis=-2)
        out[..., k] = np.linalg.norm(centroid - targets[k], axis=-1)
    return out


def centroid_progress(positions: ArrayLike, goal: ArrayLike) -> float:
    """How far the whole flock's centroid moved towards `goal` (m) from the first step to the last.

    positions (T, N, 3); the displacement of the centroid projected on the unit vector from its
    first position to `goal` (negative: it moved away). With opposing goals, `goal` is the
    majority's: the teacher's flock drifts towards it at about (n_majority - n_minority) / N times
    the migration speed, while two groups that only pull against each other stay put.
    """
    p = np.asarray(positions, dtype=np.float64)
    start, end = p[0].mean(axis=0), p[-1].mean(axis=0)
    towards = np.asarray(goal, dtype=np.float64) - start
    norm = float(np.linalg.norm(towards))
    return float((end - start) @ towards / norm) if norm > 0.0 else 0.0
