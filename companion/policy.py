"""The onboard policy: a verified TorchScript file run off the event loop, every output checked.

`Policy.load(config)` loads the policy file with `companion.model_file.load_model` (the SHA-256 from
the config must match, and the sidecar's; the metadata must describe this rig: 64x384 uint8 input
in `layout.FACE_NAMES` order, body-FLU velocity output), sets torch's intra-op threads, turns on
oneDNN Graph fusion (`graph_fusion`, see `companion.model_file.enable_graph_fusion`) and warms the
model up; `fused` then says whether the graph runs as fused oneDNN partitions.

`await policy.infer(image)` runs the model in a dedicated single-thread executor, so the event loop
keeps ticking while it runs (TorchScript releases the GIL). It never raises for what the model
does: an exception, a wrong shape, a NaN/inf or a speed above `max_speed_mps` gives
`PolicyOutput(ok=False, reason=...)` with a zero velocity. At most one inference is in flight: a
call made while the previous one still runs returns `ok=False` ("busy") at once instead of
queueing, and `in_flight_since` (monotonic seconds) lets the daemon notice a hung model.

`infer_batch(images)` is the synchronous batched path for the simulation.
"""

from __future__ import annotations

import asyncio
import logging
import queue
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
from companion.errors import ConfigError
from companion.model_file import (
    LoadedModel,
    check_metadata,
    enable_graph_fusion,
    graph_is_fused,
    load_model,
)
from companion.sections import section_from_dict
from companion.validation import require_int_range, require_range

log = logging.getLogger(__name__)

SECTION = "policy"
IMAGE_SHAPE = (IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX)
_SHA256_RE = re.compile(r"^[0-9a-fA-F]{64}$")

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


def _image_error(image: NDArray[Any]) -> str:
    if image.dtype != np.uint8 or image.shape != IMAGE_SHAPE:
        return f"input must be uint8 {IMAGE_SHAPE}, got {image.dtype} {image.shape}"
    return ""


class _ModelThread:
    """One daemon thread that runs submitted calls in order; at most `capacity` waiting.

    A daemon thread (not a ThreadPoolExecutor, whose threads are joined at interpreter exit) so
    that a hung model cannot keep the process from exiting.
    """

    def __init__(self, name: str, capacity: int = 1) -> None:
        self._jobs: queue.Queue[tuple[Callable[[], Any], Future[Any]] | None] = queue.Queue(
            maxsize=capacity
        )
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fn, future = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn())
            except BaseException as exc:  # handed to the caller through the future
                future.set_exception(exc)

    def submit(self, fn: Callable[[], Any]) -> Future[Any]:
        """Queue `fn`; raises RuntimeError when closed or full."""
        if self._closed:
            raise RuntimeError("the model thread is closed")
        future: Future[Any] = Future()
        try:
            self._jobs.put_nowait((fn, future))
        except queue.Full:
            raise RuntimeError("the model thread is busy") from None
        return future

    def close(self, timeout_s: float) -> bool:
        """Stop after the running call; True if the thread ended within `timeout_s`."""
        if not self._closed:
            self._closed = True
            try:
                self._jobs.put(None, timeout=timeout_s)
            except queue.Full:
                return False
        self._thread.join(timeout_s)
        return not self._thread.is_alive()


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
        self._thread = _ModelThread("policy")
        self._lock = threading.Lock()
        self._in_flight_since: float | None = None
        self.warmup_latency_s: float | None = None
        self.fused = False  # whether the warmed-up graph runs as fused oneDNN partitions

    @classmethod
    def load(cls, config: PolicyConfig, *, clock: Callable[[], float] = time.monotonic) -> Policy:
        """Load and verify the file (raises `ModelError`), set threads, warm up (blocking)."""
        loaded = load_model(config.model_path, expected_sha256=config.sha256)
        torch.set_num_threads(config.threads)
        fusion = enable_graph_fusion(config.graph_fusion)
        if config.graph_fusion and not fusion:
            log.warning("oneDNN Graph fusion is not available in this torch build: running unfused")
        policy = cls(loaded, config, clock=clock)
        try:
            policy.warm_up()
        except BaseException:
            policy.close()
            raise
        log.info(
            "policy %s loaded (sha256 %s), warm-up %.1f ms, %s",
            loaded.path,
            loaded.sha256[:12],
            1e3 * (policy.warmup_latency_s or 0.0),
            "fused (oneDNN Graph)" if policy.fused else "unfused",
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

    def warm_up(self) -> None:
        """Run `warmup_runs` inferences on a grey image on the worker thread (blocking)."""
        if self.config.warmup_runs == 0:
            return
        grey = torch.full((1, *IMAGE_SHAPE), 128, dtype=torch.uint8)

        def run() -> tuple[float, bool]:
            start = self._clock()
            for _ in range(self.config.warmup_runs):
                self._run_model(grey)
            return (self._clock() - start) / self.config.warmup_runs, graph_is_fused()

        self.warmup_latency_s, self.fused = self._thread.submit(run).result()

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
