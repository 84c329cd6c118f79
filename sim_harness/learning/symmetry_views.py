"""The camera rig's symmetric views as pixel and label maps (numpy only; `learning.symmetry`
explains them and applies them to torch batches).

A view is `(turns, mirrored)`: first mirror the scene in the body x-z plane (when `mirrored`),
then turn the drone `turns` quarter turns to the left about its z axis.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX, split, stitch
from companion.errors import ConfigError

View = tuple[int, bool]  # (quarter turns to the left, mirrored first)

GROUPS: dict[str, tuple[View, ...]] = {
    "none": ((0, False),),
    "mirror": ((0, False), (0, True)),
    "c4": tuple((k, False) for k in range(4)),
    "d4": tuple((k, m) for m in (False, True) for k in range(4)),
}

_FRONT, _RIGHT, _BACK, _LEFT, _UP, _DOWN = (FACE_NAMES.index(n) for n in FACE_NAMES)
# Quarter turn left: new tile i shows old tile _TURN_SOURCE[i].
_TURN_SOURCE = (_LEFT, _FRONT, _RIGHT, _BACK, _UP, _DOWN)
# Mirror in the body x-z plane: right and left swap (each tile is also flipped left-right).
_MIRROR_SOURCE = (_FRONT, _LEFT, _BACK, _RIGHT, _UP, _DOWN)

_TURN_LABEL = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_MIRROR_LABEL = np.diag([1.0, -1.0, 1.0])


def require_group(name: str, field: str = "symmetry") -> tuple[View, ...]:
    """The views of a group by name; `ConfigError` naming the field and the choices otherwise."""
    if name not in GROUPS:
        choices = ", ".join(GROUPS)
        raise ConfigError(f"{field}: unknown symmetry group {name!r}; choose one of {choices}")
    return GROUPS[name]


def _turn_tiles(tiles: NDArray[np.generic]) -> NDArray[np.generic]:
    out = tiles[..., list(_TURN_SOURCE), :, :].copy()
    out[..., _UP, :, :] = np.rot90(tiles[..., _UP, :, :], k=1, axes=(-2, -1))
    out[..., _DOWN, :, :] = np.rot90(tiles[..., _DOWN, :, :], k=-1, axes=(-2, -1))
    return out


def _mirror_tiles(tiles: NDArray[np.generic]) -> NDArray[np.generic]:
    return np.flip(tiles[..., list(_MIRROR_SOURCE), :, :], axis=-1).copy()


def view_image(image: NDArray[np.generic], view: View) -> NDArray[np.generic]:
    """The stitched image(s) (..., 64, 384) as the drone would see them in `view`."""
    turns, mirrored = view
    tiles = split(np.asarray(image))
    if mirrored:
        tiles = _mirror_tiles(tiles)
    for _ in range(turns % 4):
        tiles = _turn_tiles(tiles)
    return stitch(tiles) if tiles.dtype == np.uint8 else _stitch_any(tiles)


def _stitch_any(tiles: NDArray[np.generic]) -> NDArray[np.generic]:
    moved = np.moveaxis(tiles, -3, -2)
    return np.ascontiguousarray(moved.reshape(*tiles.shape[:-3], IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX))


def label_matrix(view: View) -> NDArray[np.float64]:
    """3x3 orthogonal L: a body-frame vector v of the original view is L @ v in `view`."""
    turns, mirrored = view
    matrix = np.linalg.matrix_power(_TURN_LABEL, turns % 4)
    return matrix @ _MIRROR_LABEL if mirrored else matrix


@cache
def pixel_source(view: View) -> NDArray[np.int64]:
    """Flat index map: `view_image(x).ravel() == x.ravel()[pixel_source(view)]`."""
    index = np.arange(IMAGE_HEIGHT_PX * IMAGE_WIDTH_PX, dtype=np.int64)
    return view_image(index.reshape(IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX), view).ravel()
