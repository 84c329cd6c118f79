"""Training batches: shuffled and seeded, repeated samples, subsets in RAM, prefetching, joined
memory-mapped splits read in place."""

from pathlib import Path

import numpy as np
import pytest

from sim_harness.dataset.store import open_dataset
from sim_harness.learning.batches import (
    InMemorySplit,
    concat_splits,
    epoch_rows,
    load_batch,
    prefetch,
    shuffled_batches,
    subset,
    with_repeats,
)


def test_batches_cover_every_sample_once_sorted_and_seeded() -> None:
    batches = shuffled_batches(70, 32, seed=3, epoch=2)
    assert [len(b) for b in batches] == [32, 32, 6]
    assert all(np.all(np.diff(b) > 0) for b in batches)
    assert sorted(np.concatenate(batches).tolist()) == list(range(70))
    again = shuffled_batches(70, 32, seed=3, epoch=2)
    assert all(np.array_equal(a, b) for a, b in zip(batches, again, strict=True))
    other = shuffled_batches(70, 32, seed=3, epoch=3)
    assert not all(np.array_equal(a, b) for a, b in zip(batches, other, strict=True))


def test_a_repeat_column_shows_a_sample_that_many_times_per_epoch() -> None:
    images = np.zeros((5, 64, 384), dtype=np.uint8)
    split = InMemorySplit(images, np.zeros((5, 3), dtype=np.float32), {})
    assert epoch_rows(split).tolist() == [0, 1, 2, 3, 4]
    weighted = with_repeats(split, np.array([1, 1, 3, 1, 2]))
    rows = epoch_rows(weighted)
    batches = shuffled_batches(len(rows), 4, seed=0, epoch=1, rows=rows)
    assert sorted(np.concatenate(batches).tolist()) == [0, 1, 2, 2, 2, 3, 4, 4]
    with pytest.raises(ValueError, match="count >= 1"):
        with_repeats(split, np.array([1, 0, 1, 1, 1]))


def test_a_limited_split_is_a_fixed_subset_in_ram(smoke_dataset) -> None:
    split = open_dataset(smoke_dataset).split("train")
    part = subset(split, 50, seed=0, ram_max_bytes=2**30)
    assert isinstance(part, InMemorySplit) and part.n_samples == 50
    again = subset(split, 50, seed=0, ram_max_bytes=2**30)
    assert np.array_equal(part.targets, again.targets)
    rows = np.sort(np.random.default_rng(0).permutation(split.n_samples)[:50])
    assert np.array_equal(part.images, split.images[rows])
    assert np.array_equal(part.meta["nearest_m"], split.meta["nearest_m"][rows])
    assert subset(split, None, seed=0, ram_max_bytes=0) is split  # too big: stays memory-mapped


def test_prefetch_keeps_order_and_raises_the_producers_error() -> None:
    assert list(prefetch(iter(range(50)), depth=2)) == list(range(50))

    def failing():
        yield 1
        raise OSError("disk gone")

    with pytest.raises(OSError, match="disk gone"):
        list(prefetch(failing()))


def test_joined_splits_read_every_image_in_place_and_in_order(tmp_path: Path) -> None:
    # two memmapped "datasets" joined for training: nothing is copied into RAM up front, and any
    # rows (sorted batches, unsorted picks, slices, negative indices) read the right images
    rng = np.random.default_rng(0)
    arrays = []
    for k, n in enumerate((7, 5)):
        path = tmp_path / f"images-{k}.npy"
        mm = np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=(n, 64, 384))
        mm[:] = rng.integers(0, 256, size=mm.shape, dtype=np.uint8)
        mm.flush()
        arrays.append(np.load(path, mmap_mode="r"))
    parts = [
        InMemorySplit(a, np.full((len(a), 3), k, np.float32), {"nearest_m": np.arange(len(a))})
        for k, a in enumerate(arrays)
    ]
    joined = concat_splits(parts)
    whole = np.concatenate(arrays)
    assert joined.n_samples == 12 and joined.images.nbytes == whole.nbytes
    assert all(isinstance(part, np.memmap) for part in joined.images.parts)
    for rows in (np.array([0, 3, 6, 7, 11]), np.array([11, 2, 8, 2]), np.arange(12)):
        assert np.array_equal(joined.images[rows], whole[rows])
    assert np.array_equal(joined.images[5:9], whole[5:9])
    assert np.array_equal(joined.images[-1], whole[-1])
    assert joined.targets[:, 0].tolist() == [0.0] * 7 + [1.0] * 5
    assert joined.meta["nearest_m"].tolist() == [*range(7), *range(5)]
    images, targets = load_batch(joined, np.array([6, 7]))
    assert np.array_equal(images.numpy(), whole[[6, 7]]) and targets[:, 0].tolist() == [0.0, 1.0]
    # a joined split larger than the RAM allowance is trained on in place, a small one copied
    assert subset(joined, None, seed=0, ram_max_bytes=whole.nbytes - 1) is joined
    small = subset(joined, None, seed=0, ram_max_bytes=whole.nbytes)
    assert isinstance(small, InMemorySplit) and np.array_equal(small.images, whole)
    with pytest.raises(IndexError, match="out of range"):
        joined.images[np.array([12])]
