"""The labels of a more cautious teacher, recomputed from the stored positions of each flock.

Every dataset stores, for every sample, the teacher's Reynolds command in the body frame (the
label) and the drone's world position and attitude at the moment its image was taken; the samples
of one run at one time step are the whole flock. From those positions the separation term can be
computed again, so a training run can learn the flocking law with its separation gain scaled by
S (k_sep x S), and with the neighbours closer than R (default `NEAR_M`) weighing C in the
separation sum (a close-range boost), without drawing one image again:

    label' = label + (S - 1) * R_body_world * separation(positions)
                   + S * (C - 1) * R_body_world * separation_near(positions)

where separation_near is the separation term's share from the neighbours within R (still
averaged over all neighbours, as the law averages).

Why a student would learn a law other than the one it is judged against: the CNN's errors act on
the flock like noise on the command, and the closest pair of a crossing is what such noise costs
(`benchmarks/crossing_sensitivity.py`: a student whose separation runs a few percent weak holds
a pair 0.1 m closer). A student taught a slightly stronger separation keeps that margin on its
side. The close-range boost answers where the paper's law itself comes under 1 m: where nine or
twelve drones reach one migration point, every drone's migration term aims at that point and the
law's separation, averaged over all neighbours, pushes back too weakly
(`benchmarks/crossing_sensitivity.py --experiment n12 --variants near2`). At flight time nothing
changes: each drone's command still comes from its own image
through the CNN, plus its own migration term and the speed cap.

Before relabelling, the stored labels are recomputed from the positions with the unscaled law and
compared: a dataset whose flocks are incomplete, or labelled with other gains, is refused with its
worst mismatch named, rather than trained on silently wrong labels.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.flocking import FlockingParams, reynolds_from_offsets
from companion.frames import quat_to_rotmat
from sim_harness.learning.batches import JoinedSplit, SplitArrays, StackedImages
from sim_harness.learning.flock_loss import flock_ids

POSITION_COLUMNS = ("pos_world_enu", "q_world_body")
NEAR_M = 1.2  # by default the close-range boost weighs the neighbours closer than this
# the stored label is float32, the positions too: the law recomputed from them agrees to ~1e-5
LABEL_TOLERANCE_MPS = 2e-3


def flock_separation_body(
    meta: Mapping[str, NDArray[Any]], params: FlockingParams, near_m: float = NEAR_M
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(separation, its share from the neighbours within `near_m`, separation + cohesion) of
    every sample, body FLU m/s, from the positions of its flock (the rows of one run at one time
    step, as `flock_ids` groups them)."""
    missing = [c for c in POSITION_COLUMNS if c not in meta]
    if missing:
        raise ConfigError(
            f"separation_scale: the training data lacks the per-sample column(s) "
            f"{', '.join(missing)} (a dataset written by `swarm-sim dataset generate`, "
            "`aggregate` or `close-range` has them)"
        )
    flock = flock_ids(meta)
    pos = np.asarray(meta["pos_world_enu"], dtype=np.float64)
    n = len(flock)
    sep_world = np.zeros((n, 3))
    near_world = np.zeros((n, 3))
    rey_world = np.zeros((n, 3))
    bounds = np.flatnonzero(np.diff(flock)) + 1
    starts = np.concatenate(([0], bounds))
    ends = np.concatenate((bounds, [n]))
    sizes = ends - starts
    # flocks of one size are computed together: (F, k, k, 3) offsets in one go
    for size in np.unique(sizes):
        first = starts[sizes == size]
        rows = first[:, None] + np.arange(size)[None, :]  # (F, size)
        offsets = pairwise_offsets_batched(pos[rows]).reshape(-1, size, 3)
        valid = np.tile(~np.eye(size, dtype=bool), (len(first), 1))
        sep, near, rey = separation_parts(offsets, valid, params, near_m)
        sep_world[rows.ravel()] = sep
        near_world[rows.ravel()] = near
        rey_world[rows.ravel()] = rey
    to_world = quat_to_rotmat(np.asarray(meta["q_world_body"], dtype=np.float64))
    to_body = np.transpose(to_world, (0, 2, 1))
    return (
        np.einsum("nij,nj->ni", to_body, sep_world),
        np.einsum("nij,nj->ni", to_body, near_world),
        np.einsum("nij,nj->ni", to_body, rey_world),
    )


def separation_parts(
    offsets: NDArray[np.float64], valid: NDArray[np.bool_], params: FlockingParams, near_m: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(separation, its share from the neighbours within `near_m`, separation + cohesion) (N, 3)
    in the offsets' frame, from `reynolds_from_offsets`' (N, M, 3) offsets and (N, M) mask."""
    sep, coh, count = reynolds_from_offsets(offsets, valid, params)
    near = valid & (np.linalg.norm(offsets, axis=-1) < near_m)
    part, _, n_near = reynolds_from_offsets(offsets, near, params)
    # `part` is averaged over the near neighbours; the law averages over all of them
    share = np.divide(n_near, count, out=np.zeros(count.shape), where=count > 0)
    return sep, share[:, None] * part, sep + coh


def pairwise_offsets_batched(pos: NDArray[np.float64]) -> NDArray[np.float64]:
    """(F, k, 3) positions -> (F, k, k, 3) offsets r_ij = p_j - p_i within each flock."""
    return pos[:, None, :, :] - pos[:, :, None, :]


def cautious_targets(
    targets: NDArray[np.floating[Any]],
    meta: Mapping[str, NDArray[Any]],
    separation_scale: float,
    params: FlockingParams | None = None,
    what: str = "the training data",
    near_scale: float = 1.0,
    near_m: float = NEAR_M,
) -> NDArray[np.float32]:
    """The labels of the law with k_sep x `separation_scale` and the neighbours within `near_m`
    weighing `near_scale` in its separation sum (float32 (n, 3), body FLU m/s).

    Raises ConfigError when the stored labels are not the unscaled law's of the stored positions.
    """
    params = params or FlockingParams()
    sep_body, near_body, rey_body = flock_separation_body(meta, params, near_m)
    stored = np.asarray(targets, dtype=np.float64)
    err = np.abs(rey_body - stored).max(axis=1)
    worst = int(np.argmax(err)) if len(err) else 0
    if len(err) and err[worst] > LABEL_TOLERANCE_MPS:
        where = ", ".join(
            f"{c} {np.asarray(meta[c])[worst]}" for c in ("run", "time_s", "agent") if c in meta
        )
        raise ConfigError(
            f"separation_scale: {what}'s labels are not the flocking law's of its stored "
            f"positions (sample {worst}: {where}; off by {err[worst]:.3f} m/s; "
            f"{int((err > LABEL_TOLERANCE_MPS).sum())} samples off): an incomplete flock, or "
            "other gains; relabel only data written by this project's generators"
        )
    boost = separation_scale * (near_scale - 1.0)
    return (stored + (separation_scale - 1.0) * sep_body + boost * near_body).astype(np.float32)


def relabelled(
    split: SplitArrays,
    separation_scale: float,
    what: str,
    near_scale: float = 1.0,
    near_m: float = NEAR_M,
) -> JoinedSplit:
    """`split` with the labels of the law whose separation gain is scaled by `separation_scale`,
    its neighbours within `near_m` by `near_scale` more (its images shared, not copied); `what`
    names the split in an error."""
    images = split.images
    if not isinstance(images, StackedImages):
        images = StackedImages([np.asarray(images)])
    targets = cautious_targets(
        split.targets, split.meta, separation_scale, what=what, near_scale=near_scale, near_m=near_m
    )
    return JoinedSplit(images=images, targets=targets, meta=split.meta)
