"""Training checkpoints: everything needed to resume a run or rebuild its model.

A checkpoint (`*.ckpt`, written with `torch.save`, read with `weights_only=True`) is a dict:

- `format`: `CHECKPOINT_FORMAT`
- `epoch`: completed epochs (1-based count; the next epoch to run is `epoch + 1`)
- `model`: the model's state dict; `model_config`: `{"pixel_mean", "pixel_std", "dropout"}`
- `optimizer`, `scheduler`: their state dicts
- `best_val_loss`, `best_epoch`, `epochs_since_best`: early-stopping state
- `rng`: `{"torch": CPU generator state, "cuda": list of CUDA generator states or None}`
- `history`: one dict per completed epoch (what `metrics.jsonl` holds)
- `config`: the `TrainConfig` as plain data; `dataset`: `{"id", "root"}`; `command`: the
  command line that started the run; `initial_val_loss`: validation loss before training.

Writes are atomic (temporary file, then rename), so a run killed mid-write keeps its previous
checkpoint.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

from sim_harness.errors import SimError
from sim_harness.model import DroNet, build_model

CHECKPOINT_FORMAT = "vision-swarm-checkpoint/1"
LAST_NAME = "last.ckpt"
BEST_NAME = "best.ckpt"


class CheckpointError(SimError):
    """A checkpoint is missing, unreadable, or does not belong to the run being resumed."""


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write `state` to `path` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint (a run directory means its `best.ckpt`)."""
    path = Path(path)
    if path.is_dir():
        path = path / BEST_NAME
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except (OSError, RuntimeError, EOFError, pickle.UnpicklingError) as exc:
        first_line = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise CheckpointError(f"cannot read checkpoint {path}: {first_line}") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a training checkpoint ({CHECKPOINT_FORMAT})")
    return state


def model_from_checkpoint(state: dict[str, Any], device: str | torch.device = "cpu") -> DroNet:
    """Rebuild the checkpoint's model in eval mode on `device`."""
    cfg = state["model_config"]
    model = build_model(cfg["pixel_mean"], cfg["pixel_std"], cfg["dropout"], device=device)
    model.load_state_dict(state["model"])
    return model.eval()


def rng_state() -> dict[str, Any]:
    """torch's CPU and CUDA generator states (dropout draws from them)."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
    return {"torch": torch.get_rng_state(), "cuda": cuda}


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of `rng_state` (CUDA states only when CUDA is available now and then)."""
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
