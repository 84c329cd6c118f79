"""Policy ensembles: one policy file whose answer is the weighted mean of several policies'.

Where `learning.average` mixes the weights of fine-tunes of one ancestor into one network (the
cost of one network, the behaviour of a blend), an ensemble calls every member and averages
their answers. Its point is the part of each network's error that the others do not share:
networks of different architectures or training runs err differently on the same image, and the
mean of their answers errs less. In flight that error acts as noise on each drone's command, and
noise is what turns a slowly drifting flock's velocities apart (the opposing flock's order
parameter: models/README.md). The price is every member's inference per image.

The file is the drone's ordinary policy format (`companion.model_file`): TorchScript, uint8
(B, 64, 384) in, body FLU (B, 3) m/s out, so the daemon, the simulator and the platform check
load it unchanged. Inside, each member is the member's own exported graph (with its own
symmetry average), verified against its hash before it is copied in.

Grad-CAM needs eager networks: the ensemble's weights file holds every member's state dict,
model config, symmetry group and share, and `load_eager_policy` rebuilds them as an
`EnsembleNet`, which `learning.gradcam.grad_cam` explains as one model (each member's map of the
evidence for the ensemble's answer, added). The export refuses a graph that answers differently
from those eager members (`EXPORT_TOLERANCE_MPS`), so the saliency is of the network that flies.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from companion.errors import ConfigError, ModelError
from companion.model_file import LoadedModel, load_model, torchscript_calls
from sim_harness.learning.average import require_weights
from sim_harness.learning.export import (
    ENSEMBLE_KEY,
    EXPORT_TOLERANCE_MPS,
    default_check_images,
    is_checkpoint,
    load_eager_model,
    model_config,
    verified_weights,
    write_policy,
)
from sim_harness.learning.model import DroNet, build_from_config, count_parameters
from sim_harness.learning.symmetry import SymmetricPolicy, require_group

MAX_MEMBERS = 8


class PolicyEnsemble(nn.Module):
    """The weighted mean of member policies' answers (TorchScript members, scripted as a whole)."""

    def __init__(self, members: Sequence[nn.Module], weights: Sequence[float]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.weights = [float(w) for w in weights]

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        total = torch.zeros(images_u8.shape[0], 3, device=images_u8.device)
        for k, member in enumerate(self.members):
            total = total + self.weights[k] * member(images_u8)
        return total


class EnsembleNet(nn.Module):
    """The eager form of an ensemble: bare member networks (no symmetry average) and shares.

    `forward` is the weighted mean of the members' answers; `members` is what Grad-CAM hooks.
    """

    def __init__(self, members: Sequence[DroNet], weights: Sequence[float]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)
        self.shares = [float(w) for w in weights]

    def forward(self, images_u8: torch.Tensor) -> torch.Tensor:
        outputs = [w * m(images_u8) for w, m in zip(self.shares, self.members, strict=True)]
        return torch.stack(outputs).sum(dim=0)


@dataclass(frozen=True)
class Member:
    """One member of an ensemble: its verified policy, eager network, symmetry group and share."""

    path: Path
    weight: float
    loaded: LoadedModel
    network: DroNet
    symmetry: str

    def to_json(self) -> dict[str, Any]:
        training = self.loaded.metadata.get("training") or {}
        dataset = self.loaded.metadata.get("dataset") or {}
        chain = training.get("chain")
        if not isinstance(chain, list):  # an export that recorded only its last command
            chain = [training["command"]] if training.get("command") else []
        return {
            "model": str(self.path),
            "weight": self.weight,
            "sha256": self.loaded.sha256,
            "arch": self.network.arch,
            "symmetry": self.symmetry,
            "parameters": count_parameters(self.network),
            "dataset_id": dataset.get("id"),
            "test_metrics": self.loaded.metadata.get("test_metrics"),
            "chain": [str(c) for c in chain],
        }


def require_shares(weights: Sequence[float] | None, count: int) -> list[float]:
    """The shares of `count` members (2 to `MAX_MEMBERS`): equal when None; else each in (0, 1],
    summing to 1."""
    if count > MAX_MEMBERS:
        raise ConfigError(f"models: an ensemble takes 2 to {MAX_MEMBERS} policies, got {count}")
    return require_weights(weights, count, "an ensemble")


def _symmetry_of(metadata: dict[str, Any]) -> str:
    runtime = metadata.get("runtime")
    symmetry = runtime.get("symmetry") if isinstance(runtime, dict) else None
    group = str(symmetry.get("group")) if isinstance(symmetry, dict) else "none"
    require_group(group)
    return group


def load_members(paths: Sequence[Path], weights: Sequence[float] | None = None) -> list[Member]:
    """Every member verified (its hash, its weights file's hash), with its share.

    Refused with `ModelError`: an ensemble among the members (list its members instead), members
    of different camera rigs, a member without eager weights.
    """
    shares = require_shares(weights, len(paths))
    members = []
    for path, share in zip(paths, shares, strict=True):
        path = Path(path)
        loaded = load_model(path)
        if ENSEMBLE_KEY in loaded.metadata:
            raise ModelError(f"{path} is itself an ensemble: list its members instead")
        network, _ = load_eager_model(path)
        members.append(Member(path, share, loaded, network, _symmetry_of(loaded.metadata)))
    rig = members[0].loaded.metadata.get("camera")
    for member in members[1:]:
        if member.loaded.metadata.get("camera") != rig:
            raise ModelError(f"{member.path}: its camera rig differs from {members[0].path}'s")
    return members


def scripted_ensemble(members: Sequence[Member]) -> torch.jit.ScriptModule:
    """The members' own exported graphs under one scripted weighted mean."""
    module = PolicyEnsemble([m.loaded.module for m in members], [m.weight for m in members])
    with torchscript_calls():
        scripted: torch.jit.ScriptModule = torch.jit.script(module.eval())
    return scripted


def _eager_policy(members: Sequence[Member]) -> nn.Module:
    """What the exported graph must compute: each eager member under its own symmetry average."""
    nets = [
        m.network if m.symmetry == "none" else SymmetricPolicy(m.network, m.symmetry)
        for m in members
    ]
    return PolicyEnsemble([n.eval() for n in nets], [m.weight for m in members]).eval()


def ensemble_metadata(
    members: Sequence[Member], test_metrics: dict[str, Any] | None, command: str
) -> dict[str, Any]:
    """The first member's metadata (rig, frames, dataset), with what the ensemble is instead of
    its network: members and shares, parameters, runtime, test metrics, the command."""
    metadata = copy.deepcopy(members[0].loaded.metadata)
    for key in ("eager_weights", "export_check", "pixel_mean", "pixel_std"):
        metadata.pop(key, None)
    described = [m.to_json() for m in members]
    chain: list[str] = []
    for member in described:
        chain += [c for c in member["chain"] if c not in chain]
    views = sum(len(require_group(m.symmetry)) for m in members)
    groups = {m.symmetry for m in members}
    metadata.update(
        {
            ENSEMBLE_KEY: described,
            "test_metrics": test_metrics,
            "training": {
                "command": command,
                "output_gain": 1.0,
                "chain": [*chain, command],
                "chain_complete": False,
            },
            "architecture": {
                "name": f"ensemble of {len(members)} networks, answers averaged with their shares",
                "arch": "ensemble",
                "members": [f"{m.network.arch} x {m.weight:g}" for m in members],
                "parameters": sum(count_parameters(m.network) for m in members),
                "gradcam_layer": "each member's block2.conv_strided, maps added",
            },
            "runtime": {
                **metadata.get("runtime", {}),
                "graph": "scripted weighted mean of the members' own frozen graphs",
                "symmetry": {
                    # exactly equivariant under a group all members average over
                    "group": groups.pop() if len(groups) == 1 else "none",
                    "views": views,
                    "members": [m.symmetry for m in members],
                    "what": "each member averaged over its own symmetric views (its export's); "
                    f"{views} network calls an image in all",
                },
            },
            "torch_version": torch.__version__,
        }
    )
    return metadata


@dataclass(frozen=True)
class EnsembleExport:
    """Where the ensemble went, its hash, and the largest |graph - eager members| at export."""

    path: Path
    sha256: str
    weights_path: Path
    max_abs_diff_mps: float
    metadata: dict[str, Any]


def export_ensemble(
    members: Sequence[Member],
    path: Path,
    test_metrics: dict[str, Any] | None,
    command: str,
    scripted: torch.jit.ScriptModule | None = None,
    check_images_u8: torch.Tensor | None = None,
) -> EnsembleExport:
    """Write the ensemble policy `path` (+ sidecar with the platform check's reference) and its
    weights file (every member's eager network). Raises `ModelError` if the graph and the eager
    members differ by more than `EXPORT_TOLERANCE_MPS` on `check_images_u8` (default 16 seeded
    random images)."""
    path = Path(path)
    scripted = scripted if scripted is not None else scripted_ensemble(members)
    check_images_u8 = default_check_images() if check_images_u8 is None else check_images_u8
    with torch.inference_mode():
        got = scripted(check_images_u8)
        diff = float((got - _eager_policy(members)(check_images_u8)).abs().max())
    if not diff <= EXPORT_TOLERANCE_MPS:
        raise ModelError(f"the ensemble's graph differs from its members by {diff:g} m/s: refused")
    weights_state = {
        ENSEMBLE_KEY: [
            {
                "model_config": model_config(m.network),
                "model": m.network.state_dict(),
                "weight": m.weight,
                "symmetry": m.symmetry,
            }
            for m in members
        ]
    }
    metadata = ensemble_metadata(members, test_metrics, command)
    checked = int(check_images_u8.shape[0])
    digest, weights, _ = write_policy(scripted, metadata, path, weights_state, checked, diff)
    return EnsembleExport(path, digest, weights, diff, metadata)


def load_eager_policy(
    path: Path, device: str | torch.device = "cpu"
) -> tuple[DroNet | EnsembleNet, dict[str, Any]]:
    """What Grad-CAM explains: the eager network of a checkpoint or policy file, or, for an
    ensemble's file, its `EnsembleNet` (both weights files verified through the policy's hash).
    Returns (model, checkpoint or metadata)."""
    path = Path(path)
    if is_checkpoint(path):
        return load_eager_model(path, device)
    state, metadata = verified_weights(path, device)
    if ENSEMBLE_KEY not in metadata:
        network = build_from_config(state["model_config"], device)
        network.load_state_dict(state["model"])
        return network.eval(), metadata
    records = state.get(ENSEMBLE_KEY)
    if not isinstance(records, list) or not records:
        raise ModelError("the weights file lists no ensemble members")
    networks = []
    for record in records:
        network = build_from_config(record["model_config"], device)
        network.load_state_dict(record["model"])
        networks.append(network.eval())
    return EnsembleNet(networks, [float(r["weight"]) for r in records]).eval(), metadata
