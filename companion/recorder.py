"""MCAP flight recorder: bounded queue + writer thread, so the control loop never waits on disk.

`record*()` encodes the message as JSON on the caller's thread (microseconds; a 64x384 frame is
~33 kB of base64) and hands it to a bounded queue; when the queue is full the message is dropped
and counted, never waited for. The writer thread appends to the current MCAP file (zstd chunks).

Crash safety: the writer finishes the current chunk and flushes it to the OS at least every
`flush_every_s` (default 1 s), also when no new message arrives, so a killed process loses at most
about that much; the file stays readable without its footer (`companion.flight_log.LogReader`
stops at the first incomplete record; `recover_log` rewrites a complete file). Data reach the
disk when the kernel writes them back; `fsync=True` forces that at every flush (power loss).

Rotation: a new file after `max_file_mb` or `max_file_s`, named
`{file_prefix}_{session start, UTC}_{index:03d}.mcap`; every file carries the schemas, channels and
a `flight` metadata record, so each opens on its own. Format and topics: `companion.flight_log`.

Housekeeping (`companion.log_budget`): the file being written is held under an exclusive
`flock`, so other processes (the ground station's `logs pull`) can tell it from closed files;
with `max_total_mb` set, opening a file first deletes the oldest closed `*.mcap` files of the
folder until they plus one full file (`max_file_mb`) fit, and records each deletion as a
`log deleted` health event (warning) in the new file.
"""

from __future__ import annotations

import base64
import itertools
import logging
import os
import queue
import re
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from companion import jsonable
from companion.errors import ConfigError, RecorderError
from companion.flight_log import (
    CHANNELS,
    TOPIC_FRAME,
    TOPIC_HEALTH,
    TOPIC_POLICY,
    TOPIC_SETPOINT,
    TOPIC_TELEMETRY,
    format_summary,
    summarize_log,
)
from companion.log_budget import lock_for_writing, make_room
from companion.sections import require_bool, section_from_dict
from companion.validation import require_int_range, require_range

log = logging.getLogger(__name__)

SECTION = "recorder"
_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
HEALTH_LEVELS = ("info", "warning", "error")

__all__ = [
    "TOPIC_FRAME",
    "TOPIC_HEALTH",
    "TOPIC_POLICY",
    "TOPIC_SETPOINT",
    "TOPIC_TELEMETRY",
    "FlightRecorder",
    "RecorderConfig",
    "RecorderStats",
    "format_summary",
    "summarize_log",
]


@dataclass(frozen=True)
class RecorderConfig:
    """The `[recorder]` section."""

    directory: Path = Path("flights")
    enabled: bool = True
    max_file_mb: float = 512.0  # start a new file beyond this size
    max_file_s: float = 900.0  # ... or after this long
    frame_every_n: int = 1  # record every n-th stitched frame (1: all, 10 Hz)
    flush_every_s: float = 1.0  # at most this much is lost when the process is killed
    fsync: bool = False  # also fsync at every flush (survives power loss; costs SD-card time)
    queue_size: int = 256  # messages waiting for the writer; beyond: dropped and counted
    file_prefix: str = "flight"
    max_total_mb: float | None = None  # all *.mcap in `directory`; None: no budget

    def __post_init__(self) -> None:
        s = SECTION
        if not isinstance(self.directory, str | Path) or not str(self.directory).strip():
            raise ConfigError(f"{s}.directory: expected a directory path, got {self.directory!r}")
        object.__setattr__(self, "directory", Path(self.directory))
        require_bool(f"{s}.enabled", self.enabled)
        require_range(f"{s}.max_file_mb", self.max_file_mb, 0.0, 1e6, low_inclusive=False)
        require_range(f"{s}.max_file_s", self.max_file_s, 0.0, 86400.0, low_inclusive=False)
        require_int_range(f"{s}.frame_every_n", self.frame_every_n, 1, 10000)
        require_range(f"{s}.flush_every_s", self.flush_every_s, 0.01, 60.0)
        require_bool(f"{s}.fsync", self.fsync)
        require_int_range(f"{s}.queue_size", self.queue_size, 1, 100_000)
        if self.max_total_mb is not None:
            require_range(f"{s}.max_total_mb", self.max_total_mb, 0.0, 1e9, low_inclusive=False)
            if self.max_total_mb < self.max_file_mb:
                raise ConfigError(
                    f"{s}.max_total_mb: {self.max_total_mb:g} is below {s}.max_file_mb "
                    f"({self.max_file_mb:g}); allowed range [max_file_mb, 1e9] MB"
                )
        if not isinstance(self.file_prefix, str) or not _PREFIX_RE.match(self.file_prefix):
            raise ConfigError(
                f"{s}.file_prefix: {self.file_prefix!r} must be 1-64 of A-Z a-z 0-9 _ . -"
            )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], base_dir: Path | None = None) -> RecorderConfig:
        """From the parsed `[recorder]` table; a relative `directory` is taken from `base_dir`."""
        overrides: dict[str, Any] = {}
        directory = data.get("directory") if isinstance(data, Mapping) else None
        if isinstance(directory, str) and directory.strip() and base_dir is not None:
            overrides["directory"] = Path(base_dir) / Path(directory).expanduser()
        return section_from_dict(cls, SECTION, data, **overrides)


@dataclass(frozen=True)
class RecorderStats:
    """Counters for health reporting."""

    queued: int  # accepted by record*()
    written: int  # handed to the MCAP writer
    dropped: int  # refused: queue full, recorder stopped or failed
    files: tuple[Path, ...]
    error: str | None  # the write error that stopped the recorder, if any


_STOP = object()
_Item = tuple[str, int, int, int, bytes]  # topic, log ns, publish ns, sequence, JSON


class FlightRecorder:
    """Thread-safe, non-blocking flight recorder. `start()`, `record*()`, `close()`.

    `clock_ns` gives log times (ns since the Unix epoch); `monotonic` paces flushes and rotation.
    When `config.enabled` is False every call is a cheap no-op.
    """

    def __init__(
        self,
        config: RecorderConfig,
        *,
        drone_id: str = "",
        metadata: Mapping[str, str] | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self._drone_id = drone_id
        self._metadata = dict(metadata or {})
        self._clock_ns = clock_ns
        self._monotonic = monotonic
        self._queue: queue.Queue[_Item | object] = queue.Queue(maxsize=config.queue_size)
        self._sequences = {topic: itertools.count() for topic, _, _ in CHANNELS}
        self._frame_calls = itertools.count()
        self._bad_topics: set[str] = set()
        self._thread: threading.Thread | None = None
        self._accepting = False
        self._queued = 0
        self._written = 0
        self._dropped = 0
        self._error: str | None = None
        self._files: list[Path] = []
        self._session = ""
        # Writer-thread state.
        self._stream: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._channel_ids: dict[str, int] = {}
        self._file_opened_s = 0.0
        self._pending_bytes = 0
        self._file_messages = 0
        self._last_flush_s = 0.0

    # --- lifecycle -------------------------------------------------------------------------

    def start(self) -> None:
        """Open the first file and start the writer thread (raises `RecorderError` on failure)."""
        if not self.config.enabled or self._thread is not None:
            return
        stamp = datetime.fromtimestamp(self._clock_ns() / 1e9, tz=UTC)
        self._session = stamp.strftime("%Y%m%dT%H%M%SZ")
        try:
            self.config.directory.mkdir(parents=True, exist_ok=True)
            self._open_file(0)
        except OSError as exc:
            raise RecorderError(
                f"cannot start recording in {self.config.directory}: {exc}"
            ) from exc
        self._accepting = True
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is queued, finish the file (summary + footer) and stop the thread."""
        self._accepting = False
        thread = self._thread
        if thread is None:
            return
        if not thread.is_alive():  # stopped by a write error; the file is already closed
            self._thread = None
            return
        try:
            self._queue.put(_STOP, timeout=timeout_s)
        except queue.Full:
            log.error("recorder: writer thread stuck; file left without footer")
            return
        thread.join(timeout_s)
        if thread.is_alive():
            log.error("recorder: writer thread did not finish within %.1f s", timeout_s)
        self._thread = None

    def __enter__(self) -> FlightRecorder:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def files(self) -> tuple[Path, ...]:
        return tuple(self._files)

    def stats(self) -> RecorderStats:
        return RecorderStats(self._queued, self._written, self._dropped, self.files, self._error)

    # --- producers (any thread) -------------------------------------------------------------

    def record(
        self, topic: str, payload: Mapping[str, Any], *, publish_time_ns: int | None = None
    ) -> bool:
        """Queue one JSON message on a known topic; False if it was dropped.

        Never blocks and never raises for what it is given: an unknown topic or a payload that
        cannot be encoded is dropped, counted and logged (once per topic).
        """
        if not self._accepting:
            if self.config.enabled:
                self._dropped += 1
            return False
        sequences = self._sequences.get(topic)
        try:
            if sequences is None:
                raise ValueError(f"unknown topic; topics: {', '.join(self._sequences)}")
            data = jsonable.dumps(payload)
        except (TypeError, ValueError) as exc:
            self._dropped += 1
            if topic not in self._bad_topics:
                self._bad_topics.add(topic)
                log.error("recorder: dropping a message on %r: %s", topic, exc)
            return False
        log_ns = self._clock_ns()
        publish_ns = log_ns if publish_time_ns is None else int(publish_time_ns)
        item = (topic, log_ns, publish_ns, next(sequences), data)
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self._dropped += 1
            return False
        self._queued += 1
        return True

    def record_frame(
        self,
        image_u8: NDArray[np.uint8],
        *,
        publish_time_ns: int | None = None,
        frame_id: str = "camera_rig",
    ) -> bool:
        """Queue every `frame_every_n`-th stitched image as a foxglove.RawImage (mono8)."""
        if not self._accepting or next(self._frame_calls) % self.config.frame_every_n:
            return False
        image = np.ascontiguousarray(image_u8)
        if image.dtype != np.uint8 or image.ndim != 2:
            self._dropped += 1
            log.error("recorder: not a 2-D uint8 image: %s %s", image.dtype, image.shape)
            return False
        stamp_ns = self._clock_ns() if publish_time_ns is None else int(publish_time_ns)
        height, width = image.shape
        message = {
            "timestamp": {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000},
            "frame_id": frame_id,
            "width": width,
            "height": height,
            "encoding": "mono8",
            "step": width,
            "data": base64.b64encode(image.tobytes()).decode("ascii"),
        }
        return self.record(TOPIC_FRAME, message, publish_time_ns=stamp_ns)

    def record_health(
        self,
        event: str,
        level: str = "info",
        detail: Any = "",
        *,
        publish_time_ns: int | None = None,
    ) -> bool:
        """Queue a health event (`level` one of info, warning, error)."""
        if level not in HEALTH_LEVELS:
            raise ValueError(f"level must be one of {HEALTH_LEVELS}, got {level!r}")
        payload = {"level": level, "event": event, "detail": detail}
        return self.record(TOPIC_HEALTH, payload, publish_time_ns=publish_time_ns)

    # --- writer thread ------------------------------------------------------------------------

    def _path(self, index: int) -> Path:
        prefix = self.config.file_prefix
        if self._drone_id:
            prefix = f"{prefix}_{self._drone_id}"
        return self.config.directory / f"{prefix}_{self._session}_{index:03d}.mcap"

    def _open_file(self, index: int) -> None:
        events = make_room(self.config.directory, self.config.max_total_mb, self.config.max_file_mb)
        path = self._path(index)
        stream = open(path, "xb")  # noqa: SIM115 - closed in _close_file
        lock_for_writing(stream)
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="vision-swarm companion")
        self._channel_ids = {}
        for topic, name, schema in CHANNELS:
            schema_id = writer.register_schema(name, "jsonschema", jsonable.dumps(schema))
            self._channel_ids[topic] = writer.register_channel(topic, "json", schema_id)
        info = {
            "drone_id": self._drone_id,
            "session": self._session,
            "file_index": str(index),
            **self._metadata,
        }
        writer.add_metadata("flight", info)
        for event in events:
            stamp_ns = self._clock_ns()
            writer.add_message(
                self._channel_ids[TOPIC_HEALTH],
                log_time=stamp_ns,
                data=jsonable.dumps(event),
                publish_time=stamp_ns,
                sequence=next(self._sequences[TOPIC_HEALTH]),
            )
        stream.flush()
        self._stream, self._writer = stream, writer
        self._files.append(path)
        self._file_opened_s = self._monotonic()
        self._last_flush_s = self._file_opened_s
        self._pending_bytes = 0
        self._file_messages = 0
        log.info("recording to %s", path)

    def _close_file(self) -> None:
        writer, stream = self._writer, self._stream
        self._writer = self._stream = None
        if writer is not None and stream is not None:
            try:
                writer.finish()  # type: ignore[no-untyped-call]
                stream.flush()
                if self.config.fsync:
                    os.fsync(stream.fileno())
            finally:
                stream.close()

    def _flush(self, now_s: float) -> None:
        if self._writer is None or self._stream is None:
            return
        self._writer.flush()  # type: ignore[no-untyped-call]
        if self.config.fsync:
            os.fsync(self._stream.fileno())
        self._pending_bytes = 0
        self._last_flush_s = now_s

    def _rotation_due(self, now_s: float, incoming: int) -> bool:
        if self._stream is None:
            return False
        size = self._stream.tell() + self._pending_bytes + incoming
        too_big = size > self.config.max_file_mb * 1e6
        too_long = now_s - self._file_opened_s >= self.config.max_file_s
        return too_big or too_long

    def _write(self, item: _Item, now_s: float) -> None:
        topic, log_ns, publish_ns, sequence, data = item
        if self._file_messages and self._rotation_due(now_s, len(data)):
            self._close_file()
            self._open_file(len(self._files))
        assert self._writer is not None
        self._writer.add_message(
            self._channel_ids[topic],
            log_time=log_ns,
            data=data,
            publish_time=publish_ns,
            sequence=sequence,
        )
        self._pending_bytes += len(data) + 40
        self._file_messages += 1
        self._written += 1

    def _run(self) -> None:
        flush_s = self.config.flush_every_s
        try:
            while True:
                timeout = None
                if self._pending_bytes:
                    timeout = max(0.0, self._last_flush_s + flush_s - self._monotonic())
                try:
                    item = self._queue.get(timeout=timeout)
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                now_s = self._monotonic()
                if item is not None:
                    self._write(item, now_s)  # type: ignore[arg-type]
                if self._pending_bytes and now_s - self._last_flush_s >= flush_s:
                    self._flush(now_s)
        except OSError as exc:
            self._error = f"{type(exc).__name__}: {exc}"
            self._accepting = False
            log.error("recorder stopped: %s", self._error)
        finally:
            try:
                self._close_file()
            except OSError as exc:
                self._error = self._error or f"{type(exc).__name__}: {exc}"
                log.error("recorder: cannot finish the file: %s", exc)
