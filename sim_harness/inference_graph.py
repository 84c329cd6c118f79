"""The network rewritten for batch-small CPU inference: the graph the export traces.

Same function as `DroNet` (outputs agree to float rounding; the export checks 1e-4 and the
tests 1e-5), different operators where single-thread, batch-1 CPU inference is measurably faster
(`benchmarks/cnn_latency.py`, figures in docs/BENCHMARKS.md):

- **max pool 3x3/2** as a max over three row slices, then over three column slices, on the
  channels_last tensor: about 70 us instead of about 150-260 us for `max_pool2d`, which computes
  indices it then drops. Exact (a max is a max).
- **pre-activation batch norms** (each block's `bn1`, the final `bn_out`) as one fused
  `addcmul(shift, x, scale)` with the running statistics folded in. `torch.jit.freeze` folds only
  a batch norm that directly follows a conv (each block's `bn2`), so these stayed `batch_norm`.
- **1x1 stride-2 shortcuts** through `aten::thnn_conv2d` (im2col + GEMM): `conv2d` sends block 1's
  to oneDNN (input above 20,480 values), about 2x slower for a 1x1 kernel at batch 1.

Everything else (standardization, the 5x5 and 3x3 convs, the head) is the eager module's own
code. Training, evaluation and Grad-CAM keep using `DroNet`; only the exported file runs this.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from sim_harness.model import DroNet, ResidualBlock, example_input, to_channels_last


class ScaleShift(nn.Module):
    """An eval-mode `BatchNorm2d` folded to `x * scale + shift` (per channel)."""

    def __init__(self, bn: nn.BatchNorm2d) -> None:
        super().__init__()
        assert bn.running_var is not None and bn.running_mean is not None
        with torch.no_grad():
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            shift = bn.bias - bn.running_mean * scale
        self.scale: torch.Tensor
        self.shift: torch.Tensor
        self.register_buffer("scale", scale.reshape(1, -1, 1, 1).clone())
        self.register_buffer("shift", shift.reshape(1, -1, 1, 1).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.addcmul(self.shift, x, self.scale)


class SlicedMaxPool(nn.Module):
    """`MaxPool2d(3, stride=2)` (no padding, floor mode) for a fixed input height and width,
    computed as two separable maxima over strided slices; output in channels_last."""

    def __init__(self, height: int, width: int) -> None:
        super().__init__()
        self.rows = [slice(k, k + 2 * ((height - 3) // 2) + 1, 2) for k in range(3)]
        self.cols = [slice(k, k + 2 * ((width - 3) // 2) + 1, 2) for k in range(3)]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r0, r1, r2 = self.rows
        c0, c1, c2 = self.cols
        rows = torch.maximum(torch.maximum(x[:, :, r0], x[:, :, r1]), x[:, :, r2])
        out = torch.maximum(torch.maximum(rows[:, :, :, c0], rows[:, :, :, c1]), rows[:, :, :, c2])
        return out.contiguous(memory_format=torch.channels_last)


class FastResidualBlock(nn.Module):
    """`ResidualBlock` with its `bn1` folded and its 1x1/2 shortcut on the im2col path."""

    def __init__(self, block: ResidualBlock) -> None:
        super().__init__()
        self.bn1 = ScaleShift(block.bn1)
        self.conv_strided = block.conv_strided
        self.bn2 = block.bn2  # follows a conv: torch.jit.freeze folds it into conv_strided
        self.conv = block.conv
        self.shortcut = block.shortcut

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        main = self.conv_strided(torch.relu(self.bn1(x)))
        main = self.conv(torch.relu(self.bn2(main)))
        shortcut = torch.ops.aten.thnn_conv2d(
            x, self.shortcut.weight, [1, 1], self.shortcut.bias, [2, 2], [0, 0]
        )
        out: torch.Tensor = main + shortcut
        return out


class InferenceDroNet(nn.Module):
    """`DroNet` for export: same weights and outputs, faster operators (module docstring)."""

    def __init__(self, model: DroNet) -> None:
        super().__init__()
        model = to_channels_last(copy.deepcopy(model)).eval()
        self.standardize = model.standardize
        self.conv1 = model.conv1
        with torch.no_grad():
            conv1_out = self.conv1(self.standardize(example_input(1)))
        self.pool = SlicedMaxPool(conv1_out.shape[2], conv1_out.shape[3])
        self.block1 = FastResidualBlock(model.block1)
        self.block2 = FastResidualBlock(model.block2)
        self.block3 = FastResidualBlock(model.block3)
        self.bn_out = ScaleShift(model.bn_out)
        self.head = model.head

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = self.pool(self.conv1(self.standardize(images_u8)))
        x = self.bn_out(self.block3(self.block2(self.block1(x))))
        out: torch.Tensor = self.head(torch.flatten(torch.relu(x), 1))
        return out
