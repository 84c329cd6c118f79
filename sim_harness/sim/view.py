"""Pictures of what one drone sees: the 64x384 strip and an enlarged, labelled cube-cross layout."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import cv2
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES, split

# Cube cross: the panorama row is left | front | right | back; up above and down below the front.
_CROSS_CELLS = {
    "up": (0, 1),
    "left": (1, 0),
    "front": (1, 1),
    "right": (1, 2),
    "back": (1, 3),
    "down": (2, 1),
}


def save_strip(image: NDArray[np.uint8], path: Path, scale: int = 4) -> Path:
    """The 64x384 strip as a PNG, enlarged `scale` times with nearest-neighbour pixels."""
    path.parent.mkdir(parents=True, exist_ok=True)
    big = cv2.resize(
        image, (image.shape[1] * scale, image.shape[0] * scale), interpolation=cv2.INTER_NEAREST
    )
    if not cv2.imwrite(str(path), big):
        raise OSError(f"could not write {path}")
    return path


def save_layout(image: NDArray[np.uint8], path: Path, title: str) -> Path:
    """The six faces as a labelled cube cross (3 x 4 cells)."""
    tiles = split(image)
    fig, axes = plt.subplots(3, 4, figsize=(8, 6.4), dpi=110)
    for ax in axes.flat:
        ax.axis("off")
    for name, tile in zip(FACE_NAMES, tiles, strict=True):
        ax = axes[_CROSS_CELLS[name]]
        ax.imshow(tile, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_title(name, fontsize=10)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
