"""Mini-batches straight from a dataset split's arrays: index arrays in, tensors out.

No per-sample Python: a batch is one sorted index array taken from the (memory-mapped or in-RAM)
uint8 image array in one fancy-indexing call (sorted, so a memmap reads forward through the file),
wrapped with `torch.from_numpy`. A background thread prepares the next batches while the model
trains on the current one; its queue holds at most `depth` batches.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol, TypeVar

import numpy as np
import torch
from numpy.typing import NDArray

T = TypeVar("T")


class ImageRows(Protocol):
    """uint8 images (n, 64, 384) indexed by row: a numpy array, a memmap or `StackedImages`."""

    @property
    def shape(self) -> tuple[int, ...]: ...

    @property
    def nbytes(self) -> int: ...

    def __getitem__(self, index: Any, /) -> Any: ...


class SplitArrays(Protocol):
    """What training and evaluation read from a dataset split (see `sim_harness.dataset.store`).

    `images`: uint8 (n, 64, 384); `targets`: float32 (n, 3), body FLU velocity in m/s;
    `meta`: per-sample columns, each (n,) (e.g. "n_neighbours", "nearest_m").
    """

    @property
    def n_samples(self) -> int: ...

    @property
    def images(self) -> ImageRows: ...

    @property
    def targets(self) -> NDArray[np.float32]: ...

    @property
    def meta(self) -> Mapping[str, NDArray[Any]]: ...


@dataclass(frozen=True)
class InMemorySplit:
    """A split held in plain arrays (a subset loaded into RAM, or synthetic data in tests)."""

    images: NDArray[np.uint8]
    targets: NDArray[np.float32]
    meta: Mapping[str, NDArray[Any]]

    @property
    def n_samples(self) -> int:
        return int(self.images.shape[0])


class StackedImages:
    """Several (n_k, 64, 384) uint8 arrays read as one, in order, without copying them.

    The parts stay where they are (a dataset's split is a read-only memmap of its image cache),
    so training on a base dataset plus aggregation rounds and extra linear sets needs the page
    cache, not RAM the size of every image. Indexing takes what training and evaluation use: an
    int, a slice, or an integer index array (sorted rows read each part's file forward).
    """

    def __init__(self, parts: list[NDArray[np.uint8]]) -> None:
        if not parts:
            raise ValueError("no image arrays to stack")
        frame = parts[0].shape[1:]
        if any(part.shape[1:] != frame or part.dtype != np.uint8 for part in parts):
            raise ValueError(f"every part must be uint8 images of shape (n, {frame})")
        self.parts = parts
        self.starts = np.cumsum([0] + [part.shape[0] for part in parts])
        self.shape: tuple[int, ...] = (int(self.starts[-1]), *frame)
        self.dtype = np.dtype(np.uint8)

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape))

    def __getitem__(self, index: int | slice | NDArray[np.integer]) -> NDArray[np.uint8]:
        if isinstance(index, slice):
            return self[np.arange(*index.indices(len(self)))]
        rows = np.asarray(index)
        if rows.ndim == 0:
            return self[rows[None]][0]
        if rows.dtype.kind not in "iu":
            raise IndexError(f"stacked images take integer rows, got {rows.dtype}")
        rows = np.where(rows < 0, rows + len(self), rows)
        if rows.size and (rows.min() < 0 or rows.max() >= len(self)):
            raise IndexError(f"rows out of range for {len(self)} images")
        part_of = np.searchsorted(self.starts, rows, side="right") - 1
        out = np.empty((rows.size, *self.shape[1:]), dtype=np.uint8)
        for k in np.unique(part_of):
            mine = part_of == k
            out[mine] = self.parts[k][rows[mine] - self.starts[k]]
        return out

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> NDArray[Any]:
        whole = self[slice(None)]
        return whole if dtype is None else whole.astype(dtype)


@dataclass(frozen=True)
class JoinedSplit:
    """Several splits read as one: images stacked in place, targets and meta joined in RAM."""

    images: StackedImages
    targets: NDArray[np.float32]
    meta: Mapping[str, NDArray[Any]]

    @property
    def n_samples(self) -> int:
        return len(self.images)


def concat_splits(parts: list[SplitArrays]) -> JoinedSplit:
    """One split holding every sample of `parts` in order (meta: the columns all share).

    The images are not copied (`StackedImages`); the small per-sample arrays are.
    """
    keys = set.intersection(*(set(part.meta) for part in parts))
    return JoinedSplit(
        images=StackedImages([part.images for part in parts]),
        targets=np.concatenate([np.asarray(part.targets, dtype=np.float32) for part in parts]),
        meta={key: np.concatenate([np.asarray(part.meta[key]) for part in parts]) for key in keys},
    )


def subset(split: SplitArrays, limit: int | None, seed: int, ram_max_bytes: int) -> SplitArrays:
    """The first-come `limit` samples of a seeded permutation (all when `limit` is None).

    The chosen rows are copied into RAM when they fit in `ram_max_bytes`; otherwise the split is
    returned as is (memmapped) when no limit applies, or the subset's rows are copied anyway
    (a limit is meant for quick runs).
    """
    n = split.n_samples
    if limit is None or limit >= n:
        if split.images.nbytes > ram_max_bytes:
            return split
        rows = np.arange(n)
    else:
        rows = np.sort(np.random.default_rng(seed).permutation(n)[:limit])
    return InMemorySplit(  # fancy indexing copies: the result no longer touches the memmap
        images=split.images[rows],
        targets=np.asarray(split.targets[rows], dtype=np.float32),
        meta={key: np.asarray(col[rows]) for key, col in split.meta.items()},
    )


REPEAT_COLUMN = "repeat"  # optional per-sample meta column: how often an epoch shows the sample


def epoch_rows(split: SplitArrays) -> NDArray[np.int64]:
    """The sample indices one epoch covers: each sample once, or `meta["repeat"]` times."""
    n = split.n_samples
    counts = split.meta.get(REPEAT_COLUMN)
    if counts is None:
        return np.arange(n, dtype=np.int64)
    return np.repeat(np.arange(n, dtype=np.int64), np.asarray(counts, dtype=np.int64))


def shuffled_batches(
    n: int, batch_size: int, seed: int, epoch: int, rows: NDArray[np.int64] | None = None
) -> list[NDArray[np.int64]]:
    """Index arrays covering `range(n)` (or the multiset `rows` of n entries) once in a random
    order fixed by `(seed, epoch)`.

    Each batch is sorted (memmap locality); the last one may be smaller. A fixed per-epoch order
    makes a resumed run see the same batches as an uninterrupted one.
    """
    order = np.random.default_rng([seed, epoch]).permutation(n)
    if rows is not None:
        order = rows[order]
    return [np.sort(order[i : i + batch_size]) for i in range(0, n, batch_size)]


_Split = TypeVar("_Split", InMemorySplit, JoinedSplit)


def with_repeats(split: _Split, counts: NDArray[np.int64]) -> _Split:
    """`split` with a per-sample repeat count (see `epoch_rows`)."""
    if counts.shape != (split.n_samples,) or (counts < 1).any():
        raise ValueError(f"need one count >= 1 per sample ({split.n_samples})")
    return replace(split, meta={**split.meta, REPEAT_COLUMN: counts})


def sequential_batches(n: int, batch_size: int) -> list[slice]:
    """Contiguous slices covering `range(n)` in order (evaluation)."""
    return [slice(i, min(i + batch_size, n)) for i in range(0, n, batch_size)]


def load_batch(
    split: SplitArrays, rows: NDArray[np.int64] | slice, pin: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """(images uint8 (B, 64, 384), targets float32 (B, 3)) as CPU tensors, optionally pinned."""
    images = torch.from_numpy(np.array(split.images[rows]))  # a writable copy, even of a slice
    targets = torch.from_numpy(np.array(split.targets[rows], dtype=np.float32))
    if pin:
        images, targets = images.pin_memory(), targets.pin_memory()
    return images, targets


def prefetch(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Iterate `items`, produced by a background thread at most `depth` items ahead.

    An exception in the producer is raised in the consumer. Leaving the loop early (break, error)
    stops the producer and joins it.
    """
    slots: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(kind: str, value: Any) -> bool:
        while not stop.is_set():
            try:
                slots.put((kind, value), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put("item", item):
                    return
        except BaseException as exc:  # handed to the consumer, which re-raises it
            put("error", exc)
            return
        put("done", None)

    worker = threading.Thread(target=produce, name="batch-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            kind, value = slots.get()
            if kind == "done":
                return
            if kind == "error":
                raise value
            yield value
    finally:
        stop.set()
        worker.join()
