"""Choosing a renderer by name: one option definition for every command that renders.

- `pybullet`: `sim_harness.sim.render.PyBulletRenderer` (TinyRenderer, one call per face).
- `raycast`: `sim_harness.sim.raycast.RaycastRenderer` (all agents' faces in one numpy pass; the
  same images to within a pixel or two per drone: benchmarks/render_fidelity.py).
- `raycast-aa`: the same, each pixel the mean of a 4 x 4 grid of drone samples (area-averaged, as
  a camera sensor integrates a pixel; far drones no longer vanish between the rays).

Datasets record the renderer that made their images (manifest `renderer`), exported models copy it
into their metadata (`dataset.renderer`). Commands that fly a CNN (`experiments`, `dataset
aggregate`, `hil`) draw with that same renderer unless told otherwise (`renderer_of_model`); a CNN
flight with another renderer logs a warning.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from sim_harness.errors import ConfigError
from sim_harness.sim.render import Renderer
from sim_harness.sim.scene import SceneSpec

log = logging.getLogger(__name__)

RENDERERS: tuple[str, ...] = ("pybullet", "raycast", "raycast-aa")
AA_SUPERSAMPLE = 4  # raycast-aa: drone samples per pixel side
DEFAULT_RENDERER = "pybullet"


def require_renderer(name: str, field: str = "renderer") -> str:
    if name not in RENDERERS:
        choices = ", ".join(RENDERERS)
        raise ConfigError(f"{field}: unknown renderer {name!r}; choose one of {choices}")
    return name


def make_renderer(name: str = DEFAULT_RENDERER, scene: SceneSpec | None = None) -> Renderer:
    """A new renderer of that name, drawing `scene` (default `SceneSpec()`) behind the drones
    (pybullet's is imported only when asked for)."""
    require_renderer(name)
    if name in ("raycast", "raycast-aa"):
        from sim_harness.sim.raycast import RaycastRenderer

        supersample = AA_SUPERSAMPLE if name == "raycast-aa" else 1
        return RaycastRenderer(supersample=supersample, scene=scene)
    from sim_harness.sim.render import PyBulletRenderer

    return PyBulletRenderer(scene=scene)


def add_renderer_option(parser: argparse.ArgumentParser, follows_model: bool = False) -> None:
    """`--renderer NAME`, the same on every command that renders. `follows_model`: a command
    that flies a CNN; its default (None) is the renderer the model was trained on
    (`renderer_of_model`)."""
    default = "the one the model's training images were drawn with" if follows_model else None
    parser.add_argument(
        "--renderer",
        default=None if follows_model else DEFAULT_RENDERER,
        choices=RENDERERS,
        help=f"what draws the camera images (default {default or DEFAULT_RENDERER}); raycast "
        "renders all drones' views in one batched pass, several times faster; raycast-aa "
        "averages 4 x 4 drone samples per pixel (far drones stay visible)",
    )


def model_renderer(metadata: Mapping[str, Any]) -> str:
    """The renderer that made a model's training images (models made before it was recorded:
    pybullet, the only one there was)."""
    dataset = metadata.get("dataset") or {}
    return str(dataset.get("renderer", DEFAULT_RENDERER))


def renderer_of_model(model_path: str | Path) -> str:
    """The renderer of a policy file's training images, read from its sidecar `NAME.json`
    (no torch load); pybullet when the sidecar is missing or records none (loading the model
    refuses a file without its sidecar later, with the reason)."""
    sidecar = Path(model_path).with_suffix(".json")  # companion.model_file.sidecar_path's rule;
    try:  # that module imports torch, which the CLIs load only once they fly
        metadata = json.loads(sidecar.read_text())["metadata"]
        return model_renderer(metadata)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return DEFAULT_RENDERER


def warn_if_trained_elsewhere(metadata: Mapping[str, Any], renderer: str) -> bool:
    """Log one warning when the model was trained on another renderer's images; True if so."""
    trained = model_renderer(metadata)
    if trained == renderer:
        return False
    log.warning(
        "the model was trained on %s images but flies with the %s renderer", trained, renderer
    )
    return True
