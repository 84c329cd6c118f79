"""Learning-rate schedules of a training run (pure arithmetic; no torch, so the CLI can list them).

- `plateau`: the paper's. The lr is multiplied by `lr_factor` once `lr_patience_epochs` epochs in
  a row have not lowered the validation loss (`optimization.make_scheduler`).
- `cosine`: the lr falls batch by batch from its initial value to 0 along half a cosine over the
  run's `max_epochs`. A fine-tune of one or two epochs never meets a plateau, so at `plateau` it
  ends at its full lr, with SGD's noise still in the weights; `cosine` anneals it. A resumed run
  picks the curve up where it stopped (the lr is a function of the batch's place in the run).
"""

from __future__ import annotations

import math

LR_SCHEDULES = ("plateau", "cosine")


def cosine_lr(base_lr: float, step: int, total_steps: int) -> float:
    """The lr of batch `step` (0-based) of a `total_steps`-batch run: `base_lr` at the first
    batch, falling to `base_lr * (1 - cos(pi / total_steps)) / 2` at the last (never exactly 0,
    so the last batch still learns)."""
    if total_steps < 1 or not 0 <= step < total_steps:
        raise ValueError(f"step {step} outside a run of {total_steps} batches")
    return 0.5 * base_lr * (1.0 + math.cos(math.pi * step / total_steps))
