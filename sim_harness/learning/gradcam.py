"""Grad-CAM saliency of the policy network (Selvaraju et al. 2017), as in the paper's Fig. 9.

Layer: block 2's strided 3x3 conv, a 64-channel 4 x 24 map for a 64x384 image (the paper's
"penultimate strided convolutional layer"). For a scalar target `s`:

    alpha_k = mean over the 4x24 cells of d s / d A_k          (one weight per channel k)
    cam     = ReLU(sum_k alpha_k A_k)                          (4 x 24)
    heatmap = bilinear upsampling of cam to 64 x 384 (cell centres on the 16-px stride grid),
              divided by its maximum (all zeros when the map is zero)

Targets (the output is a vector, so the scalar must be chosen):

- "speed" (default): the predicted velocity's magnitude |v|. Its gradient is the projection of
  dv onto the predicted direction, so the map shows where the evidence lies that pushes the
  command the way it points (how fast and where the drone wants to go).
- "x", "y", "z": the magnitude of one body FLU component, |v_k| (forward, left, up): the evidence
  for that component's predicted value, whatever its sign.

`grad_cam` works on raw uint8 images (a dataset sample or any stitched 64x384 frame).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import ArrayLike, NDArray

from companion.camera.layout import FACE_NAMES, FACE_SIZE_PX, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ConfigError
from sim_harness.learning.model import DroNet

TARGETS = ("speed", "x", "y", "z")


@dataclass(frozen=True)
class GradCamResult:
    """Saliency of a batch: `heatmap` (B, 64, 384) in [0, 1], `cam` (B, 4, 24) before upsampling
    and normalization, `vel_body_flu` (B, 3) the prediction in m/s, `target` the scalar used."""

    heatmap: NDArray[np.float32]
    cam: NDArray[np.float32]
    vel_body_flu: NDArray[np.float32]
    target: str


def _scalar_target(vel: torch.Tensor, target: str) -> torch.Tensor:
    """Sum over the batch of the chosen scalar (the samples do not interact in eval mode)."""
    scalar: torch.Tensor
    if target == "speed":
        direction = (vel / vel.norm(dim=1, keepdim=True).clamp_min(1e-9)).detach()
        scalar = (vel * direction).sum()
    else:
        k = "xyz".index(target)
        scalar = (vel[:, k] * torch.sign(vel[:, k]).detach()).sum()
    return scalar


def _cam(network: DroNet, activation: torch.Tensor, grads: torch.Tensor) -> torch.Tensor:
    """ReLU(sum_k alpha_k A_k) of one network's layer, laid out as the strip: (B, 1, 4, 24)."""
    activation = network.as_strip(activation)
    grads = network.as_strip(grads)
    alpha = grads.mean(dim=(2, 3), keepdim=True)  # (B, C, 1, 1)
    return torch.relu((alpha * activation).sum(dim=1, keepdim=True))


def _networks(model: torch.nn.Module) -> list[DroNet]:
    """The networks whose Grad-CAM layer is hooked: the model, or an ensemble's members."""
    if isinstance(model, DroNet):
        return [model]
    members = getattr(model, "members", None)
    if isinstance(members, torch.nn.ModuleList) and all(isinstance(m, DroNet) for m in members):
        return [m for m in members if isinstance(m, DroNet)]
    raise TypeError(f"Grad-CAM explains a DroNet or an ensemble of them, not {type(model)}")


def grad_cam(model: torch.nn.Module, images_u8: ArrayLike, target: str = "speed") -> GradCamResult:
    """Grad-CAM of `model` for uint8 images (64, 384) or (B, 64, 384). See the module docstring.

    `model` is a `DroNet` or an ensemble of them (`learning.ensemble.EnsembleNet`): there the
    scalar is the ensemble's answer's, each member's map is computed at its own layer (its share
    is inside the gradient) and the maps are added before the upsampling and normalization.
    The model is put in eval mode; its parameters are left untouched (no gradients accumulate).
    """
    if target not in TARGETS:
        raise ConfigError(f"target: {target!r} is not one of {', '.join(TARGETS)}")
    images = np.asarray(images_u8)
    single = images.ndim == 2
    batch = images[None] if single else images
    if batch.dtype != np.uint8 or batch.shape[1:] != (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX):
        raise ValueError(
            f"expected uint8 images (B, {IMAGE_HEIGHT_PX}, {IMAGE_WIDTH_PX}), got "
            f"{images.dtype} {images.shape}"
        )
    model.eval()
    networks = _networks(model)
    device = next(model.parameters()).device
    captured: dict[int, torch.Tensor] = {}

    def keeper(k: int) -> Callable[[torch.nn.Module, object, torch.Tensor], None]:
        def keep(_module: torch.nn.Module, _inputs: object, out: torch.Tensor) -> None:
            if not out.requires_grad:  # a model whose parameters were frozen
                out.requires_grad_(True)
            captured[k] = out

        return keep

    hooks = [n.gradcam_layer.register_forward_hook(keeper(k)) for k, n in enumerate(networks)]
    try:
        with torch.enable_grad():
            vel = model(torch.from_numpy(np.array(batch)).to(device))  # a writable copy
            layers = [captured[k] for k in range(len(networks))]
            grads = torch.autograd.grad(_scalar_target(vel, target), layers)
    finally:
        for hook in hooks:
            hook.remove()
    cam = sum(
        (_cam(n, a.detach(), g) for n, a, g in zip(networks, layers, grads, strict=True)),
        torch.zeros(()),
    )
    up = F.interpolate(
        cam, size=(IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX), mode="bilinear", align_corners=False
    )
    peak = up.amax(dim=(2, 3), keepdim=True)
    heat = torch.where(peak > 0, up / peak.clamp_min(1e-30), torch.zeros_like(up))
    return GradCamResult(
        heatmap=heat[:, 0].cpu().numpy().astype(np.float32),
        cam=cam[:, 0].cpu().numpy().astype(np.float32),
        vel_body_flu=vel.detach().cpu().numpy().astype(np.float32),
        target=target,
    )


def blend(
    image_u8: NDArray[np.uint8], heatmap: NDArray[np.float32], alpha: float = 0.5
) -> NDArray[np.uint8]:
    """RGB uint8 (64, 384, 3): the grayscale image with the heatmap's jet colours over it
    (red = most influence, blue = least), `alpha` the heatmap's weight."""
    gray = cv2.cvtColor(np.asarray(image_u8, dtype=np.uint8), cv2.COLOR_GRAY2RGB)
    heat = np.clip(np.rint(np.asarray(heatmap) * 255.0), 0, 255).astype(np.uint8)
    colours = cv2.cvtColor(cv2.applyColorMap(heat, cv2.COLORMAP_JET), cv2.COLOR_BGR2RGB)
    return np.asarray(cv2.addWeighted(colours, alpha, gray, 1.0 - alpha, 0.0), dtype=np.uint8)


def save_gradcam_png(
    image_u8: NDArray[np.uint8],
    heatmaps: Mapping[str, NDArray[np.float32]],
    path: Path,
    title: str = "",
) -> Path:
    """A PNG: the image, then one row per heatmap (64, 384) blended over it (labelled with the
    mapping's key), faces named along the bottom; `title` (e.g. the velocities) above."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = 1 + len(heatmaps)
    fig, axes = plt.subplots(rows, 1, figsize=(10, 1.6 * rows + 0.4), dpi=100, squeeze=False)
    axes[0, 0].imshow(image_u8, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    axes[0, 0].set_ylabel("image", fontsize=8)
    for ax, (label, heat) in zip(axes[1:, 0], heatmaps.items(), strict=True):
        ax.imshow(blend(image_u8, heat), interpolation="nearest")
        ax.set_ylabel(label, fontsize=8)
    for ax in axes[:, 0]:
        ax.set_xticks([FACE_SIZE_PX * (k + 0.5) for k in range(len(FACE_NAMES))], FACE_NAMES)
        ax.set_yticks([])
        for k in range(1, len(FACE_NAMES)):
            ax.axvline(FACE_SIZE_PX * k - 0.5, color="w", lw=0.6)
    if title:
        axes[0, 0].set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path
