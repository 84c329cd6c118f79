"""The paper's flocking law: separation + cohesion (the Reynolds command), migration, speed cap.

For agent i with neighbours N_i = {j != i : |r_ij| < r_max}, r_ij = p_j - p_i:

    v_sep = -(k_sep / |N_i|) * sum_j r_ij / |r_ij|^2
    v_coh =  (k_coh / |N_i|) * sum_j r_ij
    v_rey = v_sep + v_coh                       (what the CNN learns)
    v_mig = k_mig * r_mig / |r_mig|,  r_mig = p_mig - p_i   (optional)
    v     = v~ / |v~| * min(|v~|, v_max),  v~ = v_rey + v_mig

Degenerate cases, chosen so that every output is finite:
- no neighbours: v_sep = v_coh = 0;
- a coincident neighbour (|r_ij| < `COINCIDENT_M`) has no direction to flee: it counts in |N_i| but
  adds nothing to the separation sum (it adds nothing to the cohesion sum either, r_ij = 0);
- an agent at its migration point, or without one (NaN row), gets v_mig = 0;
- a zero command stays zero under the speed cap.

Everything is vectorized over agents; all vectors are in one world frame (the law is
frame-agnostic: it commutes with rotations and is invariant under translations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.validation import require_non_negative, require_positive

FloatArray = NDArray[np.float64]

#: Two agents closer than this are treated as coincident (no separation direction).
COINCIDENT_M = 1e-9


@dataclass(frozen=True)
class FlockingParams:
    """Flocking gains and limits; the defaults are the paper's Table I."""

    r_max_m: float = 20.0  # perception radius: neighbours are strictly closer than this
    v_max_mps: float = 2.0  # speed cap of the final command
    k_sep: float = 7.0  # separation gain (m^2/s, so that k_sep / distance is a speed)
    k_coh: float = 1.0  # cohesion gain (1/s)
    k_mig: float = 1.0  # migration gain (m/s: the migration term's speed)

    def __post_init__(self) -> None:
        require_positive("flocking.r_max_m", self.r_max_m)
        require_positive("flocking.v_max_mps", self.v_max_mps)
        require_non_negative("flocking.k_sep", self.k_sep)
        require_non_negative("flocking.k_coh", self.k_coh)
        require_non_negative("flocking.k_mig", self.k_mig)


@dataclass(frozen=True)
class FlockingCommand:
    """All parts of the flocking command, each (N, 3) in the input's world frame."""

    separation: FloatArray
    cohesion: FloatArray
    reynolds: FloatArray
    migration: FloatArray
    final: FloatArray
    n_neighbours: NDArray[np.int64]  # (N,)


def pairwise_offsets(positions: ArrayLike) -> FloatArray:
    """r_ij = p_j - p_i for all pairs: (N, 3) -> (N, N, 3)."""
    p = np.asarray(positions, dtype=np.float64)
    return p[None, :, :] - p[:, None, :]


def reynolds_from_offsets(
    offsets: ArrayLike, valid: ArrayLike, params: FlockingParams
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Separation and cohesion of each agent from the offsets to the others it perceives.

    Args:
        offsets: (N, M, 3) offsets r_ij from agent i to candidate j, world frame, metres.
        valid: (N, M) bool, False for padding and for i itself; invalid slots may hold anything
            (NaN included) and are ignored.
        params: gains; `r_max_m` selects neighbours among the valid candidates.

    Returns:
        (separation (N, 3), cohesion (N, 3), number of neighbours (N,)).
    """
    valid_mask = np.asarray(valid, dtype=bool)
    # Invalid slots are ignored whatever they hold (NaN padding included).
    r = np.where(valid_mask[..., None], np.asarray(offsets, dtype=np.float64), 0.0)
    d2 = np.einsum("nmk,nmk->nm", r, r)
    neighbour = valid_mask & (d2 < params.r_max_m**2)
    count = neighbour.sum(axis=1)
    # 1/|r|^2 on non-coincident neighbours, 0 elsewhere (never divides by zero).
    far_enough = neighbour & (d2 >= COINCIDENT_M**2)
    inv_d2 = np.divide(1.0, d2, out=np.zeros_like(d2), where=far_enough)
    weights = np.where(neighbour, 1.0, 0.0)
    sum_unit_over_d = np.einsum("nm,nmk->nk", inv_d2, r)
    sum_offsets = np.einsum("nm,nmk->nk", weights, r)
    scale = np.divide(1.0, count, out=np.zeros(count.shape), where=count > 0)[:, None]
    separation = -params.k_sep * scale * sum_unit_over_d
    cohesion = params.k_coh * scale * sum_offsets
    return separation, cohesion, count.astype(np.int64)


def migration_velocity(
    positions: ArrayLike, migration_points: ArrayLike | None, k_mig: float
) -> FloatArray:
    """k_mig * unit(p_mig - p_i) per agent; zero without a point (None or NaN row) or at it.

    Shapes: positions (N, 3); migration_points (N, 3) or (3,) for a common point, or None.
    """
    p = np.asarray(positions, dtype=np.float64)
    if migration_points is None:
        return np.zeros_like(p)
    target = np.broadcast_to(np.asarray(migration_points, dtype=np.float64), p.shape)
    has_target = np.all(np.isfinite(target), axis=-1)
    r_mig = np.where(has_target[:, None], target - p, 0.0)
    dist = np.linalg.norm(r_mig, axis=-1, keepdims=True)
    unit = np.divide(r_mig, dist, out=np.zeros_like(r_mig), where=dist > COINCIDENT_M)
    return np.asarray(k_mig * unit, dtype=np.float64)


def cap_speed(velocity: ArrayLike, v_max_mps: float) -> FloatArray:
    """v / |v| * min(|v|, v_max) for each row of (..., 3); zero stays zero."""
    v = np.asarray(velocity, dtype=np.float64)
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    scale = np.divide(v_max_mps, speed, out=np.ones_like(speed), where=speed > v_max_mps)
    return np.asarray(v * scale, dtype=np.float64)


def command_from_offsets(
    offsets: ArrayLike,
    valid: ArrayLike,
    positions: ArrayLike,
    migration_points: ArrayLike | None,
    params: FlockingParams,
) -> FlockingCommand:
    """Full command from what each agent perceives: offsets to others and its own position.

    Shapes: offsets (N, M, 3), valid (N, M), positions (N, 3) (used only for the migration term),
    migration_points as in `migration_velocity`.
    """
    separation, cohesion, count = reynolds_from_offsets(offsets, valid, params)
    reynolds = separation + cohesion
    migration = migration_velocity(positions, migration_points, params.k_mig)
    final = cap_speed(reynolds + migration, params.v_max_mps)
    return FlockingCommand(separation, cohesion, reynolds, migration, final, count)


def flocking_command(
    positions: ArrayLike,
    migration_points: ArrayLike | None,
    params: FlockingParams,
) -> FlockingCommand:
    """The full command of every agent from all positions (N, 3), world frame, metres.

    `migration_points` is (N, 3) (NaN rows: no point for that agent), (3,) for a common point,
    or None for a self-propelled flock.
    """
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must have shape (N, 3), got {p.shape}")
    valid = ~np.eye(p.shape[0], dtype=bool)
    return command_from_offsets(pairwise_offsets(p), valid, p, migration_points, params)
