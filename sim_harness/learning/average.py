"""Weight averaging: one network whose parameters are a weighted mean of several networks'.

For fine-tunes of one common ancestor (e.g. round 31 and a student tuned from it), the mean of
their weights is a network between them in weight space that usually fits as well as either
(the runs stay in one basin of the loss) and answers with a blend of their behaviours, at the
cost of one network, unlike an ensemble that calls each. Networks trained from different starts
do not average into anything useful; this module cannot tell, the evaluation after it does.

Every floating-point tensor of the state dict is averaged, batch-norm running statistics too
(the networks are exported frozen, so the averaged statistics are what the graph folds in);
integer buffers (batch norm's step counters) are taken from the first network. The networks
must share architecture and input standardization: anything else is refused with `ModelError`.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from companion.errors import ConfigError, ModelError
from sim_harness.learning.checkpoint import checkpoint_file
from sim_harness.learning.export import (
    checkpoint_chain,
    is_checkpoint,
    load_eager_model,
    model_config,
)
from sim_harness.learning.model import DroNet, build_from_config

WEIGHT_SUM_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Source:
    """One network of an average: where it came from, its share, its dataset and history."""

    path: Path
    weight: float
    sha256: str
    dataset_id: str | None
    chain: list[str]
    chain_complete: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "model": str(self.path),
            "weight": self.weight,
            "sha256": self.sha256,
            "chain": self.chain,
            "chain_complete": self.chain_complete,
        }


def require_weights(
    weights: Sequence[float] | None, count: int, what: str = "an average"
) -> list[float]:
    """The shares of `count` networks: equal when None; else each in (0, 1], summing to 1."""
    if count < 2:
        raise ConfigError(f"models: {what} needs at least 2 networks, got {count}")
    if weights is None:
        return [1.0 / count] * count
    values = [float(w) for w in weights]
    if len(values) != count:
        raise ConfigError(f"weights: {len(values)} given for {count} models (one each)")
    for value in values:
        if not (math.isfinite(value) and 0.0 < value <= 1.0):
            raise ConfigError(f"weights: each must be in (0, 1], got {value:g}")
    if abs(sum(values) - 1.0) > WEIGHT_SUM_TOLERANCE:
        raise ConfigError(f"weights: must sum to 1, got {sum(values):g}")
    return values


def _source(path: Path, weight: float, state: dict[str, Any]) -> Source:
    """What the average records of one network (`state`: its checkpoint or policy metadata)."""
    if is_checkpoint(path):
        file = checkpoint_file(path)  # what load_checkpoint reads
        history = checkpoint_chain(state)
    else:
        file = path
        training = state.get("training") or {}
        chain = training.get("chain")
        if isinstance(chain, list):
            history = {"chain": chain, "chain_complete": bool(training.get("chain_complete"))}
        else:
            command = training.get("command")
            history = {"chain": [command] if command else [], "chain_complete": False}
    dataset = state.get("dataset")
    dataset_id = dataset.get("id") if isinstance(dataset, dict) else None
    return Source(
        path=path,
        weight=weight,
        sha256=hashlib.sha256(file.read_bytes()).hexdigest() if file.is_file() else "",
        dataset_id=dataset_id,
        chain=[str(c) for c in history["chain"]],
        chain_complete=bool(history["chain_complete"]),
    )


def average_networks(models: Sequence[DroNet], weights: Sequence[float]) -> DroNet:
    """A new network (eval mode) whose floating-point tensors are sum(w_k * tensor_k)."""
    first = models[0]
    config = model_config(first)
    config.pop("dropout")  # inactive in eval: the networks may differ in it
    keys = list(first.state_dict())
    for k, model in enumerate(models[1:], start=2):
        other = model_config(model)
        other.pop("dropout")
        if other != config:
            raise ModelError(f"network {k} differs from the first: {other} vs {config}")
        if list(model.state_dict()) != keys:
            raise ModelError(f"network {k} has other parameters than the first")
    states = [m.state_dict() for m in models]
    mixed: dict[str, torch.Tensor] = {}
    for key in keys:
        tensors = [s[key] for s in states]
        if any(t.shape != tensors[0].shape for t in tensors):
            raise ModelError(f"{key}: the networks' shapes differ")
        if tensors[0].is_floating_point():
            mixed[key] = sum(
                (w * t.detach().double() for w, t in zip(weights, tensors, strict=True)),
                torch.zeros_like(tensors[0], dtype=torch.float64),
            ).to(tensors[0].dtype)
        else:
            mixed[key] = tensors[0].clone()
    average = build_from_config(model_config(first), "cpu")
    average.load_state_dict(mixed)
    return average.eval()


def average_policies(
    paths: Sequence[Path], weights: Sequence[float] | None = None
) -> tuple[DroNet, list[Source]]:
    """The weighted mean of the networks at `paths` (policy files, verified against their hashes
    and their weights files', or training checkpoints) and what each contributed."""
    shares = require_weights(weights, len(paths))
    models: list[DroNet] = []
    sources: list[Source] = []
    for path, share in zip(paths, shares, strict=True):
        model, state = load_eager_model(Path(path))
        models.append(model.cpu())
        sources.append(_source(Path(path), share, state))
    return average_networks(models, shares), sources


def averaged_chain(sources: Sequence[Source], command: str) -> dict[str, Any]:
    """The training history of an average: every source's commands once, in the order first
    met (a fine-tune's chain holds its ancestor's), then the averaging command itself."""
    chain: list[str] = []
    for source in sources:
        chain += [c for c in source.chain if c not in chain]
    return {
        "chain": [*chain, command],
        "chain_complete": all(s.chain_complete for s in sources),
        "averaged": [s.to_json() for s in sources],
    }
