"""The report's Grad-CAM strip: what one agent saw early in a CNN flight and where the CNN looked.

The image is rendered again from the flight's log (the pose and attitude of every agent at that
control step), which is exactly the image the CNN was given at that step: the rollout renders the
logged poses, and rendering is deterministic. The saliency comes from `learning.gradcam`, run on
the eager network whose weights the policy file records (`learning.export.load_eager_model`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES
from companion.errors import ModelError
from sim_harness.experiments.runner import RunRecord, SuiteResult
from sim_harness.learning.checkpoint import CheckpointError
from sim_harness.learning.ensemble import load_eager_policy
from sim_harness.learning.gradcam import TARGETS, grad_cam, save_gradcam_png
from sim_harness.sim.render import PyBulletRenderer
from sim_harness.sim.rollout import FlightLog
from sim_harness.sim.world import World

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
    first: NDArray[np.uint8] = image[0]
    return first


def pick_flight(result: SuiteResult) -> RunRecord | None:
    """The CNN's common-goal flight of the first seed, else its first flight; None without one."""
    cnn = [r for r in result.runs if r.controller == "cnn"]
    common = [r for r in cnn if r.experiment == "common"]
    chosen = common or cnn
    return chosen[0] if chosen else None


def saliency(
    model_path: Path, image: NDArray[np.uint8]
) -> tuple[dict[str, NDArray[np.float32]], NDArray[np.float32]] | None:
    """Grad-CAM heatmaps (64, 384) per target ("speed", "x", "y", "z") of the policy file's eager
    network for one image, and its predicted body-FLU velocity (3,); None when the policy file
    carries no eager weights (Grad-CAM needs them)."""
    try:
        model, _ = load_eager_policy(model_path)
    except (ModelError, CheckpointError) as exc:
        log.warning("no Grad-CAM strip: %s", exc)
        return None
    heatmaps: dict[str, NDArray[np.float32]] = {}
    vel = np.zeros(3, dtype=np.float32)
    for target in TARGETS:
        cam = grad_cam(model, image, target)
        heatmaps["|v|" if target == "speed" else f"|v_{target}|"] = cam.heatmap[0]
        vel = cam.vel_body_flu[0]
    return heatmaps, vel


def save_gradcam_strip(result: SuiteResult, path: Path, time_s: float) -> GradcamStrip | None:
    """Agent 0's view at `time_s` of the CNN's first common-goal flight, with its Grad-CAM."""
    record = pick_flight(result)
    if record is None:
        return None
    flight = record.log
    step = min(round(time_s / flight.rates.control_dt_s), flight.n_steps - 1)
    image = capture_image(flight, 0, step)
    found = saliency(result.config.model_path, image)
    if found is None:
        return None
    heatmaps, vel = found
    t = step * flight.rates.control_dt_s
    title = (
        f"{record.experiment}, seed {record.seed}, agent 0, t = {t:.1f} s: CNN output (body FLU) "
        f"[{vel[0]:+.2f}, {vel[1]:+.2f}, {vel[2]:+.2f}] m/s"
    )
    save_gradcam_png(image, heatmaps, path, title)
    caption = (
        f"Agent 0's six views ({', '.join(FACE_NAMES)}) at t = {t:.1f} s of the CNN's "
        f"{record.experiment} flight, seed {record.seed}, rendered again from the logged poses "
        "(the image the CNN was given); below, the Grad-CAM at block 2's strided convolution "
        "(a 4x24 map, bilinearly upsampled; red: most influence) for the predicted speed |v| and "
        "for each body component (x forward, y left, z up)."
    )
    return GradcamStrip(path, caption)
