"""The labels of a more cautious teacher, recomputed from the stored positions of each flock.

Every dataset stores, for every sample, the teacher's Reynolds command in the body frame (the
label) and the drone's world position and attitude at the moment its image was taken; the samples
of one run at one time step are the whole flock. From those positions the separation term can be
computed again, so a training run can learn the flocking law with its separation gain scaled by
S (k_sep x S), and with the neighbours closer than R (default `NEAR_M`) weighing C in the
separation sum (a close-range boost), without drawing one image again:

    label' = label + (S - 1) * R_body_world * separation(positions)
                   + S * (C - 1) * R_body_world * separation_near(positions)

where separation is the whole separation term (or, with a reach M, its share from the neighbours
within M) and separation_near its share from the neighbours within R (still averaged over all
neighbours, as the law averages). With a ramp W > 0 the boost does not step in
at R: a neighbour at distance d counts in separation_near with the share clip((R - d) / W, 0, 1),
so its weight rises linearly from 1 at R to C at R - W and stays C closer. With a separation
reach M (default: every neighbour), k_sep x S applies only to the neighbours closer than M: the
caution where a neighbour can be hit, the paper's law for the far ones (whose 7/d terms, over the
whole flock, are most of the label and most of what the paper's R² scores). A network answers the
step blurred, too weakly inside R and too strongly just outside (`benchmarks/boost_answer.py`);
a ramp is a label it can follow, but for the same cost in the paper's R² it holds the faster
flock's pairs closer than the step does, while the reach M = 4 m keeps them and gains R²
(docs/BENCHMARKS.md, "What the R² aim leaves for a cautious law").

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
from companion.flocking import COINCIDENT_M, FlockingParams, reynolds_from_offsets
from companion.frames import quat_to_rotmat
from sim_harness.learning.batches import JoinedSplit, SplitArrays, StackedImages
from sim_harness.learning.flock_loss import flock_ids

POSITION_COLUMNS = ("pos_world_enu", "q_world_body")
NEAR_M = 1.2  # by default the close-range boost weighs the neighbours closer than this
RAMP_M = 0.0  # by default the boost steps in at its reach (no ramp)
# by default k_sep x S applies to every neighbour (None); else to those closer than this
SCALE_REACH_M: float | None = None
# the stored label is float32, the positions too: the law recomputed from them agrees to ~1e-5
LABEL_TOLERANCE_MPS = 2e-3


def flock_separation_body(
    meta: Mapping[str, NDArray[Any]],
    params: FlockingParams,
    near_m: float = NEAR_M,
    ramp_m: float = RAMP_M,
    reach_m: float | None = SCALE_REACH_M,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(separation (its share from the neighbours within `reach_m`, if given), its share from the
    neighbours within `near_m` (ramped in over `ramp_m`), separation + cohesion) of every
    sample, body FLU m/s, from the positions of its flock (the rows of one run at one time step,
    as `flock_ids` groups them)."""
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
        sep, near, rey = separation_parts(offsets, valid, params, near_m, ramp_m, reach_m)
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
    offsets: NDArray[np.float64],
    valid: NDArray[np.bool_],
    params: FlockingParams,
    near_m: float,
    ramp_m: float = RAMP_M,
    reach_m: float | None = SCALE_REACH_M,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(separation (or its share from the neighbours within `reach_m`), its share from the
    neighbours within `near_m`, separation + cohesion) (N, 3) in the offsets' frame, from
    `reynolds_from_offsets`' (N, M, 3) offsets and (N, M) mask; with `ramp_m` > 0 each
    neighbour's share of the second is `boost_shares`'."""
    sep, coh, count = reynolds_from_offsets(offsets, valid, params)
    dist = np.linalg.norm(np.where(valid[..., None], offsets, 0.0), axis=-1)
    scaled = sep if reach_m is None else _share(offsets, valid & (dist < reach_m), count, params)
    if ramp_m <= 0.0:
        return scaled, _share(offsets, valid & (dist < near_m), count, params), sep + coh
    weight = boost_shares(dist, valid, near_m, ramp_m)
    # each neighbour's separation, -k_sep r / |r|^2, weighted, averaged over all neighbours
    d2 = dist**2
    inv_d2 = np.divide(weight, d2, out=np.zeros_like(d2), where=weight > 0)
    scale = np.divide(1.0, count, out=np.zeros(count.shape), where=count > 0)[:, None]
    r = np.where(valid[..., None], offsets, 0.0)
    near_part = -params.k_sep * scale * np.einsum("nm,nmk->nk", inv_d2, r)
    return scaled, near_part, sep + coh


def _share(
    offsets: NDArray[np.float64],
    subset: NDArray[np.bool_],
    count: NDArray[np.int64],
    params: FlockingParams,
) -> NDArray[np.float64]:
    """The separation of the neighbours in `subset`, averaged over all `count` neighbours as the
    law averages (N, 3)."""
    part, _, n_part = reynolds_from_offsets(offsets, subset, params)
    share = np.divide(n_part, count, out=np.zeros(count.shape), where=count > 0)
    return share[:, None] * part


def boost_shares(
    dist: NDArray[np.float64], valid: NDArray[np.bool_], near_m: float, ramp_m: float = RAMP_M
) -> NDArray[np.float64]:
    """Each neighbour's share of the close-range boost, (N, M) in [0, 1]: 1 closer than
    `near_m` - `ramp_m`, falling linearly to 0 at `near_m` (a step at `near_m` without a ramp);
    0 for invalid slots and neighbours that coincide with the agent."""
    if ramp_m <= 0.0:
        share = (dist < near_m).astype(np.float64)
    else:
        share = np.clip((near_m - dist) / ramp_m, 0.0, 1.0)
    return np.where(valid & (dist >= COINCIDENT_M), share, 0.0)


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
    ramp_m: float = RAMP_M,
    reach_m: float | None = SCALE_REACH_M,
) -> NDArray[np.float32]:
    """The labels of the law with k_sep x `separation_scale` (for the neighbours within
    `reach_m`, if given) and the neighbours within `near_m` weighing `near_scale` in its
    separation sum, ramped in over `ramp_m` (float32 (n, 3), body FLU m/s).

    Raises ConfigError when the stored labels are not the unscaled law's of the stored positions.
    """
    params = params or FlockingParams()
    sep_body, near_body, rey_body = flock_separation_body(meta, params, near_m, ramp_m, reach_m)
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
    ramp_m: float = RAMP_M,
    reach_m: float | None = SCALE_REACH_M,
) -> JoinedSplit:
    """`split` with the labels of the law whose separation gain is scaled by `separation_scale`
    (within `reach_m`, if given), its neighbours within `near_m` by `near_scale` more, ramped in
    over `ramp_m` (its images shared, not copied); `what` names the split in an error."""
    images = split.images
    if not isinstance(images, StackedImages):
        images = StackedImages([np.asarray(images)])
    targets = cautious_targets(
        split.targets,
        split.meta,
        separation_scale,
        what=what,
        near_scale=near_scale,
        near_m=near_m,
        ramp_m=ramp_m,
        reach_m=reach_m,
    )
    return JoinedSplit(images=images, targets=targets, meta=split.meta)
