"""Image sources for the camera emulator: what the six emulated cameras see, tick by tick."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_SIZE_PX, IMAGE_WIDTH_PX, N_FACES, split
from sim_harness.errors import SimError

TileSource = Callable[[float], NDArray[np.uint8] | Sequence[NDArray[np.uint8]]]
"""Seconds since the emulator started -> six (64, 64) uint8 tiles in FACE_NAMES order."""


def bar_pattern(t_s: float) -> NDArray[np.uint8]:
    """Default source: per face a distinct level plus a bar moving one column per 0.1 s."""
    tiles = np.empty((N_FACES, FACE_SIZE_PX, FACE_SIZE_PX), dtype=np.uint8)
    for index in range(N_FACES):
        tiles[index] = 30 + 35 * index
    tiles[:, :, int(t_s * 10.0) % FACE_SIZE_PX] = 255
    return tiles


def as_tile_source(
    source: TileSource | NDArray[np.uint8],
) -> Callable[[float, int], NDArray[np.uint8]]:
    """Uniform source: (seconds since start, tick index) -> (6, 64, 64) tiles.

    A `TileSource` is called with the time; a recording (N, 64, 384) uint8 of stitched frames is
    played in a loop, frame `tick % N` at tick `tick`. The caller checks the shape and dtype of
    what a `TileSource` returns.
    """
    if isinstance(source, np.ndarray):
        recorded = np.asarray(source)
        shape_ok = recorded.shape[1:] == (FACE_SIZE_PX, IMAGE_WIDTH_PX) and len(recorded) > 0
        if not shape_ok or recorded.dtype != np.uint8:
            raise SimError(f"camera emulator: recording must be (N, 64, 384) uint8, "
                           f"got {recorded.dtype} {recorded.shape}")  # fmt: skip
        tiles = split(recorded)  # (N, 6, 64, 64)
        return lambda _t_s, tick: tiles[tick % len(tiles)]
    fn = source
    return lambda t_s, _tick: np.asarray(fn(t_s))
