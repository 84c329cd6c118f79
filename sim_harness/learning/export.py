"""Exporting a trained network as the drone's policy file, and loading models for research tools.

The export is the `companion.model_file` format: `NAME.pt` (TorchScript, metadata embedded) and
`NAME.json` (its SHA-256). The TorchScript graph is traced in eval mode from a CPU copy in
channels_last layout, with the input standardization folded into conv1
(`learning.inference_graph`), and frozen (`torch.jit.freeze`, which also folds each batch norm
that follows a conv into it). Input uint8 (B, 64, 384), output float32 (B, 3), body FLU velocity
in m/s; it loads with `torch.jit.load` alone. The drone's loader (`companion.policy.Policy.load`)
turns on torch's oneDNN Graph fuser first, which compiles the graph into fused partitions at its
first calls; the metadata's `runtime` section says so for other loaders.

`torch.jit.optimize_for_inference` is not baked into the file: in torch 2.13 it rewrites convs
into MKL-DNN constants that `torch.jit.load` cannot read back ("required keyword attribute 'value'
is undefined"), and it measured slower than the oneDNN Graph fuser (docs/BENCHMARKS.md).

The sidecar also records a reference input and output (`companion.model_reference`): the
exported graph's output on `reference_scene()`, computed here, which the drone's loader reproduces
before it flies (a platform that computes the policy wrongly is refused). `add_reference` adds one
to a policy exported before that check.

Grad-CAM needs the eager network, which a frozen graph no longer is, so the export also writes
`NAME.weights.pt` (state dict + model config, read with `weights_only=True`); its SHA-256 is in
the policy's metadata, so it is verified through the policy file's own hash.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from companion.camera.layout import camera_spec
from companion.errors import CompanionError, ModelError
from companion.frames import BODY_FRAME, WORLD_FRAME
from companion.model_file import (
    base_metadata,
    enable_graph_fusion,
    load_model,
    save_model,
    sidecar_path,
    torchscript_calls,
)
from companion.model_reference import SIDECAR_KEY, Reference, reference_scene
from companion.validation import require_range
from sim_harness.learning.checkpoint import load_checkpoint, model_from_checkpoint
from sim_harness.learning.evaluate import PolicyModule
from sim_harness.learning.inference_graph import InferenceDroNet
from sim_harness.learning.model import (
    DroNet,
    build_from_config,
    count_parameters,
    example_input,
    to_channels_last,
)
from sim_harness.learning.symmetry import SymmetricPolicy, require_group

WEIGHTS_SUFFIX = ".weights.pt"
EXPORT_TOLERANCE_MPS = 1e-4  # an export whose graph differs more than this from eager is refused
ENSEMBLE_KEY = "ensemble"  # an ensemble policy's metadata and weights file list its members here


@dataclass(frozen=True)
class ExportResult:
    """Where the policy went, its hash, and the largest |exported - eager| seen at export."""

    path: Path
    sha256: str
    weights_path: Path
    max_abs_diff_mps: float
    metadata: dict[str, Any]
    reference: Reference


def to_torchscript(
    model: DroNet, graph: str = "inference", symmetry: str = "none"
) -> torch.jit.ScriptModule:
    """Traced and frozen CPU copy of `model` in eval mode, channels_last.

    `graph="inference"` (the export) traces `InferenceDroNet`, the same function with the input
    standardization folded into conv1; `graph="eager"` traces `DroNet` itself (for the tests).
    A `cube` network is traced as it is (its first conv pads with neighbouring faces, not with a
    constant, so there is no standardization to fold).
    `symmetry` (a `learning.symmetry.GROUPS` name) wraps it in `SymmetricPolicy`: the network
    averaged over the rig's symmetric views of each image, in one batch.
    """
    if graph not in ("inference", "eager"):
        raise ValueError(f"graph must be 'inference' or 'eager', not {graph!r}")
    cpu = to_channels_last(copy.deepcopy(model)).eval()
    folded = graph == "inference" and cpu.arch == "dronet"
    module: torch.nn.Module = InferenceDroNet(cpu).eval() if folded else cpu
    if symmetry != "none":
        module = SymmetricPolicy(module, symmetry).eval()
    with torch.no_grad(), torchscript_calls():  # TorchScript is the drone's format, for now
        traced = torch.jit.trace(module, example_input(1))  # type: ignore[no-untyped-call]
        frozen: torch.jit.ScriptModule = torch.jit.freeze(traced)
    return frozen


OUTPUT_GAIN_RANGE = (0.5, 2.0)  # `scale_output`'s accepted gains


def require_output_gain(gain: float) -> float:
    """`gain` if inside `OUTPUT_GAIN_RANGE`, else `ConfigError` naming the field and the range."""
    return require_range("output-gain", gain, *OUTPUT_GAIN_RANGE)


def scale_output(model: DroNet, gain: float) -> None:
    """Multiply the regression head's weights and bias by `gain`, in place: the network then
    answers `gain` times what it did, exactly (the head is linear and last; the symmetrized
    policy averages outputs linearly). Raises `ConfigError` outside `OUTPUT_GAIN_RANGE`.

    Why a gain: a network trained with a squared error on images that cannot pin every detail
    answers large commands too small (`benchmarks/command_shrinkage.py`); in flight that is a
    flock whose separation pushes too softly. The gain is chosen in closed loop on seeds the
    bar does not fly and recorded in the policy's training metadata (`output_gain`).
    """
    require_output_gain(gain)
    with torch.no_grad():
        model.head.weight.mul_(gain)
        model.head.bias.mul_(gain)


def weights_path_for(policy_path: Path) -> Path:
    """`NAME.pt` -> `NAME.weights.pt`."""
    return policy_path.with_name(policy_path.stem + WEIGHTS_SUFFIX)


def model_config(model: DroNet) -> dict[str, float | str]:
    """What `build_from_config` needs to rebuild `model`."""
    return {
        "pixel_mean": float(model.standardize.pixel_mean),
        "pixel_std": float(model.standardize.pixel_std),
        "dropout": float(model.dropout.p),
        "arch": model.arch,
    }


def policy_metadata(
    model: DroNet,
    manifest: dict[str, Any],
    test_metrics: dict[str, Any] | None,
    training: dict[str, Any],
    symmetry: str = "none",
) -> dict[str, Any]:
    """`companion.model_file.base_metadata()` plus what this network and its data were.

    Raises `ModelError` if the dataset was recorded with a different camera rig.
    """
    rig = camera_spec()
    if "camera" in manifest and json.loads(json.dumps(manifest["camera"])) != rig:
        raise ModelError("the dataset's camera spec differs from companion.camera.layout's rig")
    metadata = base_metadata()
    metadata.update(
        {
            "camera": rig,
            "frames": {
                "output": f"body {BODY_FRAME}: x forward, y left, z up",
                "world": WORLD_FRAME,
                "target": "teacher's Reynolds command rotated from world into the body frame",
                "dataset": manifest.get("frames"),
            },
            "dataset": {
                "id": manifest["id"],
                "renderer": manifest.get("renderer", "pybullet"),  # older datasets: pybullet
                "counts": manifest.get("counts"),
                "code_version": manifest.get("code_version"),
            },
            "pixel_mean": float(model.standardize.pixel_mean),
            "pixel_std": float(model.standardize.pixel_std),
            "test_metrics": test_metrics,
            "training": training,
            "architecture": {
                "name": "DroNet ResNet-8, single 3-output regression head",
                "arch": model.arch,
                "parameters": count_parameters(model),
                "gradcam_layer": "block2.conv_strided (64 x 4 x 24)"
                if model.arch == "dronet"
                else "block2.conv_strided, per face (64 x 4 x 4 x 6 faces, as the 4 x 24 strip)",
            },
            "runtime": {
                "graph": "frozen, channels_last, standardization folded into conv1"
                if model.arch == "dronet"
                else "frozen, channels_last, faces padded by their neighbours (traced as is)",
                "symmetry": {
                    "group": symmetry,
                    "views": len(require_group(symmetry)),
                    "what": "the network averaged over the camera rig's symmetric views of each "
                    "image, outputs mapped back to the body frame (sim_harness.learning.symmetry)",
                },
                "onednn_fusion": "recommended: torch.jit.enable_onednn_fusion(True) before the "
                "first call; the graph compiles into fused partitions during its first 2 calls",
                "threads": 1,
            },
            "torch_version": torch.__version__,
        }
    )
    return metadata


def export_policy(
    model: DroNet,
    path: Path,
    manifest: dict[str, Any],
    test_metrics: dict[str, Any] | None,
    training: dict[str, Any],
    scripted: torch.jit.ScriptModule | None = None,
    check_images_u8: torch.Tensor | None = None,
    symmetry: str = "none",
) -> ExportResult:
    """Write `path` (+ sidecar) and its eager weights; returns the hash and the export check.

    `scripted` is `to_torchscript(model)` when the caller already built it (e.g. to evaluate
    it); `check_images_u8` (B, 64, 384) are the images compared between eager and exported
    (default: 16 seeded random images). Raises `ModelError` if they differ by more than
    `EXPORT_TOLERANCE_MPS`. `symmetry`: the group the exported graph averages over (`scripted`,
    when given, must have been built with the same one); recorded in the metadata.
    """
    path = Path(path)
    require_group(symmetry)
    scripted = scripted if scripted is not None else to_torchscript(model, symmetry=symmetry)
    check_images_u8 = default_check_images() if check_images_u8 is None else check_images_u8
    cpu = to_channels_last(copy.deepcopy(model)).eval()
    eager: torch.nn.Module = cpu if symmetry == "none" else SymmetricPolicy(cpu, symmetry).eval()
    with torch.inference_mode():
        diff = float((scripted(check_images_u8) - eager(check_images_u8)).abs().max())
    if not diff <= EXPORT_TOLERANCE_MPS:
        raise ModelError(f"exported graph differs from the eager model by {diff:g} m/s: refused")
    metadata = policy_metadata(cpu, manifest, test_metrics, training, symmetry)
    weights_state = {"model_config": model_config(cpu), "model": cpu.state_dict()}
    digest, weights, reference = write_policy(
        scripted, metadata, path, weights_state, int(check_images_u8.shape[0]), diff
    )
    return ExportResult(path, digest, weights, diff, metadata, reference)


def default_check_images() -> torch.Tensor:
    """The export check's images when the caller gives none: 16 seeded random (64, 384) uint8."""
    generator = torch.Generator().manual_seed(0)
    shape = tuple(example_input(16).shape)
    return torch.randint(0, 256, shape, dtype=torch.uint8, generator=generator)


def write_policy(
    scripted: torch.jit.ScriptModule,
    metadata: dict[str, Any],
    path: Path,
    weights_state: dict[str, Any],
    checked_images: int,
    diff: float,
) -> tuple[str, Path, Reference]:
    """Write the eager weights file, then the policy file and its sidecar: `metadata` gains the
    weights file's name and hash and the export check's figures; the sidecar the platform check's
    reference. Returns (the policy's hash, the weights file, the reference)."""
    weights = weights_path_for(path)
    weights.parent.mkdir(parents=True, exist_ok=True)
    torch.save(weights_state, weights)
    metadata["eager_weights"] = {
        "file": weights.name,
        "sha256": hashlib.sha256(weights.read_bytes()).hexdigest(),
    }
    metadata["export_check"] = {"images": checked_images, "max_abs_diff_mps": diff}
    reference = make_reference(scripted, "computed at export from the exported graph")
    return save_model(scripted, metadata, path, reference), weights, reference


def make_reference(
    module: torch.jit.ScriptModule, how: str, image_u8: torch.Tensor | None = None
) -> Reference:
    """The platform check's reference: `module`'s output on `image_u8` (64, 384) uint8 (default
    `reference_scene()`), batch 1, unfused, computed on this machine."""
    image = torch.from_numpy(reference_scene()) if image_u8 is None else image_u8
    fusion_was = bool(torch.jit.onednn_fusion_enabled())  # type: ignore[no-untyped-call]
    enable_graph_fusion(False)
    try:
        with torch.inference_mode():
            out = module(image.unsqueeze(0)).to(torch.float64).reshape(-1)
    finally:
        enable_graph_fusion(fusion_was)
    if out.shape != (3,) or not bool(torch.isfinite(out).all()):
        raise ModelError(f"the policy's output on the reference image is {out.tolist()}: refused")
    made_with = {
        "how": how,
        "image": "companion.model_reference.reference_scene()" if image_u8 is None else "given",
        "torch": torch.__version__,
        "machine": platform.machine(),
        "graph_fusion": False,
        "batch": 1,
    }
    x, y, z = (float(v) for v in out)
    return Reference(image.numpy().copy(), (x, y, z), made_with=made_with)


def add_reference(path: Path, how: str = "add_reference on a trusted machine") -> Reference:
    """Add the platform check's reference to the sidecar of a policy exported before it.

    The policy is verified first (`load_model`: hash, metadata); its sidecar keeps every other
    field, so its hash record is unchanged. Run it on a machine known to compute the policy
    right (the export machine): the drone refuses the policy if it computes something else.
    """
    path = Path(path)
    loaded = load_model(path)
    reference = make_reference(loaded.module, how)
    sidecar = sidecar_path(path)
    record = json.loads(sidecar.read_text())
    record[SIDECAR_KEY] = reference.to_json()
    sidecar.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    return reference


def training_chain(command: str, init_from: str | None, depth: int = 0) -> dict[str, Any]:
    """Every training command that led to a model, first to last, for its metadata.

    `{"chain": [...], "chain_complete": bool}`. A fine-tune (`init_from`) inherits the chain of
    the policy file or checkpoint it started from; the chain is complete when its first command
    started from scratch, incomplete when an ancestor is missing or recorded no chain of its own.
    """
    ancestors = ancestor_chain(init_from, depth)
    return {"chain": [*ancestors["chain"], command], "chain_complete": ancestors["chain_complete"]}


def ancestor_chain(init_from: str | None, depth: int = 0) -> dict[str, Any]:
    """The chain that produced the weights at `init_from`, as that file says now (see above).

    Training records it when a fine-tune starts (`init_chain` in its checkpoints): a policy file
    is often overwritten later (a model shipped over the one it was tuned from), and resolving
    the path again at export would then read the newer model's history.
    """
    if not init_from:
        return {"chain": [], "chain_complete": True}
    inherited: dict[str, Any] = {"chain": [], "chain_complete": False}
    # An unreadable ancestor, or a history deeper than 20 (a cycle): incomplete from there on.
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError, CompanionError):
        if depth < 20:
            inherited = _recorded_chain(Path(init_from), depth)
    return inherited


def checkpoint_chain(state: dict[str, Any], depth: int = 0) -> dict[str, Any]:
    """The chain of a training checkpoint: its ancestors as recorded when it started (resolved
    from `init_from` now for checkpoints written before that was recorded), then its command."""
    recorded = state.get("init_chain")
    if recorded is None:
        return training_chain(state["command"], (state.get("config") or {}).get("init_from"), depth)
    return {
        "chain": [*recorded["chain"], state["command"]],
        "chain_complete": bool(recorded["chain_complete"]),
    }


def _recorded_chain(parent: Path, depth: int) -> dict[str, Any]:
    """The chain that produced `parent`, a checkpoint or a policy file (its sidecar)."""
    if is_checkpoint(parent):
        return checkpoint_chain(load_checkpoint(parent), depth + 1)
    training = json.loads(sidecar_path(parent).read_text())["metadata"]["training"]
    if isinstance(training.get("chain"), list):
        return {"chain": training["chain"], "chain_complete": bool(training["chain_complete"])}
    config = training.get("config")
    started_fresh = isinstance(config, dict) and "init_from" in config and not config["init_from"]
    return {"chain": [training["command"]], "chain_complete": started_fresh}


def is_checkpoint(path: Path) -> bool:
    """A training run directory or a `.ckpt` file (anything else is a policy file)."""
    return path.is_dir() or path.suffix == ".ckpt"


def load_eager_model(
    path: Path, device: str | torch.device = "cpu"
) -> tuple[DroNet, dict[str, Any]]:
    """The eager network (eval mode) from a checkpoint / run directory or a policy file.

    For a policy file, the policy's hash is verified (`load_model`), then its weights file's hash
    against the one recorded in the policy's metadata. Returns (model, checkpoint or metadata).
    An ensemble's file is refused (it is several networks: `learning.ensemble.load_eager_policy`
    reads it for Grad-CAM; fine-tuning and weight averaging take one network).
    """
    path = Path(path)
    if is_checkpoint(path):
        state = load_checkpoint(path, map_location=device)
        return model_from_checkpoint(state, device), state
    state, metadata = verified_weights(path, device)
    if ENSEMBLE_KEY in metadata:
        raise ModelError(
            f"{path} is an ensemble of {len(metadata[ENSEMBLE_KEY])} networks, not one: fine-tune "
            "or average one of its members (its metadata's `ensemble` lists them)"
        )
    model = build_from_config(state["model_config"], device)
    model.load_state_dict(state["model"])
    return model.eval(), metadata


def verified_weights(
    path: Path, device: str | torch.device = "cpu"
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A policy file's eager weights file, read after both hashes are checked: (its contents,
    the policy's metadata)."""
    loaded = load_model(path)
    record = loaded.metadata.get("eager_weights")
    if not isinstance(record, dict):
        raise ModelError(f"{path} records no eager weights (needed for Grad-CAM)")
    weights = path.with_name(str(record["file"]))
    try:
        data = weights.read_bytes()
    except OSError as exc:
        raise ModelError(f"cannot read {weights}: {exc.strerror}") from exc
    if hashlib.sha256(data).hexdigest() != record["sha256"]:
        raise ModelError(f"{weights} does not match the hash recorded in {path.name}: refused")
    state: dict[str, Any] = torch.load(weights, map_location=device, weights_only=True)
    return state, loaded.metadata


def load_for_inference(
    path: Path, device: str | torch.device = "cpu"
) -> tuple[PolicyModule, dict[str, Any]]:
    """A callable policy: the verified TorchScript module of a policy file (what the drone runs),
    or the eager network of a checkpoint. Returns (module, metadata or checkpoint)."""
    path = Path(path)
    if is_checkpoint(path):
        return load_eager_model(path, device)
    loaded = load_model(path, map_location=str(device))
    return loaded.module, loaded.metadata
