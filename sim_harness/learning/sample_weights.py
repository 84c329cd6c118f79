"""Per-sample loss weights beyond the paper's plain mean squared error.

A network trained with the plain mean squared error on images that cannot pin every detail answers
the rare states too timidly: the loss is lowest near the mean of what each image might mean. Two
weightings pull the fit towards the states the flock's safety and shape depend on:

- by command size (`speed_weights`, `--weight-speed`): a neighbour close by, a stretched flock;
- by the nearest neighbour's distance (`near_weights`, `--weight-near`): the close-range states,
  where a pair's separation is decided. In the teacher's flocks they are rare (under 0.5 % of an
  aggregated round's samples have a neighbour within 1.2 m) and their command is not large (the
  separation term is averaged over all neighbours), so the command-size weighting leaves them at
  weight 1. On such states of an aggregated round's validation split, round 19 answered 0.64 of
  the teacher's command along its direction under 1 m, against 0.94 beyond 1.4 m.

A sample takes the larger of its weights, at most the cap; the loss is normalized by the weights'
sum so the learning rate keeps its meaning.

Weights leave the fit at a weighted mean of what an image might mean, so a close neighbour whose
distance the image leaves uncertain still gets a separation that is too weak as often as too
strong. The shortfall term (`shortfall`, `--weight-shortfall`) is asymmetric instead: on the
close-range samples it adds the squared part of the error that falls short along the teacher's
command, so the fit moves towards answering such states too strongly (an expectile, not a mean):
a drone that turns away a little early loses some order; one that turns away late loses the pair.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from sim_harness.learning.train_config import TrainConfig


def speed_weights(target: torch.Tensor, speed_mps: float, cap: float) -> torch.Tensor:
    """Per-sample weights max(1, |target| / speed_mps), at most `cap`: (B, 3) -> (B,)."""
    return (target.norm(dim=1) / speed_mps).clamp(min=1.0, max=cap)


def near_weights(nearest_m: torch.Tensor, near_m: float, cap: float) -> torch.Tensor:
    """Per-sample weights (near_m / nearest_m)^4, at least 1 and at most `cap`: (B,) -> (B,).

    A fourth power so the weight climbs fast inside `near_m`: with near_m = 1.5 m and the cap 4,
    a neighbour at 1.25 m doubles a sample's weight and one at 1.06 m or closer quadruples it.
    """
    ratio = near_m / nearest_m.clamp(min=1e-3)
    return ratio.pow(4).clamp(min=1.0, max=cap)


@dataclass(frozen=True)
class SampleWeighting:
    """Per-sample loss weights (the larger of the command-size and the close-range weight) and
    the optional shortfall term."""

    cap: float
    speed_mps: float | None = None
    near_m: float | None = None
    shortfall_weight: float | None = None
    shortfall_within_m: float = 1.2

    @classmethod
    def of(cls, config: TrainConfig) -> SampleWeighting | None:
        """The config's weighting, or None for the paper's plain mean squared error."""
        if (
            config.weight_speed_mps is None
            and config.weight_near_m is None
            and config.weight_shortfall is None
        ):
            return None
        return cls(
            config.weight_cap,
            config.weight_speed_mps,
            config.weight_near_m,
            config.weight_shortfall,
            config.shortfall_within_m,
        )

    @property
    def needs_nearest(self) -> bool:
        """Whether the loss reads each sample's nearest-neighbour distance."""
        return self.near_m is not None or self.shortfall_weight is not None

    def loss(
        self, pred: torch.Tensor, target: torch.Tensor, nearest_m: torch.Tensor
    ) -> torch.Tensor:
        """The weighted loss of a batch, shortfall term included: (B, 3), (B, 3), (B,) -> ()."""
        extra = None
        if self.shortfall_weight is not None:
            extra = self.shortfall_weight * shortfall(
                pred, target, nearest_m, self.shortfall_within_m
            )
        return weighted_velocity_loss(pred, target, self.weights(target, nearest_m), extra)

    def weights(self, target: torch.Tensor, nearest_m: torch.Tensor) -> torch.Tensor:
        """(B, 3) targets and (B,) nearest-neighbour distances (ignored unless `near_m`) -> (B,)."""
        weights = torch.ones(target.shape[0], dtype=target.dtype, device=target.device)
        if self.speed_mps is not None:
            weights = torch.maximum(weights, speed_weights(target, self.speed_mps, self.cap))
        if self.near_m is not None:
            weights = torch.maximum(weights, near_weights(nearest_m, self.near_m, self.cap))
        return weights


def shortfall(
    pred: torch.Tensor, target: torch.Tensor, nearest_m: torch.Tensor, within_m: float
) -> torch.Tensor:
    """The squared shortfall along the target, per axis like the MSE: (B, 3), (B, 3), (B,) -> (B,).

    For a sample whose nearest neighbour is closer than `within_m`: max(0, -(pred - target) . u)^2
    / 3 with u the target's direction (zero for a zero target); 0 for every other sample. An
    answer longer than the target along it, or off to its side, costs nothing here.
    """
    direction = target / target.norm(dim=1, keepdim=True).clamp(min=1e-6)  # a zero target: zero
    short = (-((pred - target) * direction).sum(dim=1)).clamp(min=0.0)
    return (nearest_m < within_m).to(pred.dtype) * short.square() / 3.0


def weighted_velocity_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    weights: torch.Tensor,
    extra: torch.Tensor | None = None,
) -> torch.Tensor:
    """Squared error averaged over the axes, then over the batch with `weights` (B,), (m/s)^2.

    Normalized by the weights' sum: with all weights equal it is `velocity_loss`, so the learning
    rate keeps its meaning. `extra` (B,): a per-sample term added to the squared error before
    weighting (the shortfall term).
    """
    per_sample = (pred - target).square().mean(dim=1)
    if extra is not None:
        per_sample = per_sample + extra
    return (weights * per_sample).sum() / weights.sum()
