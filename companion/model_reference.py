"""The reference input and output recorded with a policy at export: a platform check at load.

A CPU, a torch build or a kernel can compute a policy wrongly while every hash matches (measured
under an emulated CPU with 512-bit SVE: the last linear layer off by 8.9 m/s, every other layer
right). So the export records one stitched image and the model's output on it, computed on the
export machine, in the sidecar `NAME.json` under `"reference"`:

    {"image_png_base64": <64x384 8-bit grey PNG>, "output_body_flu_mps": [x, y, z],
     "tolerance_mps": 0.001, "made_with": {...how, torch version, machine...}}

`Policy.load` runs the warmed-up policy on that image through the call that flies and refuses a
model whose output differs by more than `tolerance_mps` (`check_reference`). The sidecar is not
covered by the model's hash: the reference can only make the loader stricter, and its tolerance
is bounded by `MAX_TOLERANCE_MPS`.

Tolerance: fused vs unfused graphs, batch sizes, AVX2 vs AVX-512 and x86 vs ARM reorder float32
sums and move the shipped model's outputs by up to ~4e-6 m/s; 1e-3 m/s leaves a margin of 250x
over that and is still 8,900x below the fault above (a 1e-3 m/s error integrates to 1 cm in 10 s).
"""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ModelError

SIDECAR_KEY = "reference"
DEFAULT_TOLERANCE_MPS = 1e-3
MAX_TOLERANCE_MPS = 0.01  # a looser reference would no longer catch a wrong platform
IMAGE_SHAPE = (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX)


@dataclass(frozen=True)
class Reference:
    """One stitched image (64, 384) uint8 and the body-FLU velocity (3,) m/s it must give."""

    image_u8: NDArray[np.uint8]
    output_body_flu_mps: tuple[float, float, float]
    tolerance_mps: float = DEFAULT_TOLERANCE_MPS
    made_with: Mapping[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        """The sidecar's `"reference"` value."""
        ok, png = cv2.imencode(".png", np.ascontiguousarray(self.image_u8))
        if not ok:  # pragma: no cover - OpenCV always encodes an 8-bit grey image
            raise ModelError("cannot encode the reference image as PNG")
        return {
            "image_png_base64": base64.b64encode(png.tobytes()).decode("ascii"),
            "output_body_flu_mps": [float(v) for v in self.output_body_flu_mps],
            "tolerance_mps": self.tolerance_mps,
            "made_with": dict(self.made_with or {}),
        }

    def error_mps(self, output: NDArray[Any]) -> float:
        """Largest |output - reference| over the three axes; inf for a wrong shape or NaN."""
        got = np.asarray(output, dtype=np.float64).reshape(-1)
        if got.shape != (3,) or not np.all(np.isfinite(got)):
            return math.inf
        return float(np.max(np.abs(got - np.asarray(self.output_body_flu_mps))))


def reference_from_json(data: Any, where: str) -> Reference:
    """Parse a sidecar's `"reference"`; `ModelError` naming the field for anything malformed."""
    if not isinstance(data, Mapping):
        raise ModelError(f"{where}: reference must be an object, got {type(data).__name__}")
    try:
        png = base64.b64decode(str(data["image_png_base64"]), validate=True)
    except (KeyError, binascii.Error, ValueError) as exc:
        raise ModelError(
            f"{where}: reference.image_png_base64: expected base64 PNG ({exc})"
        ) from exc
    image = cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.dtype != np.uint8 or image.shape != IMAGE_SHAPE:
        got = "not a PNG" if image is None else f"{image.dtype} {image.shape}"
        raise ModelError(
            f"{where}: reference.image_png_base64: expected an 8-bit grey {IMAGE_WIDTH_PX}x"
            f"{IMAGE_HEIGHT_PX} PNG, got {got}"
        )
    output = data.get("output_body_flu_mps")
    if (
        not isinstance(output, Sequence)
        or len(output) != 3
        or not all(isinstance(v, int | float) and math.isfinite(v) for v in output)
    ):
        raise ModelError(
            f"{where}: reference.output_body_flu_mps: expected 3 finite numbers, got {output!r}"
        )
    tolerance = data.get("tolerance_mps", DEFAULT_TOLERANCE_MPS)
    if (
        not isinstance(tolerance, int | float)
        or isinstance(tolerance, bool)
        or not 0.0 < tolerance <= MAX_TOLERANCE_MPS
    ):
        raise ModelError(
            f"{where}: reference.tolerance_mps: expected a number in (0, {MAX_TOLERANCE_MPS:g}] "
            f"m/s, got {tolerance!r}"
        )
    made_with = data.get("made_with")
    return Reference(
        image_u8=np.ascontiguousarray(image),
        output_body_flu_mps=(float(output[0]), float(output[1]), float(output[2])),
        tolerance_mps=float(tolerance),
        made_with=made_with if isinstance(made_with, Mapping) else None,
    )


def reference_scene() -> NDArray[np.uint8]:
    """The default reference image (64, 384) uint8: sky, ground, three dark drones, some texture.

    Deterministic and about what the cameras see (not noise, which drives the shipped model to
    ~12 m/s); it is stored as a PNG with the reference, so this function may change freely.
    """
    image = np.full(IMAGE_SHAPE, 215, dtype=np.int16)  # sky
    image[IMAGE_HEIGHT_PX // 2 :] = 140  # ground
    image[28:36, 28:36] = 40  # a drone ahead (front tile, columns 0-63)
    image[30:34, 220:224] = 40  # a smaller one, further away (left tile, 192-255)
    image[26:38, 100:112] = 55  # a close one to the right (right tile, 64-127)
    texture = np.random.default_rng(20240).integers(-12, 13, IMAGE_SHAPE)
    scene: NDArray[np.uint8] = np.clip(image + texture, 0, 255).astype(np.uint8)
    return scene
