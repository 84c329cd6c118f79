"""The flight log format (MCAP + JSON) and its reader, which also reads files cut short by a crash.

Topics (every message JSON, schema encoding `jsonschema`, message encoding `json`; times in ns
since the Unix epoch; `log_time` = when the recorder got it, `publish_time` = when it happened,
e.g. the image capture time):

| topic                  | schema             | content                                        |
|------------------------|--------------------|------------------------------------------------|
| /camera/stitched       | foxglove.RawImage  | 64x384 `mono8` stitched image, data base64     |
| /policy/output         | swarm.PolicyOutput | body-FLU velocity, latency, ok, reason         |
| /control/setpoint      | swarm.Setpoint     | every stage of the control law, NED setpoint   |
| /autopilot/telemetry   | swarm.Telemetry    | what the autopilot reported                    |
| /health                | swarm.HealthEvent  | level, event, detail                           |
| /cameras               | swarm.CameraLinks  | per face: fps, parser error counters, last error |

`/cameras` is written when a counter, the last error or the connection changes (checked every
0.5 s) and at least every 5 s otherwise; `summarize_log` keeps the last one (final counters).

Foxglove opens the file as is: `foxglove.RawImage` in JSON encoding is one of its built-in image
schemas (raw `mono8` is exact and needs no image codec on the drone).

Reading: `LogReader` walks the file front to back (MCAP's stream reader, chunk CRCs checked) and
stops cleanly at the first incomplete record. A writer killed mid-flight leaves a file without a
summary or footer whose last chunk may be cut: everything before it is read. `recover_log`
rewrites what is readable into a complete, indexed file.
"""

from __future__ import annotations

import contextlib
import json
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from companion.errors import RecorderError

MCAP_MAGIC = b"\x89MCAP0\r\n"  # the first 8 bytes of every MCAP file (a crash-cut one included)
TOPIC_FRAME = "/camera/stitched"
TOPIC_POLICY = "/policy/output"
TOPIC_SETPOINT = "/control/setpoint"
TOPIC_TELEMETRY = "/autopilot/telemetry"
TOPIC_HEALTH = "/health"
TOPIC_CAMERAS = "/cameras"

_UINT = {"type": "integer", "minimum": 0}
RAW_IMAGE_SCHEMA: dict[str, Any] = {
    "title": "foxglove.RawImage",
    "description": "A raw image (Foxglove's RawImage fields, JSON encoding)",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {"sec": _UINT, "nsec": {**_UINT, "maximum": 999_999_999}},
        },
        "frame_id": {"type": "string"},
        "width": _UINT,
        "height": _UINT,
        "encoding": {"type": "string"},
        "step": _UINT,
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


def _object_schema(title: str, properties: dict[str, str]) -> dict[str, Any]:
    return {
        "title": title,
        "type": "object",
        "properties": {name: {"description": text} for name, text in properties.items()},
    }


# (topic, schema name, JSON schema), in channel order.
CHANNELS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    (TOPIC_FRAME, "foxglove.RawImage", RAW_IMAGE_SCHEMA),
    (
        TOPIC_POLICY,
        "swarm.PolicyOutput",
        _object_schema(
            "swarm.PolicyOutput",
            {
                "vel_body_flu": "[x, y, z] m/s, body FLU",
                "latency_s": "inference latency, s",
                "ok": "output passed the checks",
                "reason": "why not ok",
            },
        ),
    ),
    (
        TOPIC_SETPOINT,
        "swarm.Setpoint",
        _object_schema(
            "swarm.Setpoint",
            {
                "vel_final_enu": "flown velocity, world ENU m/s",
                "vel_ned": "setpoint sent to PX4, NED m/s",
                "yaw_ned_rad": "yaw setpoint, NED rad",
            },
        ),
    ),
    (TOPIC_TELEMETRY, "swarm.Telemetry", _object_schema("swarm.Telemetry", {})),
    (
        TOPIC_HEALTH,
        "swarm.HealthEvent",
        _object_schema(
            "swarm.HealthEvent",
            {"level": "info | warning | error", "event": "short name", "detail": "free form"},
        ),
    ),
    (
        TOPIC_CAMERAS,
        "swarm.CameraLinks",
        _object_schema(
            "swarm.CameraLinks",
            {
                "<face>": "fps (last 2 s), bad_headers, bad_payloads, dropped_bytes, seq_gaps "
                "(counts since start), last_error, connected, camera_uid, frames_ok",
            },
        ),
    ),
)


@dataclass(frozen=True)
class LogMessage:
    """One message read back: topic, times (ns since the epoch), sequence and raw JSON bytes."""

    topic: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    data: bytes

    def json(self) -> Any:
        return json.loads(self.data)


# What a file cut short by a crash raises somewhere inside the stream reader.
_TRUNCATION_ERRORS = (McapError, struct.error, zstandard.ZstdError, ValueError, UnicodeDecodeError)


def require_mcap(path: Path) -> None:
    """Raise `RecorderError` unless `path` starts like an MCAP file.

    A file cut short anywhere passes: an empty one or one holding part of the magic is a writer
    killed before its first flush (an empty, incomplete log), not another kind of file.
    """
    with open(path, "rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC[: len(head)]:
        raise RecorderError(
            f"{path}: not an MCAP file (starts with {head!r}; a flight log starts with "
            f"{MCAP_MAGIC!r})"
        )


@dataclass
class LogReader:
    """Front-to-back reader of one flight log that tolerates a missing end.

    After `messages()` is exhausted: `complete` tells whether the footer was reached, and
    `stopped_at` describes where reading stopped early (None if it did not).
    """

    path: Path
    complete: bool = False
    stopped_at: str | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)

    def messages(self) -> Iterator[LogMessage]:
        """Every readable message, in file order; raises `RecorderError` if it is not MCAP."""
        require_mcap(self.path)
        with open(self.path, "rb") as stream:
            reader = StreamReader(stream, validate_crcs=True)
            records = reader.records
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    return
                except _TRUNCATION_ERRORS as exc:
                    self.stopped_at = f"{type(exc).__name__} at byte ~{stream.tell()}: {exc}"
                    return
                if isinstance(record, Schema):
                    self.schemas[record.id] = record
                elif isinstance(record, Channel):
                    self.channels[record.id] = record
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Footer):
                    self.complete = True
                elif isinstance(record, Message):
                    channel = self.channels.get(record.channel_id)
                    topic = channel.topic if channel else f"<channel {record.channel_id}>"
                    yield LogMessage(
                        topic=topic,
                        log_time_ns=record.log_time,
                        publish_time_ns=record.publish_time,
                        sequence=record.sequence,
                        data=bytes(record.data),
                    )


def summarize_log(path: str | Path) -> dict[str, Any]:
    """Duration, per-topic counts and times, health events of one flight log (crash-tolerant).

    Keys: path, complete, stopped_at, message_count, start_time_ns, end_time_ns, duration_s,
    channels {topic: {count, first_time_ns, last_time_ns}}, health_events [{time_ns, level,
    event, detail}], cameras {face: {fps, bad_headers, ...}} (the last `/cameras` record: the
    final counters), metadata {name: {key: value}}.
    """
    reader = LogReader(Path(path))
    channels: dict[str, dict[str, int]] = {}
    health: list[dict[str, Any]] = []
    cameras: dict[str, Any] = {}
    start: int | None = None
    end: int | None = None
    count = 0
    for message in reader.messages():
        count += 1
        t = message.log_time_ns
        start = t if start is None else min(start, t)
        end = t if end is None else max(end, t)
        entry = channels.setdefault(
            message.topic, {"count": 0, "first_time_ns": t, "last_time_ns": t}
        )
        entry["count"] += 1
        entry["first_time_ns"] = min(entry["first_time_ns"], t)
        entry["last_time_ns"] = max(entry["last_time_ns"], t)
        if message.topic == TOPIC_CAMERAS:
            with contextlib.suppress(ValueError):
                latest = message.json()
                cameras = latest if isinstance(latest, dict) else cameras
        if message.topic == TOPIC_HEALTH:
            try:
                event = message.json()
            except ValueError:
                event = {
                    "event": "unreadable",
                    "detail": message.data[:200].decode(errors="replace"),
                }
            health.append(
                {"time_ns": t, **(event if isinstance(event, dict) else {"detail": event})}
            )
    return {
        "path": str(path),
        "complete": reader.complete,
        "stopped_at": reader.stopped_at,
        "message_count": count,
        "start_time_ns": start,
        "end_time_ns": end,
        "duration_s": 0.0 if start is None or end is None else (end - start) / 1e9,
        "channels": channels,
        "health_events": health,
        "cameras": cameras,
        "metadata": reader.metadata,
    }


def format_summary(summary: dict[str, Any], max_events: int = 20) -> str:
    """Human-readable text of `summarize_log`'s result, for `companion log summary FILE`."""
    state = "complete" if summary["complete"] else "INCOMPLETE (writer stopped without closing)"
    lines = [
        f"{summary['path']}: {state}",
        f"duration {summary['duration_s']:.1f} s, {summary['message_count']} messages",
    ]
    for topic, entry in sorted(summary["channels"].items()):
        span_s = (entry["last_time_ns"] - entry["first_time_ns"]) / 1e9
        rate = (entry["count"] - 1) / span_s if span_s > 0 else 0.0
        lines.append(f"  {topic:<24} {entry['count']:>8} msgs  {rate:6.1f} Hz")
    events = summary["health_events"]
    lines.append(f"health events: {len(events)}")
    start = summary["start_time_ns"] or 0
    for event in events[:max_events]:
        t = (event["time_ns"] - start) / 1e9
        level = event.get("level", "?")
        lines.append(
            f"  t={t:8.2f} s  {level:<7} {event.get('event', '?')}: {event.get('detail', '')}"
        )
    if len(events) > max_events:
        lines.append(f"  ... {len(events) - max_events} more")
    lines.extend(_camera_lines(summary.get("cameras") or {}))
    if summary["stopped_at"]:
        lines.append(f"read stopped early: {summary['stopped_at']}")
    return "\n".join(lines)


def _camera_lines(cameras: dict[str, Any]) -> list[str]:
    """The final camera counters, one line per face (none if the log has no `/cameras`)."""
    if not cameras:
        return []
    lines = ["cameras (final counters):"]
    for face, entry in cameras.items():
        if not isinstance(entry, dict):
            continue
        fps = entry.get("fps")
        lines.append(
            f"  {face:<6} {'?' if fps is None else f'{fps:.1f}'} fps  "
            f"bad headers {entry.get('bad_headers', '?')}  "
            f"bad payloads {entry.get('bad_payloads', '?')}  "
            f"dropped {entry.get('dropped_bytes', '?')} B  "
            f"seq gaps {entry.get('seq_gaps', '?')}"
            + (f"  last error: {entry['last_error']}" if entry.get("last_error") else "")
        )
    return lines


def recover_log(source: str | Path, destination: str | Path) -> int:
    """Copy every readable message of `source` into a new complete, indexed file; returns the count.

    For a file left by a killed writer: tools that need the summary section get one.
    """
    require_mcap(Path(source))  # before the destination is created
    reader = LogReader(Path(source))
    count = 0
    with open(destination, "xb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="vision-swarm recover_log")
        channel_map: dict[str, int] = {}
        schema_map: dict[int, int] = {}
        for message in reader.messages():
            if message.topic not in channel_map:
                source_channel = next(
                    (c for c in reader.channels.values() if c.topic == message.topic), None
                )
                schema_id = 0
                encoding = "json"
                if source_channel is not None:
                    encoding = source_channel.message_encoding
                    schema = reader.schemas.get(source_channel.schema_id)
                    if schema is not None:
                        if schema.id not in schema_map:
                            schema_map[schema.id] = writer.register_schema(
                                schema.name, schema.encoding, schema.data
                            )
                        schema_id = schema_map[schema.id]
                channel_map[message.topic] = writer.register_channel(
                    message.topic, encoding, schema_id
                )
            writer.add_message(
                channel_map[message.topic],
                log_time=message.log_time_ns,
                data=message.data,
                publish_time=message.publish_time_ns,
                sequence=message.sequence,
            )
            count += 1
        for name, data in reader.metadata.items():
            writer.add_metadata(name, data)
        writer.finish()  # type: ignore[no-untyped-call]
    return count
