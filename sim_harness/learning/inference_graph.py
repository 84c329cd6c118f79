"""The network arranged for oneDNN Graph fusion at load time: the graph the export traces.

Same function as `DroNet` (outputs agree to float rounding; the export checks 1e-4 and the tests
1e-5). Loaders turn on TorchScript's oneDNN Graph fuser (`companion.model_file.enable_graph_fusion`,
called by `companion.policy.Policy.load`), which after two calls compiles the frozen graph into
fused oneDNN partitions: each conv with its ReLU or its residual add, each pre-activation batch
norm with its ReLU, the pool, the head. Measured single-thread, batch 1 on this project's 2-core
VM (`benchmarks/cnn_latency.py`, docs/BENCHMARKS.md), that is about 1.5x faster than the best
unfused graph.

One change to the network's own layers, so that nothing but an integer-to-float cast and a pad
stays outside the fused partitions:

- **standardization folded into conv1.** `conv1((x - mean) / std)` with zero padding equals a
  conv with weights `w / std` and bias `b - sum(w) * mean / std` over the raw image padded with
  `mean` (a raw `mean` pixel is a standardized zero). Folded in float64, then stored as float32.

Everything else (max pool, residual blocks, `bn_out`, head) is the eager module's own code;
`torch.jit.freeze` folds each block's `bn2` into the conv it follows. Training, evaluation and
Grad-CAM keep using `DroNet`; only the exported file runs this.

Without the fuser (a loader that does not enable it, or a torch build without oneDNN Graph) the
same file runs unfused: 5-6 % slower at batch 1 and 5-8 % faster at batch 9 than the hand-tuned
unfused graph it replaced (sliced max pool, folded batch norms, im2col shortcuts), whose custom
operators the fuser cannot fuse.
"""

from __future__ import annotations

import copy

import torch
from torch import nn
from torch.nn import functional as F

from sim_harness.learning.model import DroNet, to_channels_last


class FoldedStem(nn.Module):
    """`conv1(standardize(images_u8))` as one conv over the raw image padded with the mean."""

    def __init__(self, model: DroNet) -> None:
        super().__init__()
        conv = model.conv1
        assert conv.bias is not None and isinstance(conv.padding, tuple)
        mean = float(model.standardize.pixel_mean)
        std = float(model.standardize.pixel_std)
        with torch.no_grad():
            weight = conv.weight.double() / std
            bias = conv.bias.double() - weight.sum(dim=(1, 2, 3)) * mean
        self.conv = nn.Conv2d(
            conv.in_channels, conv.out_channels, conv.kernel_size, stride=conv.stride, padding=0
        )
        with torch.no_grad():
            self.conv.weight.copy_(weight.float())
            self.conv.bias.copy_(bias.float())
        self.conv.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        pad_h, pad_w = conv.padding
        self.pad = [pad_w, pad_w, pad_h, pad_h]
        self.fill = mean

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = F.pad(images_u8.unsqueeze(1).float(), self.pad, value=self.fill)
        out: torch.Tensor = self.conv(x.contiguous(memory_format=torch.channels_last))
        return out


class InferenceDroNet(nn.Module):
    """`DroNet` for export: same weights and outputs, standardization folded (module docstring)."""

    def __init__(self, model: DroNet) -> None:
        super().__init__()
        model = to_channels_last(copy.deepcopy(model)).eval()
        self.stem = FoldedStem(model)
        self.pool = model.pool
        self.block1 = model.block1
        self.block2 = model.block2
        self.block3 = model.block3
        self.bn_out = model.bn_out
        self.head = model.head

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        x = self.pool(self.stem(images_u8))
        x = self.bn_out(self.block3(self.block2(self.block1(x))))
        out: torch.Tensor = self.head(torch.flatten(torch.relu(x), 1))
        return out
