"""Training checkpoints: everything needed to resume a run or rebuild its model.

A checkpoint (`*.ckpt`, written with `torch.save`, read with `weights_only=True`) is a dict:

- `format`: `CHECKPOINT_FORMAT`
- `epoch`: completed epochs (1-based count; the next epoch to run is `epoch + 1`)
- `model`: the model's state dict; `model_config`: `{"pixel_mean", "pixel_std", "dropout", "arch"}`
  (no "arch": "dronet", as every checkpoint before the option)
- `optimizer`, `scheduler`: their state dicts; the optimizer's also names its parameters
  (`param_names`, one list per group), so a resume maps state by name, not by position
- `best_val_loss`, `best_epoch`, `epochs_since_best`: early-stopping state
- `rng`: `{"torch": CPU generator state, "cuda": list of CUDA generator states or None}`
- `history`: one dict per completed epoch (what `metrics.jsonl` holds)
- `config`: the `TrainConfig` as plain data; `dataset`: `{"id", "root"}`; `command`: the
  command line that started the run; `initial_val_loss`: validation loss before training.

Writes are atomic (temporary file, then rename), so a run killed mid-write keeps its previous
checkpoint.
"""

from __future__ import annotations

import logging
import os
import pickle
from pathlib import Path
from typing import Any

import torch

from sim_harness.errors import SimError
from sim_harness.learning.model import DroNet, build_from_config

CHECKPOINT_FORMAT = "vision-swarm-checkpoint/1"
LAST_NAME = "last.ckpt"
BEST_NAME = "best.ckpt"

log = logging.getLogger(__name__)


class CheckpointError(SimError):
    """A checkpoint is missing, unreadable, or does not belong to the run being resumed."""


def save_checkpoint(state: dict[str, Any], path: Path) -> None:
    """Write `state` to `path` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    os.replace(tmp, path)


def checkpoint_file(path: Path) -> Path:
    """The file a checkpoint path names: a run directory means its `best.ckpt`."""
    path = Path(path)
    return path / BEST_NAME if path.is_dir() else path


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint (a run directory means its `best.ckpt`)."""
    path = checkpoint_file(path)
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
    model = build_from_config(state["model_config"], device)
    model.load_state_dict(state["model"])
    return model.eval()


def optimizer_state(optimizer: torch.optim.Optimizer, model: torch.nn.Module) -> dict[str, Any]:
    """`optimizer.state_dict()` plus the name of every parameter, group by group.

    torch keys optimizer state by a parameter's position, which changes whenever a module's
    attributes are reordered; the names let `load_optimizer_state` put each momentum buffer
    back on the parameter it belongs to.
    """
    state = optimizer.state_dict()
    state["param_names"] = _group_names(optimizer, model)
    return state


def _group_names(optimizer: torch.optim.Optimizer, model: torch.nn.Module) -> list[list[str]]:
    """The name of every parameter the optimizer holds, group by group."""
    names = {id(p): name for name, p in model.named_parameters()}
    return [[names[id(p)] for p in group["params"]] for group in optimizer.param_groups]


def load_optimizer_state(
    optimizer: torch.optim.Optimizer, model: torch.nn.Module, saved: dict[str, Any]
) -> None:
    """Restore `saved` (from `optimizer_state`) into `optimizer`, matching parameters by name.

    Raises `CheckpointError` naming the parameter when the saved state does not fit the model.
    """
    saved = dict(saved)
    saved_names = saved.pop("param_names", None)
    current = _group_names(optimizer, model)
    if saved_names is None:  # older checkpoints: positions only
        saved_names = current
    if [sorted(g) for g in saved_names] != [sorted(g) for g in current]:
        raise CheckpointError(
            "cannot resume: the checkpoint's optimizer groups hold other parameters "
            f"({_group_difference(saved_names, current)})"
        )
    by_name = {
        name: saved["state"][index]
        for group, names_in_group in zip(saved["param_groups"], saved_names, strict=True)
        for index, name in zip(group["params"], names_in_group, strict=True)
        if index in saved["state"]
    }
    params = dict(model.named_parameters())
    state: dict[int, Any] = {}
    groups = []
    index = 0
    for saved_group, names_in_group in zip(saved["param_groups"], current, strict=True):
        ids = []
        for name in names_in_group:
            entry = by_name.get(name)
            if entry is not None:
                for key, value in entry.items():
                    if (
                        isinstance(value, torch.Tensor)
                        and value.dim()
                        and value.shape != params[name].shape
                    ):
                        raise CheckpointError(
                            f"cannot resume: optimizer {key} for {name} has shape "
                            f"{tuple(value.shape)}, the parameter {tuple(params[name].shape)}"
                        )
                state[index] = entry
            ids.append(index)
            index += 1
        groups.append({**saved_group, "params": ids})
    optimizer.load_state_dict({"state": state, "param_groups": groups})


def _group_difference(saved: list[list[str]], current: list[list[str]]) -> str:
    if len(saved) != len(current):
        return f"{len(saved)} groups saved, {len(current)} now"
    for i, (a, b) in enumerate(zip(saved, current, strict=True)):
        missing, extra = sorted(set(b) - set(a)), sorted(set(a) - set(b))
        if missing or extra:
            return f"group {i}: not saved {missing[:3]}, unknown {extra[:3]}"
    return "groups differ"


def rng_state() -> dict[str, Any]:
    """torch's CPU and CUDA generator states (dropout draws from them)."""
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None
    return {"torch": torch.get_rng_state(), "cuda": cuda}


def restore_rng_state(state: dict[str, Any]) -> None:
    """Inverse of `rng_state` (CUDA states only when CUDA is available now and then)."""
    torch.set_rng_state(state["torch"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def resume_into(
    path: Path,
    manifest: dict[str, Any],
    model: DroNet,
    optimizer: torch.optim.Optimizer,
    scheduler: torch.optim.lr_scheduler.ReduceLROnPlateau,
    device: torch.device,
) -> dict[str, Any]:
    """Load run checkpoint `path` into model, optimizer, scheduler and the RNGs; return its state.

    Refused with a `CheckpointError` when the file is missing, or was trained on another dataset
    (`manifest["id"]`) or another architecture.
    """
    if not path.exists():
        raise CheckpointError(f"cannot resume: {path} does not exist")
    state = load_checkpoint(path, map_location=device)
    if state["dataset"]["id"] != manifest["id"]:
        raise CheckpointError(
            f"cannot resume: {path} was trained on dataset {state['dataset']['id']}, "
            f"not {manifest['id']}"
        )
    recorded = state["model_config"].get("arch", "dronet")
    if recorded != model.arch:  # the weights would load: the state dicts are alike
        raise CheckpointError(f"cannot resume: {path} trains arch {recorded}, not {model.arch}")
    model.load_state_dict(state["model"])
    load_optimizer_state(optimizer, model, state["optimizer"])
    scheduler.load_state_dict(state["scheduler"])
    restore_rng_state(state["rng"])
    log.info("resumed %s after epoch %d", path, state["epoch"])
    return state
