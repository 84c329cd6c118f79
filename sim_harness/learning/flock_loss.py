"""The flock-sum term of the training loss: errors that the whole flock makes together.

A plain mean squared error treats the nine drones of one time step as nine unrelated samples. In
flight they are not: each command moves its drone, and the flock's centroid moves with the mean of
the commands. A small error that every drone of a flock shares (all of them under-answering the
minority's pull in a tug of war between two goals, by a few cm/s each) costs the plain loss little,
yet it is exactly what holds the flock's drift back, and what the opposing-goals count gap of
`benchmarks/opposing_balance.py` measures.

The term: for each flock f (the samples of one run at one time step), the sum of its members'
errors turned into the world frame, S_f = sum_i R_i (pred_i - target_i), and

    flock_term = sum_f |S_f|^2 / (3 * B)          (B samples in the batch)

For errors that are independent across drones it equals the mean squared error on average; an
error shared by n drones costs n times more. Training with `--weight-flock lam` minimizes
(mse + lam * flock_term) / (1 + lam), so the learning rate keeps its meaning. Only the loss knows
about flocks: at flight time each drone's command still comes from its own image alone.

Batches are then drawn as whole flocks (`flock_batches`), so that every flock's sum is complete.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.frames import quat_to_rotmat

FLOCK_COLUMNS = ("run", "time_s", "q_world_body")
PART_COLUMN = "part"  # optional: which dataset folder a row of a joined split came from


def flock_ids(meta: Mapping[str, NDArray[Any]]) -> NDArray[np.int64]:
    """Per-row flock index 0, 1, ...: rows of one run at one time step (contiguous, as stored).

    A new flock starts wherever the part, run or time changes from the previous row.
    """
    missing = [c for c in FLOCK_COLUMNS if c not in meta]
    if missing:
        raise ConfigError(
            f"weight_flock: the training data lacks the per-sample column(s) {', '.join(missing)}"
            " (a dataset written by `swarm-sim dataset generate` or `aggregate` has them)"
        )
    run = np.asarray(meta["run"])
    time = np.asarray(meta["time_s"])
    starts = np.ones(run.shape[0], dtype=bool)
    starts[1:] = (run[1:] != run[:-1]) | (time[1:] != time[:-1])
    if PART_COLUMN in meta:
        part = np.asarray(meta[PART_COLUMN])
        starts[1:] |= part[1:] != part[:-1]
    return (np.cumsum(starts) - 1).astype(np.int64)


@dataclass(frozen=True)
class FlockLoss:
    """The term's weight and each training sample's R_world_body (n, 3, 3) float32."""

    weight: float
    to_world: NDArray[np.float32]

    def view_to_world(self, rows: NDArray[np.int64], views: torch.Tensor) -> torch.Tensor:
        """(B, 3, 3): a batch's map from the augmented view's frame to the world.

        `views` holds each sample's label matrix L (`symmetry.augment_with_views`): L^T turns the
        view's frame back into the recorded body frame, R_world_body then into the world.
        """
        return torch.from_numpy(self.to_world[rows]) @ views.transpose(1, 2)


Batch = NDArray[np.int64] | tuple[NDArray[np.int64], NDArray[np.int64]]  # rows, or with flocks


def world_rotations(meta: Mapping[str, NDArray[Any]]) -> NDArray[np.float32]:
    """(n, 3, 3) float32: each sample's R_world_body (body FLU -> world ENU)."""
    return quat_to_rotmat(np.asarray(meta["q_world_body"], dtype=np.float64)).astype(np.float32)


def flock_batches(
    flock_id: NDArray[np.int64],
    rows: NDArray[np.int64],
    batch_size: int,
    seed: int,
    epoch: int,
) -> list[tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Batches of whole flocks covering the multiset `rows` once, in an order fixed by
    `(seed, epoch)`: per batch (rows sorted, batch-local flock index of each row).

    `rows` is an epoch's sample list (`batches.epoch_rows`: a sample shown k times appears k
    times, and all members of a flock share k): each showing of a flock is one entry. Entries are
    shuffled and packed in turn: a batch takes the next one while it stays within `batch_size`
    samples (at least one entry). Two showings of a flock in one batch are two flocks of it.
    """
    unique_rows, counts = np.unique(rows, return_counts=True)
    ids = flock_id[unique_rows]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], unique_rows.shape[0]]
    entries: list[NDArray[np.int64]] = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        shown = counts[s:e]
        if (shown != shown[0]).any():
            raise ValueError(f"flock {int(ids[s])}: its rows are not all shown equally often")
        entries.extend(unique_rows[s:e] for _ in range(int(shown[0])))
    order = np.random.default_rng([seed, epoch, 0xF10C]).permutation(len(entries))
    batches: list[tuple[NDArray[np.int64], NDArray[np.int64]]] = []
    current: list[NDArray[np.int64]] = []
    filled = 0
    for k in [*order.tolist(), None]:
        if current and (k is None or filled + entries[k].shape[0] > batch_size):
            batch_rows = np.concatenate(current)
            local = np.repeat(np.arange(len(current)), [c.shape[0] for c in current])
            keep = np.argsort(batch_rows, kind="stable")
            batches.append((batch_rows[keep], local[keep].astype(np.int64)))
            current, filled = [], 0
        if k is not None:
            current.append(entries[k])
            filled += entries[k].shape[0]
    return batches


def flock_term(
    error_body: torch.Tensor,
    to_world: torch.Tensor,
    local_flock: torch.Tensor,
    n_flocks: int,
) -> torch.Tensor:
    """sum_f |sum_{i in f} to_world_i @ error_i|^2 / (3 B), (m/s)^2.

    `error_body` (B, 3): prediction minus target in the frame the network saw; `to_world`
    (B, 3, 3) maps that frame to the world (R_world_body, times the augmentation's view matrix
    transposed); `local_flock` (B,) int64 in [0, n_flocks).
    """
    world = torch.bmm(to_world, error_body.unsqueeze(-1)).squeeze(-1)
    sums = torch.zeros((n_flocks, 3), dtype=world.dtype, device=world.device)
    sums = sums.index_add(0, local_flock, world)
    return sums.square().sum() / (3 * error_body.shape[0])
