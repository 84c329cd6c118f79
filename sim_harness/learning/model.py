"""The policy network: a DroNet-style ResNet-8 with one 3-output regression head.

Input: raw stitched camera images, uint8 tensor (B, 64, 384) in `companion.camera.layout` order.
Output: the body-frame (FLU) velocity command, float32 (B, 3) in m/s.

Layers (feature maps for a 64x384 input, channels x rows x columns):

    standardize  (x - pixel_mean) / pixel_std     1 x 64 x 384  (buffers, not trained)
    conv 5x5/2, 32 (padding 2)                    32 x 32 x 192
    max-pool 3x3/2 (no padding)                   32 x 15 x 95
    block1: 32 channels, stride 2                 32 x 8 x 48
    block2: 64 channels, stride 2                 64 x 4 x 24   <- Grad-CAM layer (strided conv)
    block3: 128 channels, stride 2                128 x 2 x 12
    BN, ReLU, flatten, dropout 0.5, linear 3072 -> 3

Each residual block uses DroNet's pre-activation order (Loquercio et al. 2018):
`BN-ReLU-conv3x3/2, BN-ReLU-conv3x3/1` on the main path, a 1x1 strided conv on the shortcut (fed
the block's raw input), and the sum of both. Weights are drawn from He's truncated normal (std
sqrt(2 / fan_in), cut at two standard deviations, rescaled so the cut keeps the variance, as
Keras' `he_normal`), biases are zero, batch norms start as the identity. On CPU the model runs in
channels_last memory layout, about twice as fast as contiguous NCHW here. 317,859 parameters.

Two departures from DroNet, both for the same measured reason: with the paper's initialization,
standardized inputs and SGD at lr 5e-3, the untrained network outputs about +-10 m/s and training
diverged to NaN within two steps (the 1x1 shortcuts, He-initialized, double the activation
variance at every block, so the features entering the head are large):

- `bn_out`: a batch norm on block 3's output before the final ReLU, as pre-activation ResNets end
  (He et al. 2016, "Identity mappings in deep residual networks"); 256 parameters.
- the head's weights start at zero (drawn, then zeroed), so the untrained policy commands 0 m/s.

Architectures (`ARCHS`, the training option `--arch`):

- `dronet`: the layers above over the 64x384 strip as one image; a conv at a tile's edge sees the
  next tile of the strip (the true neighbour between the four side faces, an unrelated one at the
  up and down tiles) or zeros.
- `cube`: the same layers and weights (identical state dicts, so either initializes the other),
  run on the six 64x64 faces as a batch, each spatial op padding every face with the cells of its
  true neighbours on the sphere (`CubePad`): a drone towards a cube corner, split over three
  faces, is seen whole by the convolutions instead of as three unrelated edge fragments. The
  max pool pads too (3x3/2 with padding 1), so every face stays 2^k cells wide: 32, 16, 8, 4,
  2; the head sees the same 128 x 2 x 12 features. About 1.9x the training time of `dronet` on CPU.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, cast

import torch
from torch import nn

from companion.camera.layout import FACE_SIZE_PX, FACES, FOV_DEG, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ConfigError
from companion.validation import require_positive, require_range

# std of a unit normal truncated to [-2, 2]; dividing by it keeps the target variance.
AXES = ("x", "y", "z")  # the policy's outputs: body-frame FLU velocity components
ARCHS = ("dronet", "cube")  # module docstring
_TRUNC_NORMAL_STD = 0.8796256610342398


class Standardize(nn.Module):
    """uint8 (B, H, W) -> float32 (B, 1, H, W), `(x - pixel_mean) / pixel_std`, channels_last."""

    pixel_mean: torch.Tensor
    pixel_std: torch.Tensor

    def __init__(self, pixel_mean: float, pixel_std: float) -> None:
        super().__init__()
        require_range("pixel_mean", pixel_mean, 0.0, 255.0)
        require_positive("pixel_std", pixel_std)
        self.register_buffer("pixel_mean", torch.tensor(float(pixel_mean)))
        self.register_buffer("pixel_std", torch.tensor(float(pixel_std)))

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = (images_u8.unsqueeze(1).float() - self.pixel_mean) / self.pixel_std
        return x.contiguous(memory_format=torch.channels_last)


class ResidualBlock(nn.Module):
    """DroNet's residual block: BN-ReLU-conv3x3/2, BN-ReLU-conv3x3/1, plus a 1x1/2 shortcut.

    `conv_strided` is the strided 3x3 conv; block 2's is the Grad-CAM layer.
    """

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.bn1 = nn.BatchNorm2d(in_channels)
        self.conv_strided = nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.conv = nn.Conv2d(out_channels, out_channels, 3, stride=1, padding=1)
        self.shortcut = nn.Conv2d(in_channels, out_channels, 1, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        main = self.conv_strided(torch.relu(self.bn1(x)))
        main = self.conv(torch.relu(self.bn2(main)))
        out: torch.Tensor = main + self.shortcut(x)
        return out


class DroNet(nn.Module):
    """ResNet-8 regression network, raw uint8 images in, body-frame FLU velocity (m/s) out.

    Args:
        pixel_mean: training split's mean pixel value (0..255), stored in the model.
        pixel_std: training split's pixel standard deviation (> 0), stored in the model.
        dropout: dropout probability before the linear head, in [0, 1).
    """

    arch = "dronet"

    def __init__(self, pixel_mean: float, pixel_std: float, dropout: float = 0.5) -> None:
        super().__init__()
        require_range("dropout", dropout, 0.0, 1.0, high_inclusive=False)
        self.standardize = Standardize(pixel_mean, pixel_std)
        self.conv1 = nn.Conv2d(1, 32, 5, stride=2, padding=2)
        self.pool = nn.MaxPool2d(3, stride=2)
        self.block1 = ResidualBlock(32, 32)
        self.block2 = ResidualBlock(32, 64)
        self.block3 = ResidualBlock(64, 128)
        self.bn_out = nn.BatchNorm2d(128)
        self.dropout = nn.Dropout(dropout)
        self.head = nn.Linear(128 * 2 * 12, 3)
        init_weights(self)
        nn.init.zeros_(self.head.weight)

    @property
    def gradcam_layer(self) -> nn.Conv2d:
        """Block 2's strided 3x3 conv: a 64 x 4 x 24 feature map for a 64x384 input."""
        return self.block2.conv_strided

    def as_strip(self, features: torch.Tensor) -> torch.Tensor:
        """A feature map of this network's layers laid out as the strip, (B, C, rows, columns)."""
        return features

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = self.pool(self.conv1(self.standardize(images_u8)))
        x = self.bn_out(self.block3(self.block2(self.block1(x))))
        x = torch.flatten(torch.relu(x), 1)
        vel_body_flu: torch.Tensor = self.head(self.dropout(x))
        return vel_body_flu


def cube_pad_index(size: int, pad: int) -> torch.Tensor:
    """Flat gather index padding each face of a (6, size, size) stack by `pad` cells.

    Cell (i, j) of face f, padded frame (rows top to bottom), looks along
    `axis + u right + v up` with u, v its centre's tangent-plane coordinates (the face spans
    +-tan(FOV / 2)); inside the face it is itself, outside it is the nearest cell of the face
    whose optical axis is closest to that direction (the faces overlap by FOV - 90 deg, so the
    neighbour's cell lies a little inside its edge). Returns int64 (6 (size + 2 pad)^2,).
    """
    half = math.tan(math.radians(FOV_DEG) / 2)
    frames = [
        tuple(
            torch.tensor(v, dtype=torch.float64)
            for v in (f.right_body_flu, f.up_body_flu, f.axis_body_flu)
        )
        for f in FACES
    ]
    axes = torch.stack([frame[2] for frame in frames])
    coords = ((torch.arange(-pad, size + pad, dtype=torch.float64) + 0.5) / size * 2 - 1) * half
    u, v = coords[None, :, None], coords.flip(0)[:, None, None]
    out = torch.empty(len(FACES), size + 2 * pad, size + 2 * pad, dtype=torch.int64)
    inner = torch.zeros(size + 2 * pad, size + 2 * pad, dtype=torch.bool)
    inner[pad : pad + size, pad : pad + size] = True
    for f, (right, up, axis) in enumerate(frames):
        rays = u * right + v * up + axis
        source = torch.where(inner, f, (rays @ axes.T).argmax(dim=-1))
        for g, (right_g, up_g, axis_g) in enumerate(frames):
            rays_g = rays[source == g]
            depth = rays_g @ axis_g
            col = ((rays_g @ right_g / depth / half + 1) * size / 2).floor().clamp(0, size - 1)
            row = ((1 - rays_g @ up_g / depth / half) * size / 2).floor().clamp(0, size - 1)
            out[f][source == g] = g * size * size + row.long() * size + col.long()
    return out.reshape(-1)


class CubePad(nn.Module):
    """(6B, C, S, S) faces (channels_last) -> (6B, C, S + 2 pad, S + 2 pad), each face padded with
    its neighbours' cells (`cube_pad_index`).

    Each face is copied into the middle of its padded frame and only the border cells are
    gathered; when training, `_CubePadGrad` returns the gradient the same way (the middle as is,
    the border added back onto the cells it came from), instead of autograd's full-size
    zero-fill and scatter of a whole-frame gather.
    """

    source: torch.Tensor
    target: torch.Tensor

    def __init__(self, size: int, pad: int) -> None:
        super().__init__()
        self.pad = pad
        padded = size + 2 * pad
        border = torch.ones(6, padded, padded, dtype=torch.bool)
        border[:, pad : pad + size, pad : pad + size] = False
        target = border.reshape(-1).nonzero().squeeze(1)
        # border cell k of the padded frames (flat over the six) copies face cell source[k]
        self.register_buffer("target", target, persistent=False)
        self.register_buffer("source", cube_pad_index(size, pad)[target], persistent=False)

    def forward(self, faces: torch.Tensor) -> torch.Tensor:
        if faces.requires_grad and torch.is_grad_enabled() and not torch.jit.is_tracing():
            out: torch.Tensor = _CubePadGrad.apply(faces, self.source, self.target, self.pad)
            return out
        return _cube_pad(faces, self.source, self.target, self.pad)


def _cube_pad(
    faces: torch.Tensor, source: torch.Tensor, target: torch.Tensor, pad: int
) -> torch.Tensor:
    """`CubePad`'s forward: the middle copied, the border gathered (channels_last out)."""
    stacked, channels, size, _ = faces.shape
    padded = size + 2 * pad
    cells = faces.permute(0, 2, 3, 1)  # (6B, S, S, C), a view when channels_last
    out = faces.new_empty(stacked, padded, padded, channels)
    out[:, pad : pad + size, pad : pad + size] = cells
    flat = cells.reshape(stacked // 6, 6 * size * size, channels)
    border = torch.index_select(flat, 1, source)
    out.view(stacked // 6, 6 * padded * padded, channels).index_copy_(1, target, border)
    return out.permute(0, 3, 1, 2)


class _CubePadGrad(torch.autograd.Function):
    """`_cube_pad` with its gradient computed in place of autograd's (see `CubePad`)."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, faces: torch.Tensor, source: torch.Tensor, target: torch.Tensor, pad: int
    ) -> torch.Tensor:
        ctx.save_for_backward(source, target)
        ctx.pad = pad
        return _cube_pad(faces, source, target, pad)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        source, target = ctx.saved_tensors
        pad = ctx.pad
        stacked, channels, padded, _ = grad.shape
        size = padded - 2 * pad
        cells = grad.permute(0, 2, 3, 1)  # (6B, P, P, C)
        out = cells[:, pad : pad + size, pad : pad + size].contiguous()
        border = torch.index_select(
            cells.reshape(stacked // 6, 6 * padded * padded, channels), 1, target
        )
        out.view(stacked // 6, 6 * size * size, channels).index_add_(1, source, border)
        return out.permute(0, 3, 1, 2), None, None, None


def strip_to_faces(x: torch.Tensor) -> torch.Tensor:
    """(B, C, S, 6S) strip -> (6B, C, S, S) faces in `FACE_NAMES` order, channels_last."""
    batch, channels, size, _ = x.shape
    faces = x.reshape(batch, channels, size, 6, size).permute(0, 3, 1, 2, 4)
    return faces.reshape(batch * 6, channels, size, size).contiguous(
        memory_format=torch.channels_last
    )


def faces_to_strip(x: torch.Tensor) -> torch.Tensor:
    """Inverse of `strip_to_faces`: (6B, C, S, S) -> (B, C, S, 6S)."""
    stacked, channels, size, _ = x.shape
    strip = x.reshape(stacked // 6, 6, channels, size, size).permute(0, 2, 3, 1, 4)
    return strip.reshape(stacked // 6, channels, size, 6 * size)


class CubeDroNet(DroNet):
    """`DroNet` on the cube map's faces with `CubePad` padding (module docstring, "Architectures").

    Same submodules and state-dict keys as `DroNet`; its convs pad 0 and a `CubePad` before each
    spatial op does the padding. `gradcam_layer`'s output is per face, (6B, 64, 4, 4).
    """

    arch = "cube"

    def __init__(self, pixel_mean: float, pixel_std: float, dropout: float = 0.5) -> None:
        super().__init__(pixel_mean, pixel_std, dropout)
        self.pad_conv1 = CubePad(FACE_SIZE_PX, 2)
        self.pad_pool = CubePad(FACE_SIZE_PX // 2, 1)
        size = FACE_SIZE_PX // 4  # a face after the pool
        pads = []
        for block in (self.block1, self.block2, self.block3):
            block.conv_strided.padding = (0, 0)
            block.conv.padding = (0, 0)
            pads.append(nn.ModuleList([CubePad(size, 1), CubePad(size // 2, 1)]))
            size //= 2  # the strided conv halves the face
        self.conv1.padding = (0, 0)
        self.pad_blocks = nn.ModuleList(pads)

    def as_strip(self, features: torch.Tensor) -> torch.Tensor:
        """Per-face features (6B, C, S, S) as the strip (B, C, S, 6S)."""
        return faces_to_strip(features)

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = self.conv1(self.pad_conv1(strip_to_faces(self.standardize(images_u8))))
        x = self.pool(self.pad_pool(x))
        for block, pads in zip(
            (self.block1, self.block2, self.block3), self.pad_blocks, strict=True
        ):
            main = block.conv_strided(pads[0](torch.relu(block.bn1(x))))
            main = block.conv(pads[1](torch.relu(block.bn2(main))))
            x = main + block.shortcut(x)
        x = faces_to_strip(self.bn_out(x))
        vel_body_flu: torch.Tensor = self.head(self.dropout(torch.flatten(torch.relu(x), 1)))
        return vel_body_flu


def require_arch(arch: str) -> str:
    """`arch` if one of `ARCHS`, else `ConfigError` naming the field and the choices."""
    if arch not in ARCHS:
        raise ConfigError(f"arch: unknown architecture {arch!r}; choose one of {', '.join(ARCHS)}")
    return arch


def init_weights(model: nn.Module) -> None:
    """He truncated-normal weights (fan in), zero biases, identity batch norms."""
    for module in model.modules():
        if isinstance(module, nn.Conv2d | nn.Linear):
            fan_in = module.weight[0].numel()
            std = math.sqrt(2.0 / fan_in) / _TRUNC_NORMAL_STD
            nn.init.trunc_normal_(module.weight, 0.0, std, -2.0 * std, 2.0 * std)
            if module.bias is not None:
                nn.init.zeros_(module.bias)
        elif isinstance(module, nn.BatchNorm2d):
            nn.init.ones_(module.weight)
            nn.init.zeros_(module.bias)


def build_model(
    pixel_mean: float,
    pixel_std: float,
    dropout: float = 0.5,
    device: str | torch.device = "cpu",
    arch: str = "dronet",
) -> DroNet:
    """A freshly initialized network of `arch` (`ARCHS`) on `device`, channels_last (seed torch
    first)."""
    network = CubeDroNet if require_arch(arch) == "cube" else DroNet
    return to_channels_last(network(pixel_mean, pixel_std, dropout), device)


def build_from_config(config: dict[str, Any], device: str | torch.device = "cpu") -> DroNet:
    """`build_model` from a recorded `model_config` (pixel_mean, pixel_std, dropout, arch; a
    config without "arch" predates the option: "dronet")."""
    return build_model(
        config["pixel_mean"],
        config["pixel_std"],
        config["dropout"],
        device=device,
        arch=config.get("arch", "dronet"),
    )


def to_channels_last(model: DroNet, device: str | torch.device = "cpu") -> DroNet:
    """`model` moved to `device` with its 4-D weights in channels_last layout (in place)."""
    moved = model.to(device=torch.device(device), memory_format=torch.channels_last)  # type: ignore[call-overload]
    return cast(DroNet, moved)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters (the standardization buffers are not parameters)."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def decayed_parameters(model: nn.Module) -> Iterable[tuple[str, torch.Tensor]]:
    """The conv and linear weights: the `w` of the paper's `(lambda / 2) ||w||^2` term."""
    for module_name, module in model.named_modules():
        if isinstance(module, nn.Conv2d | nn.Linear):
            yield f"{module_name}.weight", module.weight


def parameter_groups(model: nn.Module, weight_decay: float) -> list[dict[str, object]]:
    """Optimizer groups: conv/linear weights with `weight_decay`; biases and BN params without.

    Every trainable parameter lands in exactly one group.
    """
    decayed = dict(decayed_parameters(model))
    decayed_ids = {id(p) for p in decayed.values()}
    others = [p for p in model.parameters() if p.requires_grad and id(p) not in decayed_ids]
    return [
        {"params": list(decayed.values()), "weight_decay": weight_decay, "name": "weights"},
        {"params": others, "weight_decay": 0.0, "name": "biases_and_norms"},
    ]


def example_input(batch: int = 1) -> torch.Tensor:
    """A zero uint8 batch of the model's input shape, (batch, 64, 384)."""
    return torch.zeros(batch, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX, dtype=torch.uint8)
