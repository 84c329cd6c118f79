"""The onboard policy: a verified TorchScript file run off the event loop, every output checked.

`Policy.load(config)` loads the policy file with `companion.model_file.load_model` (the SHA-256 from
the config must match, and the sidecar's; the metadata must describe this rig: 64x384 uint8 input
in `layout.FACE_NAMES` order, body-FLU velocity output), sets torch's intra-op threads, turns on
oneDNN Graph fusion (`graph_fusion`, see `companion.model_file.enable_graph_fusion`), warms the
model up and runs the platform check: the warmed-up policy on the reference image recorded at
export (`companion.model_reference`) must give the recorded output within its tolerance. A model
that fails at warm-up or gives a wrong reference output is refused (`ModelError`, one line); one
whose sidecar has no reference (exported before the check) loads with a warning. `fused` then says
whether the graph runs as fused oneDNN partitions.

`await policy.infer(image)` runs the model in a dedicated single-thread executor, so the event loop
keeps ticking while it runs (TorchScript releases the GIL). It never raises for what the model
does: an exception, a wrong shape, a NaN/inf or a speed above `max_speed_mps` gives
`PolicyOutput(ok=False, reason=...)` with a zero velocity. At most one inference is in flight: a
call made while the previous one still runs returns `ok=False` ("busy") at once instead of
queueing, and `in_flight_since` (monotonic seconds) lets the daemon notice a hung model. A call
still running at `close` is abandoned (`companion.model_thread`: the process must then end with
`os._exit`, as `companion.cli.main` does).

`infer_batch(images)` is the synchronous batched path for the simulation.
"""

from __future__ import annotations

import asyncio
import logging
import re
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.errors import ConfigError, ModelError
from companion.model_file import (
    LoadedModel,
    check_metadata,
    enable_graph_fusion,
    graph_is_fused,
    load_model,
)
from companion.model_thread import ModelThread
from companion.sections import section_from_dict
from companion.validation import require_int_range, require_range

log = logging.getLogger(__name__)

SECTION = "policy"
IMAGE_SHAPE = (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX)
_SHA256_RE = re.compile(r"^[0-9a-fA-F]{64}$")
REFERENCE_RUNS = 3  # oneDNN Graph compiles its fused partitions in the first 2 calls of a graph
_ERROR_LINE_RE = re.compile(r"^[A-Za-z_][\w.]*(Error|Exception)\b.*")

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PolicyConfig:
    """The `[policy]` section."""

    model_path: Path  # NAME.pt; its sidecar NAME.json records the hash
    sha256: str | None = None  # expected hex digest; None: trust the sidecar's
    max_speed_mps: float = 10.0  # a larger output speed is treated as a model failure
    threads: int = 1  # torch intra-op threads (process-wide setting)
    warmup_runs: int = 3
    graph_fusion: bool = True  # oneDNN Graph fusion of the TorchScript graph (process-wide)

    def __post_init__(self) -> None:
        s = SECTION
        if not isinstance(self.model_path, str | Path) or not str(self.model_path).strip():
            raise ConfigError(f"{s}.model_path: expected a file path, got {self.model_path!r}")
        object.__setattr__(self, "model_path", Path(self.model_path))
        if self.sha256 is not None:
            if not isinstance(self.sha256, str) or not _SHA256_RE.match(self.sha256):
                raise ConfigError(f"{s}.sha256: expected 64 hex digits, got {self.sha256!r}")
            object.__setattr__(self, "sha256", self.sha256.lower())
        require_range(f"{s}.max_speed_mps", self.max_speed_mps, 0.0, 100.0, low_inclusive=False)
        require_int_range(f"{s}.threads", self.threads, 1, 64)
        require_int_range(f"{s}.warmup_runs", self.warmup_runs, 0, 1000)
        if not isinstance(self.graph_fusion, bool):
            got = self.graph_fusion
            raise ConfigError(f"{s}.graph_fusion: expected true or false, got {got!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base_dir: Path | None = None) -> PolicyConfig:
        """From the parsed `[policy]` table; a relative `model_path` is taken from `base_dir`."""
        overrides: dict[str, Any] = {}
        path = data.get("model_path") if isinstance(data, Mapping) else None
        if isinstance(path, str) and path.strip() and base_dir is not None:
            overrides["model_path"] = Path(base_dir) / Path(path).expanduser()
        return section_from_dict(cls, SECTION, data, **overrides)


@dataclass(frozen=True)
class PolicyOutput:
    """One inference: body-frame (FLU) velocity in m/s, zero unless `ok`."""

    vel_body_flu: FloatArray  # (3,)
    latency_s: float  # from the call to the result (monotonic clock)
    ok: bool
    reason: str = ""  # why not ok; "" when ok
    raw: list[float] | None = field(default=None)  # the model's output when it was refused

    def as_dict(self) -> dict[str, Any]:
        """Plain values for the flight log and telemetry."""
        return {
            "vel_body_flu": self.vel_body_flu.tolist(),
            "latency_s": self.latency_s,
            "ok": self.ok,
            "reason": self.reason,
            "raw": self.raw,
        }


def check_output(vel: NDArray[Any], max_speed_mps: float) -> str:
    """'' if `vel` is a finite (3,) velocity with |vel| <= max_speed_mps, else the reason."""
    if vel.shape != (3,):
        return f"output shape {tuple(vel.shape)}, expected (3,)"
    if not np.all(np.isfinite(vel)):
        return "non-finite output"
    speed = float(np.linalg.norm(vel))
    if speed > max_speed_mps:
        return f"output speed {speed:.3g} m/s exceeds the bound {max_speed_mps:g} m/s"
    return ""


def error_line(exc: BaseException) -> str:
    """The one line of an exception that says what went wrong (not torch's traceback).

    TorchScript errors start with "The following operation failed in the TorchScript
    interpreter." and a TorchScript traceback, then the original error ("RuntimeError: mat1 and
    mat2 shapes cannot be multiplied ..."); other torch errors start with it and may go on with a
    C++ stack.
    """
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if not lines:
        return type(exc).__name__
    if lines[0].startswith("The following operation failed"):
        found = [line for line in lines[1:] if _ERROR_LINE_RE.match(line)]
        return found[-1] if found else lines[-1]
    return f"{type(exc).__name__}: {lines[0]}"


def _image_error(image: NDArray[Any]) -> str:
    if image.dtype != np.uint8 or image.shape != IMAGE_SHAPE:
        return f"input must be uint8 {IMAGE_SHAPE}, got {image.dtype} {image.shape}"
    return ""


class Policy:
    """A loaded, verified, warmed-up policy. Create with `Policy.load(config)`; `close()` after.

    `_run_model` (the model call on the worker thread) is the one place to wrap in tests.
    """

    def __init__(
        self,
        loaded: LoadedModel,
        config: PolicyConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        check_metadata(loaded.metadata)
        self.loaded = loaded
        self.config = config
        self._clock = clock
        self._thread = ModelThread("policy")
        self._lock = threading.Lock()
        self._in_flight_since: float | None = None
        self.warmup_latency_s: float | None = None
        self.fused = False  # whether the warmed-up graph runs as fused oneDNN partitions
        self.reference_error_mps: float | None = None  # the platform check's; None: no reference

    @classmethod
    def load(cls, config: PolicyConfig, *, clock: Callable[[], float] = time.monotonic) -> Policy:
        """Load and verify the file, set threads, warm up, check the reference output (blocking).

        Raises `ModelError` (one line) for a file, metadata, warm-up or reference output refused.
        """
        loaded = load_model(config.model_path, expected_sha256=config.sha256)
        torch.set_num_threads(config.threads)
        fusion = enable_graph_fusion(config.graph_fusion)
        if config.graph_fusion and not fusion:
            log.warning("oneDNN Graph fusion is not available in this torch build: running unfused")
        policy = cls(loaded, config, clock=clock)
        try:
            policy.warm_up()
            policy.check_reference()
        except BaseException:
            policy.close()
            raise
        log.info(
            "policy %s loaded (sha256 %s), warm-up %.1f ms, %s, %s",
            loaded.path,
            loaded.sha256[:12],
            1e3 * (policy.warmup_latency_s or 0.0),
            "fused (oneDNN Graph)" if policy.fused else "unfused",
            policy.reference_text,
        )
        return policy

    @property
    def sha256(self) -> str:
        return self.loaded.sha256

    @property
    def metadata(self) -> dict[str, Any]:
        return self.loaded.metadata

    @property
    def in_flight_since(self) -> float | None:
        """Monotonic time the running inference started, or None when idle."""
        return self._in_flight_since

    @property
    def reference_text(self) -> str:
        """The platform check's result in words, for logs."""
        reference, error = self.loaded.reference, self.reference_error_mps
        if reference is None or error is None:
            return "no reference output to check (exported before the platform check)"
        return f"reference output within {error:.2g} m/s (tolerance {reference.tolerance_mps:g})"

    def check_reference(self) -> float | None:
        """Run the policy on its reference image as it flies (batch 1 through `_worker`, on the
        worker thread, `REFERENCE_RUNS` times); the largest error in m/s, None without a reference.

        Raises `ModelError` when an output differs from the recorded one by more than the
        reference's tolerance: this platform does not compute the policy that was exported.
        """
        reference, path = self.loaded.reference, self.loaded.path
        if reference is None:
            log.warning(
                "policy %s: its sidecar has no reference output (exported before the platform "
                "check): loaded without checking that this platform computes it right; re-export "
                "it or add one with sim_harness.learning.export.add_reference",
                path,
            )
            return None

        def run() -> list[NDArray[Any]]:
            return [self._worker(reference.image_u8) for _ in range(REFERENCE_RUNS)]

        try:
            outputs = self._thread.submit(run).result()
        except Exception as exc:
            raise ModelError(
                f"model {path} failed on its reference input: {error_line(exc)}: refused"
            ) from exc
        error = max(reference.error_mps(out) for out in outputs)
        if not error <= reference.tolerance_mps:
            got = np.array2string(np.asarray(outputs[-1]).reshape(-1), precision=4)
            expected = np.array2string(np.array(reference.output_body_flu_mps), precision=4)
            raise ModelError(
                f"model {path} gives {got} m/s on its reference input, {expected} recorded at "
                f"export: max error {error:.3g} m/s exceeds the tolerance "
                f"{reference.tolerance_mps:g} m/s (this platform computes the policy wrongly): "
                "refused"
            )
        self.reference_error_mps = error
        return error

    def warm_up(self) -> None:
        """Run `warmup_runs` inferences on a grey image on the worker thread (blocking).

        Raises `ModelError` with the model's error in one line if a call fails.
        """
        if self.config.warmup_runs == 0:
            return
        grey = torch.full((1, *IMAGE_SHAPE), 128, dtype=torch.uint8)

        def run() -> tuple[float, bool]:
            start = self._clock()
            for _ in range(self.config.warmup_runs):
                self._run_model(grey)
            return (self._clock() - start) / self.config.warmup_runs, graph_is_fused()

        try:
            self.warmup_latency_s, self.fused = self._thread.submit(run).result()
        except Exception as exc:
            path = self.loaded.path
            raise ModelError(f"model {path} failed at warm-up: {error_line(exc)}: refused") from exc

    def _run_model(self, batch_u8: torch.Tensor) -> torch.Tensor:
        """The model call: (B, 64, 384) uint8 -> (B, 3) float; runs on the worker thread."""
        with torch.inference_mode():
            out = self.loaded.module(batch_u8)
        if not isinstance(out, torch.Tensor):
            raise TypeError(f"the model returned {type(out).__name__}, not a tensor")
        return out

    def _worker(self, image: NDArray[np.uint8]) -> NDArray[Any]:
        batch = torch.from_numpy(np.ascontiguousarray(image)).unsqueeze(0)
        out = np.asarray(self._run_model(batch).detach().to(torch.float64).numpy())
        return out[0] if out.ndim == 2 and out.shape[0] == 1 else out

    def _finished(self, _future: Future[Any]) -> None:
        # Runs when the call ends, fails or is cancelled before it started (never stays set).
        with self._lock:
            self._in_flight_since = None

    async def infer(self, image_u8: NDArray[np.uint8]) -> PolicyOutput:
        """Body-FLU velocity for one stitched (64, 384) uint8 image; never raises for bad outputs.

        Cancelling the caller does not stop the model: `in_flight_since` stays set until the
        worker returns, and calls made meanwhile get `ok=False` ("busy").
        """
        start = self._clock()
        image = np.asarray(image_u8)
        problem = _image_error(image)
        if problem:
            return self._refused(start, problem)
        with self._lock:
            if self._in_flight_since is not None:
                since = self._in_flight_since
                return self._refused(
                    start, f"busy: the previous inference has run for {start - since:.3f} s"
                )
            self._in_flight_since = start
        try:
            future = self._thread.submit(lambda: self._worker(image))
        except RuntimeError as exc:  # closed
            with self._lock:
                self._in_flight_since = None
            return self._refused(start, f"policy unavailable: {exc}")
        future.add_done_callback(self._finished)
        try:
            vel = await asyncio.wrap_future(future)
        except Exception as exc:  # whatever the model raised must not reach the control loop
            # TorchScript errors end with the original exception ("builtins.RuntimeError: ...").
            text = str(exc).strip()
            last_line = text.splitlines()[-1] if text else type(exc).__name__
            log.warning("policy inference failed: %s", last_line)
            return self._refused(start, f"model error: {last_line}")
        reason = check_output(vel, self.config.max_speed_mps)
        if reason:
            raw = [float(v) for v in vel.reshape(-1)[:16]]
            return self._refused(start, reason, raw)
        return PolicyOutput(vel_body_flu=vel, latency_s=self._clock() - start, ok=True)

    def _refused(self, start: float, reason: str, raw: list[float] | None = None) -> PolicyOutput:
        return PolicyOutput(
            vel_body_flu=np.zeros(3),
            latency_s=self._clock() - start,
            ok=False,
            reason=reason,
            raw=raw,
        )

    def infer_batch(self, images_u8: NDArray[np.uint8], *, zero_invalid: bool = True) -> FloatArray:
        """Body-FLU velocities (B, 3) float64 for images (B, 64, 384) uint8, on the caller's thread.

        Rows that fail `check_output` (non-finite, too fast) are zeroed (hover), as on the drone,
        unless `zero_invalid` is False. Raises ValueError for a wrong input or output shape.
        """
        images = np.asarray(images_u8)
        if images.dtype != np.uint8 or images.ndim != 3 or images.shape[1:] != IMAGE_SHAPE:
            expected = f"uint8 (B, {IMAGE_SHAPE[0]}, {IMAGE_SHAPE[1]})"
            raise ValueError(f"images must be {expected}, got {images.dtype} {images.shape}")
        out = self._run_model(torch.from_numpy(np.ascontiguousarray(images)))
        vel = np.asarray(out.detach().to(torch.float64).numpy())
        if vel.shape != (images.shape[0], 3):
            raise ValueError(f"model output shape {vel.shape}, expected ({images.shape[0]}, 3)")
        if zero_invalid:
            speed = np.linalg.norm(vel, axis=1)
            good = np.all(np.isfinite(vel), axis=1) & (speed <= self.config.max_speed_mps)
            vel = np.where(good[:, None], vel, 0.0)
        return vel

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop the worker thread, waiting at most `timeout_s` for a running inference.

        A model still running after that is abandoned (its daemon thread ends with the process).
        """
        if not self._thread.close(timeout_s):
            log.warning("policy: an inference was still running at close; abandoned")

    def __enter__(self) -> Policy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
