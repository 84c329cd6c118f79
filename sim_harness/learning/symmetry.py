"""The camera rig's symmetries: the same scene seen by a drone turned or mirrored, and its label.

The six cube-map cameras (`companion.camera.layout`) are symmetric under the eight rotations and
reflections of a square about the body z axis (the dihedral group D4). A drone that yaws 90 deg to
the left at the same place sees exactly what the rig saw before, re-ordered: its new front tile is
the old left tile, right <- front, back <- right, left <- back, and the up and down tiles turn a
quarter in their plane (up counter-clockwise, down clockwise). Mirroring the world in the body x-z
plane flips every tile left-right and swaps the right and left tiles. The teacher's command is a
function of the neighbours' positions in the body frame, so it transforms with the view: a yaw of
90 deg to the left maps body (x, y, z) to (y, -x, z); the mirror maps it to (x, -y, z).

Two uses, both inside the paper's method (each drone's command still comes from its own image):

- **augmentation** (`augment`): each training sample is shown in a random one of the eight
  views with its transformed label, which stays exactly valid; the data holds every heading
  the flock can have relative to its neighbours, not only the ones the dataset flew.
- **symmetrized policy** (`SymmetricPolicy`): the exported graph runs the network on all views of
  the image in one batch and averages the outputs mapped back to the original body frame. The
  result is exactly equivariant: a constant bias of the network in the body frame (e.g. a small
  backward pull, which stalls a tug of war between two groups) averages out to zero.

A view is `(turns, mirrored)`: first mirror (when `mirrored`), then `turns` quarter turns to the
left. Exact for the rig, the sky and the ground (rendering an agent yawed by 90 deg equals the
re-ordered image up to the renderer's sub-pixel sample offset: tests/sim_harness/learning).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from sim_harness.learning.symmetry_views import (
    GROUPS,
    View,
    label_matrix,
    pixel_source,
    require_group,
    view_image,
)

__all__ = [
    "GROUPS",
    "SymmetricPolicy",
    "View",
    "augment",
    "augment_with_views",
    "label_matrix",
    "require_group",
    "view_image",
    "view_tables",
]


def view_tables(views: tuple[View, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """(pixel sources (G, 64*384) int64, label matrices (G, 3, 3) float32) of `views`."""
    sources = torch.from_numpy(np.stack([pixel_source(v) for v in views]))
    labels = torch.from_numpy(np.stack([label_matrix(v) for v in views]).astype(np.float32))
    return sources, labels


def augment(
    images_u8: torch.Tensor, targets: torch.Tensor, generator: torch.Generator, group: str = "d4"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Each sample of a batch in a random view of `group`, with its label transformed to match.

    `images_u8` (B, 64, 384), `targets` (B, 3) body FLU; returns new tensors (same devices).
    """
    images, labels, _ = augment_with_views(images_u8, targets, generator, group)
    return images, labels


def augment_with_views(
    images_u8: torch.Tensor, targets: torch.Tensor, generator: torch.Generator, group: str = "d4"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """`augment`, also returning each sample's label matrix L (B, 3, 3): label = L @ target.

    L is orthogonal: L^T maps a vector of the view's frame back to the recorded body frame.
    """
    views = require_group(group)
    if len(views) == 1:
        eye = torch.eye(3, dtype=targets.dtype, device=targets.device)
        return images_u8, targets, eye.expand(targets.shape[0], 3, 3)
    sources, labels = view_tables(views)
    chosen = torch.randint(0, len(views), (images_u8.shape[0],), generator=generator)
    flat = images_u8.reshape(images_u8.shape[0], -1)
    index = sources[chosen].to(flat.device)
    viewed = torch.gather(flat, 1, index).reshape(images_u8.shape)
    matrices = labels[chosen].to(targets.device, targets.dtype)
    return viewed, torch.bmm(matrices, targets.unsqueeze(-1)).squeeze(-1), matrices


class SymmetricPolicy(nn.Module):
    """`net` averaged over the views of a group, each output mapped back to the input's frame.

    uint8 (B, 64, 384) in, (B, 3) out, like `net`; runs `net` once on a batch of B x G images.
    """

    def __init__(self, net: nn.Module, group: str = "d4") -> None:
        super().__init__()
        views = require_group(group)
        sources, labels = view_tables(views)
        self.net = net
        self.group = group
        self.n_views = len(views)
        self.register_buffer("sources", sources, persistent=False)
        # Row g maps a view-frame output back: L_g^T (orthogonal), applied as v @ L_g.
        self.register_buffer("back", labels, persistent=False)

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        batch = images_u8.shape[0]
        flat = images_u8.reshape(batch, -1)
        shape = (batch * self.n_views, *images_u8.shape[1:])
        views = flat[:, self.sources.reshape(-1)].reshape(shape)
        out = self.net(views).reshape(batch, self.n_views, 1, 3)
        back: torch.Tensor = torch.matmul(out, self.back).reshape(batch, self.n_views, 3)
        return back.mean(dim=1)
