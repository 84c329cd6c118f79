"""The optimizer of a training run and what steers it epoch by epoch: SGD with momentum, the lr
(the paper's plateau halving, or a cosine over the run: `lr_schedule`) and early stopping.

The paper's recipe: SGD, momentum 0.9, weight decay on the conv and linear weights only (its
`(lambda / 2) ||w||^2` term), lr x `lr_factor` once `lr_patience_epochs` epochs in a row have not
lowered the validation loss, and stop once more than `early_stop_patience_epochs` have not.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from sim_harness.learning.lr_schedule import cosine_lr
from sim_harness.learning.model import DroNet, parameter_groups
from sim_harness.learning.train_config import TrainConfig


def make_optimizer(model: DroNet, config: TrainConfig) -> torch.optim.SGD:
    """SGD with momentum; weight decay on the conv and linear weights only."""
    return torch.optim.SGD(
        parameter_groups(model, config.weight_decay),
        lr=config.lr,
        momentum=config.momentum,
    )


def make_scheduler(
    optimizer: torch.optim.Optimizer, config: TrainConfig
) -> torch.optim.lr_scheduler.ReduceLROnPlateau:
    """lr x `lr_factor` on the `lr_patience_epochs`-th consecutive epoch without improvement."""
    return torch.optim.lr_scheduler.ReduceLROnPlateau(
        optimizer,
        mode="min",
        factor=config.lr_factor,
        patience=config.lr_patience_epochs - 1,  # torch acts on the (patience + 1)-th bad epoch
        threshold=0.0,
    )


def cosine_lr_at(config: TrainConfig, epoch: int, n_batches: int) -> Callable[[int], float]:
    """The lr of each batch of `epoch` (1-based) on the run's cosine curve."""
    done, run = (epoch - 1) * n_batches, config.max_epochs * n_batches
    return lambda step: cosine_lr(config.lr, done + step, run)


@dataclass
class Plateau:
    """Early-stopping bookkeeping; `stop` once more than `patience_epochs` epochs in a row have
    not lowered the validation loss (an equal loss is no improvement)."""

    patience_epochs: int
    best_val_loss: float = math.inf
    best_epoch: int = 0
    epochs_since_best: int = 0

    def update(self, epoch: int, val_loss: float) -> bool:
        """Record one epoch's validation loss; True when it is a new best."""
        improved = val_loss < self.best_val_loss
        if improved:
            self.best_val_loss, self.best_epoch, self.epochs_since_best = val_loss, epoch, 0
        else:
            self.epochs_since_best += 1
        return improved

    @property
    def stop(self) -> bool:
        return self.epochs_since_best > self.patience_epochs

    def as_state(self) -> dict[str, Any]:
        return {
            "best_val_loss": self.best_val_loss,
            "best_epoch": self.best_epoch,
            "epochs_since_best": self.epochs_since_best,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Take up the bookkeeping a checkpoint saved with `as_state`."""
        self.best_val_loss = state["best_val_loss"]
        self.best_epoch = state["best_epoch"]
        self.epochs_since_best = state["epochs_since_best"]
