"""The camera rig contract: six cube-map cameras and how their images form one 64x384 strip.

Shared byte for byte by the simulation (rendering, dataset), the onboard rig (stitching) and the
exported model's metadata. Body frame FLU (x forward, y left, z up).

Faces, left to right in the strip (each 64x64 tile, row 0 at the top, column 0 at the left):

| index | face  | optical axis (body) | image up (body) | image right (body) |
|-------|-------|---------------------|-----------------|--------------------|
| 0     | front | +x                  | +z              | -y                 |
| 1     | right | -y                  | +z              | -x                 |
| 2     | back  | -x                  | +z              | +y                 |
| 3     | left  | +y                  | +z              | +x                 |
| 4     | up    | +z                  | -x              | -y                 |
| 5     | down  | -z                  | +x              | -y                 |

The first four tiles form one continuous 360 deg panorama turning clockwise (seen from above) from
the front; each tile's right edge meets the next tile's left edge. The up and down faces are seen as
if the front camera tilted up (or down) by 90 deg: the up tile's bottom edge and the down tile's top
edge meet the front tile.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FACE_NAMES: tuple[str, ...] = ("front", "right", "back", "left", "up", "down")
FACE_SIZE_PX = 64
N_FACES = len(FACE_NAMES)
IMAGE_HEIGHT_PX = FACE_SIZE_PX
IMAGE_WIDTH_PX = FACE_SIZE_PX * N_FACES
FOV_DEG = 100.0  # horizontal and vertical
CAMERA_OFFSET_M = 0.15  # from the centre of gravity along each optical axis
FRAME_RATE_HZ = 10.0
PIXEL_FORMAT = "GRAY8"


@dataclass(frozen=True)
class Face:
    """One camera: optical axis and image up direction as unit vectors in the body frame (FLU)."""

    name: str
    axis_body_flu: tuple[float, float, float]
    up_body_flu: tuple[float, float, float]

    @property
    def right_body_flu(self) -> tuple[float, float, float]:
        """Image right = axis x up (right-handed camera: right, up, backwards = -axis)."""
        r = np.cross(self.axis_body_flu, self.up_body_flu)
        return (float(r[0]), float(r[1]), float(r[2]))

    @property
    def position_body_flu(self) -> tuple[float, float, float]:
        """Camera centre in the body frame, `CAMERA_OFFSET_M` along the axis."""
        a = self.axis_body_flu
        return (a[0] * CAMERA_OFFSET_M, a[1] * CAMERA_OFFSET_M, a[2] * CAMERA_OFFSET_M)


FACES: tuple[Face, ...] = (
    Face("front", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    Face("right", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    Face("back", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    Face("left", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    Face("up", (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0)),
    Face("down", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)),
)
assert tuple(f.name for f in FACES) == FACE_NAMES


def stitch(tiles: Sequence[NDArray[np.uint8]] | NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Six 64x64 uint8 tiles in `FACE_NAMES` order -> one 64x384 uint8 image.

    Accepts a sequence of six (64, 64) arrays or an array (..., 6, 64, 64) (batched).
    """
    arr = np.asarray(tiles)
    if arr.shape[-3:] != (N_FACES, FACE_SIZE_PX, FACE_SIZE_PX) or arr.dtype != np.uint8:
        raise ValueError(
            f"expected uint8 tiles of shape (..., {N_FACES}, {FACE_SIZE_PX}, {FACE_SIZE_PX}), "
            f"got {arr.dtype} {arr.shape}"
        )
    moved = np.moveaxis(arr, -3, -2)  # (..., 64, 6, 64)
    return np.ascontiguousarray(moved.reshape(*arr.shape[:-3], IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX))


def split(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """Inverse of `stitch`: (..., 64, 384) -> (..., 6, 64, 64)."""
    arr = np.asarray(image)
    if arr.shape[-2:] != (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX):
        raise ValueError(f"expected (..., {IMAGE_HEIGHT_PX}, {IMAGE_WIDTH_PX}), got {arr.shape}")
    tiles = arr.reshape(*arr.shape[:-2], IMAGE_HEIGHT_PX, N_FACES, FACE_SIZE_PX)
    return np.ascontiguousarray(np.moveaxis(tiles, -2, -3))


def camera_spec() -> dict[str, Any]:
    """The rig as plain data, for dataset manifests and model metadata."""
    return {
        "faces": [
            {
                "name": f.name,
                "axis_body_flu": list(f.axis_body_flu),
                "up_body_flu": list(f.up_body_flu),
            }
            for f in FACES
        ],
        "face_size_px": FACE_SIZE_PX,
        "image_shape": [IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX],
        "fov_deg": FOV_DEG,
        "camera_offset_m": CAMERA_OFFSET_M,
        "frame_rate_hz": FRAME_RATE_HZ,
        "pixel_format": PIXEL_FORMAT,
        "body_frame": "FLU",
    }
