"""What the cameras see besides the drones: a textured ground and a sky, drawn per pixel.

pybullet's TinyRenderer draws the drones; the environment is drawn analytically from the same
camera model and composited behind them wherever TinyRenderer's depth buffer is empty. Texturing a
ground plane and a sky dome through TinyRenderer cost 1.4 ms per 64x64 face (2.4 ms against 1.0 ms
for the drones alone, measured with 9 drones) and aliased badly near the horizon; the analytic
environment costs a fraction of that for all six faces at once and fades distant texture smoothly.

- Ground: the plane z = 0 with a procedural, seeded gray texture (smooth patches within 100-210,
  repeating every 15 m), like a field seen from a few metres. Its contrast fades with distance
  towards the mean gray (aerial perspective), which also removes the far-field aliasing.
- Sky: bright at the horizon and slightly darker towards the zenith, like an overcast sky.

The drones are darker than both (sim_harness.sim.quad_body), so they stand out everywhere.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_SIZE_PX, FACES, FOV_DEG
from companion.validation import require_int_range
from sim_harness.sim.pybullet_import import pb

_MAX_GROUND_M = 1000.0


@dataclass(frozen=True)
class SceneSpec:
    """Scene parameters (metres, gray levels 0-255)."""

    ground_tile_m: float = 15.0  # the ground texture repeats with this period
    ground_texture_px: int = 256
    ground_seed: int = 7
    ground_mean: float = 155.0
    ground_std: float = 24.0
    ground_fade_m: float = 45.0  # texture contrast falls by 1/e over this distance
    sky_horizon_gray: float = 235.0
    sky_zenith_gray: float = 200.0

    def as_dict(self) -> dict[str, float | int]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


#: What `random_scene` draws from (uniformly): grounds of other patterns, brightness, contrast and
#: patch size, hazier or clearer air, brighter or duller skies. The ground stays within gray 100-210
#: (`ground_texture` clips it), so the dark drones stand out against every draw, as by default.
SCENE_RANGES: dict[str, tuple[float, float]] = {
    "ground_tile_m": (8.0, 25.0),
    "ground_mean": (125.0, 185.0),
    "ground_std": (8.0, 36.0),
    "ground_fade_m": (30.0, 70.0),
    "sky_horizon_gray": (215.0, 245.0),
    "sky_zenith_drop": (10.0, 50.0),  # the zenith this much darker than the horizon
}


def unseen_scene(seed: int | None) -> SceneSpec | None:
    """Random scene number `seed` (>= 0) for flying over a ground no dataset used; None: default."""
    if seed is None:
        return None
    require_int_range("ground", seed, 0)
    return random_scene(np.random.default_rng([seed, 0x6E64]))


def random_scene(rng: np.random.Generator) -> SceneSpec:
    """A scene drawn from `SCENE_RANGES`, its ground texture from a fresh seed.

    For training images against many backgrounds (`swarm-sim dataset rerender --vary-scene`): a
    network trained on one ground texture learns that texture, and its answers drift when the
    ground changes (benchmarks/ground_robustness.py).
    """
    u = {k: float(rng.uniform(*r)) for k, r in SCENE_RANGES.items()}
    return SceneSpec(
        ground_tile_m=u["ground_tile_m"],
        ground_seed=int(rng.integers(0, 2**31 - 1)),
        ground_mean=u["ground_mean"],
        ground_std=u["ground_std"],
        ground_fade_m=u["ground_fade_m"],
        sky_horizon_gray=u["sky_horizon_gray"],
        sky_zenith_gray=u["sky_horizon_gray"] - u["sky_zenith_drop"],
    )


def ground_texture(spec: SceneSpec) -> NDArray[np.uint8]:
    """Seeded, seamlessly tiling gray noise (sum of smooth octaves), uint8 (size, size)."""
    size = spec.ground_texture_px
    rng = np.random.default_rng(spec.ground_seed)
    img = np.zeros((size, size))
    for cells, amplitude in ((4, 1.0), (8, 0.6), (16, 0.35), (32, 0.2)):
        noise = np.tile(rng.standard_normal((cells, cells)), (3, 3))
        big = cv2.resize(noise, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        img += amplitude * big[size : 2 * size, size : 2 * size]
    img = (img - img.mean()) / img.std()
    return np.clip(spec.ground_mean + spec.ground_std * img, 100, 210).astype(np.uint8)


def pixel_rays_body_flu() -> NDArray[np.float64]:
    """Ray through each pixel centre of each face, body frame FLU, unit length: (6, 64, 64, 3).

    Same pinhole model as the renderer: square image, `FOV_DEG` vertically and horizontally, row 0
    at the top, column 0 at the left (companion.camera.layout).
    """
    half = np.tan(np.deg2rad(FOV_DEG) / 2)
    centres = (np.arange(FACE_SIZE_PX) + 0.5) / FACE_SIZE_PX * 2.0 - 1.0
    x_ndc = centres[None, :]  # right
    y_ndc = -centres[:, None]  # up
    rays = np.empty((len(FACES), FACE_SIZE_PX, FACE_SIZE_PX, 3))
    for f, face in enumerate(FACES):
        axis, up, right = (
            np.array(v) for v in (face.axis_body_flu, face.up_body_flu, face.right_body_flu)
        )
        rays[f] = axis + (x_ndc * half)[..., None] * right + (y_ndc * half)[..., None] * up
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


@dataclass
class Environment:
    """Shades camera rays that hit no drone: ground below the horizon, sky above."""

    spec: SceneSpec = field(default_factory=SceneSpec)

    def __post_init__(self) -> None:
        self._texture = ground_texture(self.spec).astype(np.float32)
        self._rays_body = pixel_rays_body_flu().reshape(-1, 3).astype(np.float32)  # (6*64*64, 3)

    def shade(
        self, eye_world_enu: NDArray[np.float64], rot_world_body: NDArray[np.float64]
    ) -> NDArray[np.float32]:
        """Gray level of every pixel for K observers: (K, 6, 64, 64) float32.

        `eye_world_enu` (K, 6, 3): camera centres; `rot_world_body` (K, 3, 3): body FLU -> ENU.
        """
        s = self.spec
        k = len(eye_world_enu)
        n_px = FACE_SIZE_PX * FACE_SIZE_PX
        rot_t = np.asarray(rot_world_body, dtype=np.float32).transpose(0, 2, 1)
        rays = (self._rays_body @ rot_t).reshape(k, len(FACES), n_px, 3)  # world directions
        eye = np.asarray(eye_world_enu, dtype=np.float32)[:, :, None, :]
        dz = rays[..., 2]
        below = dz < -1e-6
        # Distance along the (unit) ray to the ground plane z = 0; 0 where the ray goes up. Capped
        # at _MAX_GROUND_M, where the faded texture is flat anyway, so that texture coordinates
        # stay within the +-32767 px that cv2.remap handles (it wraps them with BORDER_WRAP).
        t = np.divide(eye[..., 2], -dz, out=np.zeros_like(dz), where=below)
        np.minimum(t, np.float32(_MAX_GROUND_M), out=t)
        scale = np.float32(s.ground_texture_px / s.ground_tile_m)
        map_x = (eye[..., 0] + t * rays[..., 0]) * scale
        map_y = (eye[..., 1] + t * rays[..., 1]) * scale
        # cv2.remap takes maps of fewer than 32767 rows: 64 observers (24,576 rows) at a time.
        rows_x, rows_y = map_x.reshape(-1, FACE_SIZE_PX), map_y.reshape(-1, FACE_SIZE_PX)
        chunk = 64 * len(FACES) * FACE_SIZE_PX
        texel = np.concatenate(
            [
                cv2.remap(
                    self._texture,
                    rows_x[i : i + chunk],
                    rows_y[i : i + chunk],
                    interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP,
                )
                for i in range(0, len(rows_x), chunk)
            ]
        ).reshape(dz.shape)
        fade = np.exp(t * np.float32(-1.0 / s.ground_fade_m))
        ground = np.float32(s.ground_mean) + (texel - np.float32(s.ground_mean)) * fade
        # Sky: linear in sin(elevation), from the horizon gray to the zenith gray.
        sky = np.float32(s.sky_horizon_gray) + np.float32(
            s.sky_zenith_gray - s.sky_horizon_gray
        ) * np.clip(dz, 0.0, 1.0)
        out = np.where(below, ground, sky)
        return out.reshape(k, len(FACES), FACE_SIZE_PX, FACE_SIZE_PX)


def load_texture(client_id: int, image: NDArray[np.uint8]) -> int:
    """Load an RGB (H, W, 3) or gray (H, W) uint8 image as a texture of pybullet client `client_id`.

    pybullet loads textures only from files: the image goes through a temporary PNG.
    """
    rgb = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    with tempfile.TemporaryDirectory(prefix="swarm-tex-") as tmp:
        path = Path(tmp) / "texture.png"
        cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))
        return int(pb.loadTexture(str(path), physicsClientId=client_id))
