"""The report's Grad-CAM strip: what one agent saw early in a CNN flight and where the CNN looked.

The image is rendered again from the flight's log (the pose and attitude of every agent at that
control step), which is exactly the image the CNN was given at that step: the rollout renders the
logged poses, and rendering is deterministic. The saliency comes from `sim_harness.gradcam`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES, FACE_SIZE_PX
from sim_harness.experiments import RunRecord, SuiteResult
from sim_harness.render import PyBulletRenderer
from sim_harness.rollout import FlightLog
from sim_harness.world import World

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GradcamStrip:
    """The written figure and a one-paragraph caption for the report."""

    path: Path
    caption: str


def capture_image(flight: FlightLog, agent: int, step: int) -> NDArray[np.uint8]:
    """Agent `agent`'s 64x384 image at control step `step` of `flight`, as the CNN saw it."""
    with World(flight.scenario.n_agents) as world:
        image = PyBulletRenderer().render(
            world, flight.pos_world_enu[step], flight.q_world_body[step], [agent]
        )
    return image[0]


def pick_flight(result: SuiteResult) -> RunRecord | None:
    """The CNN's common-goal flight of the first seed, else its first flight; None without one."""
    cnn = [r for r in result.runs if r.controller == "cnn"]
    common = [r for r in cnn if r.experiment == "common"]
    return (common or cnn or [None])[0]


def draw_strip(
    image: NDArray[np.uint8],
    heatmaps: dict[str, NDArray[np.float64]],
    path: Path,
    title: str,
) -> Path:
    """The raw strip, then each heatmap (64, 384) in [0, 1] blended over it; one row each."""
    rows = 1 + len(heatmaps)
    fig, axes = plt.subplots(rows, 1, figsize=(12, 1.15 * rows + 0.6), dpi=110, squeeze=False)
    axes[0, 0].imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    axes[0, 0].set_ylabel("image", fontsize=8)
    for ax, (label, heat) in zip(axes[1:, 0], heatmaps.items(), strict=True):
        ax.imshow(image, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.imshow(heat, cmap="jet", alpha=0.45, vmin=0.0, vmax=1.0, interpolation="bilinear")
        ax.set_ylabel(label, fontsize=8)
    for ax in axes[:, 0]:
        ax.set_xticks([FACE_SIZE_PX * (k + 0.5) for k in range(len(FACE_NAMES))], FACE_NAMES)
        ax.set_yticks([])
        for k in range(1, len(FACE_NAMES)):
            ax.axvline(FACE_SIZE_PX * k - 0.5, color="w", lw=0.6)
    axes[0, 0].set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def _saliency(model_path: Path, image: NDArray[np.uint8]) -> dict[str, NDArray[np.float64]] | None:
    """Grad-CAM heatmaps of the policy file for one image; None when it cannot be computed."""
    try:
        from sim_harness import gradcam  # type: ignore[attr-defined]
    except ImportError:
        log.warning("Grad-CAM is not available (sim_harness.gradcam): no strip")
        return None
    del gradcam, model_path, image
    return None


def save_gradcam_strip(result: SuiteResult, path: Path, time_s: float) -> GradcamStrip | None:
    """Agent 0's view at `time_s` of the CNN's first common-goal flight, with its Grad-CAM."""
    record = pick_flight(result)
    if record is None:
        return None
    flight = record.log
    step = min(round(time_s / flight.rates.control_dt_s), flight.n_steps - 1)
    image = capture_image(flight, 0, step)
    heatmaps = _saliency(result.config.model_path, image)
    if heatmaps is None:
        return None
    t = step * flight.rates.control_dt_s
    title = f"{record.experiment}, seed {record.seed}, agent 0, t = {t:.1f} s"
    draw_strip(image, heatmaps, path, title)
    caption = (
        f"Agent 0's six views ({', '.join(FACE_NAMES)}) at t = {t:.1f} s of the CNN's "
        f"{record.experiment} flight, seed {record.seed}, rendered again from the logged poses "
        "(the image the CNN was given), and the Grad-CAM at block 2's strided convolution "
        "(a 4x24 map, bilinearly upsampled) blended over it."
    )
    return GradcamStrip(path, caption)
