"""The exported policy file: TorchScript + metadata + SHA-256, one format for simulation and drone.

A policy is two files side by side:

- `NAME.pt`: a TorchScript module taking the raw stitched images, uint8 tensor (B, 64, 384) in the
  `companion.camera.layout` order, and returning the body-frame (FLU) velocity, float32 (B, 3) m/s.
  Standardization is inside. The metadata is embedded as the extra file `metadata.json`, so the
  `.pt` alone is self-describing and loads with torch only (`torch.jit.load`).
- `NAME.json`: `{"sha256": <hex digest of NAME.pt>, "metadata": {...}, "reference": {...}}`, the
  recorded hash and, since the platform check, a reference input and output
  (`companion.model_reference`; older sidecars have none).

`load_model` refuses a file whose hash differs from the expected one (from the config) or from the
recorded one, and metadata that does not describe this project's rig and frames.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from companion.camera.layout import FACE_NAMES, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ModelError
from companion.model_reference import SIDECAR_KEY, Reference, reference_from_json

MODEL_FORMAT = "vision-swarm-policy/1"
METADATA_NAME = "metadata.json"
OUTPUT_FRAME = "body_flu"
# torch 2.13 warns on every torch.jit.script/trace/save/load call that TorchScript is deprecated
# (in favour of torch.export). This project keeps TorchScript as the drone's format until its
# runtime moves (docs/torchscript-migration.md), so that one message is expected; it is matched
# exactly, so torch's other warnings (e.g. "not supported in Python 3.14+ and may break") show.
_JIT_DEPRECATED = r"`torch\.jit\.\w+` is deprecated\."


@contextlib.contextmanager
def torchscript_calls() -> Iterator[None]:
    """Silence torch's TorchScript deprecation warning around this project's own torch.jit calls.

    `warnings.catch_warnings` swaps the process-wide filter list while the block runs (Python
    3.11 has no per-thread filters); only a DeprecationWarning with exactly that message is
    dropped meanwhile.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=_JIT_DEPRECATED, category=DeprecationWarning)
        yield


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def sidecar_path(model_path: str | Path) -> Path:
    """Where the recorded hash and metadata of `model_path` live (`NAME.pt` -> `NAME.json`)."""
    return Path(model_path).with_suffix(".json")


def base_metadata() -> dict[str, Any]:
    """The metadata fields every policy file carries about its input and output contract."""
    return {
        "format": MODEL_FORMAT,
        "input": {
            "dtype": "uint8",
            "shape": [-1, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX],
            "face_order": list(FACE_NAMES),
            "standardization": "inside",
        },
        "output": {"frame": OUTPUT_FRAME, "units": "m/s", "shape": [-1, 3]},
    }


def check_metadata(metadata: dict[str, Any]) -> None:
    """Raise `ModelError` unless the metadata describes this project's input and output contract."""
    expected = base_metadata()
    if metadata.get("format") != MODEL_FORMAT:
        raise ModelError(f"model format is {metadata.get('format')!r}, expected {MODEL_FORMAT!r}")
    for section in ("input", "output"):
        got = metadata.get(section)
        if not isinstance(got, dict):
            raise ModelError(f"model metadata has no {section!r} section")
        for key, value in expected[section].items():
            if got.get(key) != value:
                raise ModelError(
                    f"model metadata {section}.{key} is {got.get(key)!r}, expected {value!r}"
                )


def save_model(
    module: torch.jit.ScriptModule,
    metadata: dict[str, Any],
    path: str | Path,
    reference: Reference | None = None,
) -> str:
    """Write `module` with `metadata` embedded, then the sidecar with its hash (and `reference`,
    the platform check's input and output, when given); returns the hash."""
    check_metadata(metadata)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(metadata, indent=2, sort_keys=True)
    with torchscript_calls():
        torch.jit.save(module, str(path), _extra_files={METADATA_NAME: text})
    digest = sha256_file(path)
    sidecar: dict[str, Any] = {"sha256": digest, "metadata": metadata}
    if reference is not None:
        sidecar[SIDECAR_KEY] = reference.to_json()
    sidecar_path(path).write_text(json.dumps(sidecar, indent=2, sort_keys=True) + "\n")
    return digest


def enable_graph_fusion(enabled: bool = True) -> bool:
    """Turn TorchScript's oneDNN Graph fuser on or off (process-wide); True if it is now on.

    With it on, a frozen policy graph is compiled into fused oneDNN partitions during its first
    two calls (measured about 1.5x faster at batch 1 on one thread, docs/BENCHMARKS.md). A module's
    compiled plan is kept, so the setting counts at a module's first calls. A torch build without
    oneDNN (some ARM builds) cannot turn it on: this returns False and the policy runs unfused.
    """
    try:
        torch.jit.enable_onednn_fusion(enabled)
        return bool(torch.jit.onednn_fusion_enabled())  # type: ignore[no-untyped-call]
    except (AttributeError, RuntimeError):
        return False


def graph_is_fused() -> bool:
    """Whether the TorchScript graph this thread ran last was compiled into oneDNN partitions."""
    # None before any call on this thread
    graph = torch.jit.last_executed_optimized_graph()  # type: ignore[attr-defined]
    return graph is not None and "prim::oneDNNFusionGroup" in str(graph)


@dataclass(frozen=True)
class LoadedModel:
    """A verified policy: TorchScript module, metadata and the SHA-256 it was loaded with."""

    module: torch.jit.ScriptModule
    metadata: dict[str, Any]
    sha256: str
    path: Path
    reference: Reference | None = None  # from the sidecar; None: exported before the check


def load_model(
    path: str | Path, expected_sha256: str | None = None, map_location: str = "cpu"
) -> LoadedModel:
    """Load and verify a policy file.

    The hash is computed over the exact bytes that are then deserialized. It must equal
    `expected_sha256` when given, and the sidecar's recorded hash when the sidecar exists. The
    sidecar's reference (if any) is parsed here; a malformed one is refused.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"cannot read model file {path}: {exc.strerror}") from exc
    digest = hashlib.sha256(data).hexdigest()
    if expected_sha256 is not None and digest != expected_sha256.lower():
        raise ModelError(
            f"model file {path} has SHA-256 {digest}, but {expected_sha256} was expected: refused"
        )
    sidecar = sidecar_path(path)
    reference = None
    if sidecar.exists():
        try:
            record = json.loads(sidecar.read_text())
            recorded = record["sha256"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ModelError(f"cannot read the recorded hash in {sidecar}: {exc}") from exc
        if digest != recorded:
            raise ModelError(
                f"model file {path} has SHA-256 {digest}, but {sidecar.name} records {recorded}: "
                "refused"
            )
        if SIDECAR_KEY in record:
            reference = reference_from_json(record[SIDECAR_KEY], sidecar.name)
    elif expected_sha256 is None:
        raise ModelError(f"model file {path} has no recorded hash ({sidecar.name} is missing)")
    extra = {METADATA_NAME: ""}
    try:
        with torchscript_calls():
            module = torch.jit.load(  # type: ignore[no-untyped-call]
                io.BytesIO(data), map_location=map_location, _extra_files=extra
            )
    except RuntimeError as exc:
        raise ModelError(f"model file {path} is not a TorchScript module: {exc}") from exc
    try:
        metadata = json.loads(extra[METADATA_NAME])
    except ValueError as exc:
        raise ModelError(f"model file {path} carries no readable {METADATA_NAME}") from exc
    if not isinstance(metadata, dict):
        raise ModelError(f"model file {path}: {METADATA_NAME} is not an object")
    check_metadata(metadata)
    return LoadedModel(
        module=module, metadata=metadata, sha256=digest, path=path, reference=reference
    )
