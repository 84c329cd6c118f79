"""Camera wire protocol v1 (OpenMV Cam M7 -> companion): message types, encoders, streaming parser.

Every message is a fixed 32-byte little-endian header (`HEADER_FORMAT`) followed by a payload of
`payload_len` bytes (at most `MAX_PAYLOAD_SIZE`). The header carries its own CRC (bytes 0..29) and
the payload's CRC; both are CRC-16/CCITT-FALSE. docs/camera-protocol.md is the specification;
firmware_cfg/openmv/main.py carries a byte-identical MicroPython encoder.
"""

from __future__ import annotations

import binascii
import dataclasses
import math
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, NamedTuple, TypeAlias

import numpy as np
import numpy.typing as npt

from companion.camera.hello import TEXT_MAX_CHARS, build_hello_payload, is_uid, parse_hello_payload
from companion.errors import CompanionError

MAGIC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
HEADER_FORMAT = "<2sBBBBHIQHHIHH"
HEADER_STRUCT = struct.Struct(HEADER_FORMAT)
HEADER_SIZE = 32
HEADER_CRC_OFFSET = 30  # the header CRC covers bytes [0, 30) and is stored at [30, 32)
MAX_PAYLOAD_SIZE = 65536  # 64 KiB: a CRC-valid header can never ask for more
MAX_HELLO_SIZE = 512
STATUS_FORMAT = "<HIIIhh"
STATUS_STRUCT = struct.Struct(STATUS_FORMAT)
STATUS_SIZE = 18
I16_UNAVAILABLE = -32768  # STATUS gain/temperature sentinel: "not available"
SEQ_MODULO = 1 << 32
UNASSIGNED_CAMERA_ID = 255
_U16_MAX = 0xFFFF
_U32_MAX = 0xFFFFFFFF
_U64_MAX = (1 << 64) - 1

assert HEADER_STRUCT.size == HEADER_SIZE
assert STATUS_STRUCT.size == STATUS_SIZE


class ProtocolError(CompanionError, ValueError):
    """An encoder was asked to build a message the protocol cannot carry (bad size or range)."""


class MessageType(IntEnum):
    """Header byte 3."""

    FRAME = 1
    HELLO = 2
    STATUS = 3


class PixelFormat(IntEnum):
    """Header byte 5. JPEG is reserved: v1 encoders refuse it and v1 parsers reject it."""

    NONE = 0
    GRAY8 = 1
    JPEG = 2


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor); 16-bit int."""
    return binascii.crc_hqx(data, crc)


@dataclass(frozen=True, eq=False)
class FrameMessage:
    """One image. `image` is a read-only (height, width) uint8 array owning a copy of the payload.

    Equality is identity (arrays do not compare to a bool): compare `image` with `np.array_equal`.
    """

    camera_id: int
    seq: int
    timestamp_us: int  # camera clock at capture, µs since the camera script started
    image: npt.NDArray[np.uint8]
    pixel_format: PixelFormat = PixelFormat.GRAY8


@dataclass(frozen=True)
class HelloMessage:
    """Who the camera is: board unique id (lowercase hex) and firmware/protocol versions."""

    camera_id: int
    seq: int
    timestamp_us: int
    unique_id: str
    firmware: str
    protocol_version: int
    platform: str = ""


@dataclass(frozen=True)
class StatusMessage:
    """Camera health, about once per second. `None` means the camera could not measure it."""

    camera_id: int
    seq: int
    timestamp_us: int
    fps_hz: float  # FRAME rate over the last status interval, 0.01 Hz resolution
    frames_sent: int  # FRAMEs written since boot (u32, wraps)
    frames_dropped: int  # frame slots missed or failed writes since boot (u32, wraps)
    exposure_us: int  # locked exposure time, µs
    gain_db: float | None  # locked sensor gain, 0.01 dB resolution
    temperature_c: float | None  # MCU die temperature, 0.01 °C resolution


Message: TypeAlias = FrameMessage | HelloMessage | StatusMessage


@dataclass(slots=True)
class ParserCounters:
    """What a `FrameParser` saw. Every byte fed ends up in an accepted message, in
    `dropped_bytes`, or still buffered (`FrameParser.buffered_bytes`).
    """

    frames_ok: int = 0  # messages of any type accepted (both CRCs and all rules passed)
    corrupted_headers: int = 0  # magic found but the header CRC failed
    corrupted_payloads: int = 0  # header fine but the payload CRC failed
    invalid_messages: int = 0  # CRC-valid but breaking a v1 rule (length, type, format, content)
    unsupported_version: int = 0  # CRC-valid messages of another protocol version (skipped)
    dropped_bytes: int = 0  # bytes discarded: garbage, bad frames, skipped messages
    sequence_gaps: int = 0  # gap events: seq != last_seq + 1 (mod 2^32) for a camera id
    missed_messages: int = 0  # messages missing in forward gaps (jump < 2^31)


def _check_int(name: str, value: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= high:
        raise ProtocolError(f"{name}: expected an integer in [0, {high}], got {value!r}")
    return value


def _header(
    msg_type: MessageType,
    camera_id: int,
    seq: int,
    timestamp_us: int,
    payload: bytes,
    pixel_format: PixelFormat = PixelFormat.NONE,
    width: int = 0,
    height: int = 0,
) -> bytes:
    _check_int("camera_id", camera_id, 0xFF)
    _check_int("seq", seq, _U32_MAX)
    _check_int("timestamp_us", timestamp_us, _U64_MAX)
    if len(payload) > MAX_PAYLOAD_SIZE:
        raise ProtocolError(f"payload: {len(payload)} bytes exceeds {MAX_PAYLOAD_SIZE}")
    head = bytearray(HEADER_SIZE)
    HEADER_STRUCT.pack_into(
        head, 0, MAGIC, PROTOCOL_VERSION, msg_type, camera_id, pixel_format, 0, seq, timestamp_us,
        width, height, len(payload), crc16_ccitt_false(payload), 0,
    )  # fmt: skip
    struct.pack_into("<H", head, HEADER_CRC_OFFSET, crc16_ccitt_false(head[:HEADER_CRC_OFFSET]))
    return bytes(head)


def encode_frame(
    image: npt.NDArray[np.uint8], *, camera_id: int, seq: int, timestamp_us: int
) -> bytes:
    """FRAME message for a GRAY8 image of shape (height, width), 1 <= height*width <= 64 KiB."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 2:
        raise ProtocolError("image: expected a 2-D uint8 numpy array (height, width)")
    height, width = image.shape
    if not (0 < height <= _U16_MAX and 0 < width <= _U16_MAX):
        raise ProtocolError(f"image: shape {image.shape} must have sides in [1, {_U16_MAX}]")
    payload = np.ascontiguousarray(image).tobytes()
    head = _header(MessageType.FRAME, camera_id, seq, timestamp_us, payload, PixelFormat.GRAY8,
                   width, height)  # fmt: skip
    return head + payload


def hello_payload(unique_id: bytes | str, firmware: str, platform: str = "") -> bytes:
    """ASCII JSON {"uid","fw","proto","omv"}: fixed key order, no spaces (as the firmware).

    `unique_id` as raw bytes or hex (either case; sent lowercase); `firmware` and `platform`
    printable ASCII, at most 64 characters each (the rules in `companion.camera.hello`).
    """
    uid = unique_id.hex() if isinstance(unique_id, bytes | bytearray) else str(unique_id).lower()
    if not is_uid(uid):
        raise ProtocolError(f"unique_id: {unique_id!r} is not 2..64 hex digits (even count)")
    payload = build_hello_payload(uid, firmware, platform, PROTOCOL_VERSION)
    if payload is None:
        raise ProtocolError(
            f"firmware/platform: {firmware!r}, {platform!r} must be printable ASCII, "
            f"at most {TEXT_MAX_CHARS} characters"
        )
    return payload


def encode_hello(
    *,
    camera_id: int,
    seq: int,
    timestamp_us: int,
    unique_id: bytes | str,
    firmware: str,
    platform: str = "",
) -> bytes:
    """HELLO message; `unique_id` as raw bytes (e.g. machine.unique_id()) or a hex string."""
    payload = hello_payload(unique_id, firmware, platform)
    return _header(MessageType.HELLO, camera_id, seq, timestamp_us, payload) + payload


def _hundredths(name: str, value: float | None, low: int, high: int) -> int:
    """round(value * 100) checked to lie in [low, high]; None -> I16_UNAVAILABLE."""
    if value is None:
        return I16_UNAVAILABLE
    scaled = round(value * 100) if math.isfinite(value) else high + 1
    if not low <= scaled <= high:
        raise ProtocolError(f"{name}: {value} outside [{low / 100}, {high / 100}]")
    return scaled


def encode_status(
    *,
    camera_id: int,
    seq: int,
    timestamp_us: int,
    fps_hz: float,
    frames_sent: int,
    frames_dropped: int,
    exposure_us: int,
    gain_db: float | None = None,
    temperature_c: float | None = None,
) -> bytes:
    """STATUS message: 18-byte struct `STATUS_FORMAT` (fps and dB/°C in hundredths)."""
    payload = STATUS_STRUCT.pack(
        _hundredths("fps_hz", fps_hz, 0, _U16_MAX),
        _check_int("frames_sent", frames_sent, _U32_MAX),
        _check_int("frames_dropped", frames_dropped, _U32_MAX),
        _check_int("exposure_us", exposure_us, _U32_MAX),
        _hundredths("gain_db", gain_db, I16_UNAVAILABLE + 1, 0x7FFF),
        _hundredths("temperature_c", temperature_c, I16_UNAVAILABLE + 1, 0x7FFF),
    )
    return _header(MessageType.STATUS, camera_id, seq, timestamp_us, payload) + payload


def encode_message(message: Message) -> bytes:
    """Encode any decoded message again (the parser's inverse)."""
    common: dict[str, Any] = {
        "camera_id": message.camera_id,
        "seq": message.seq,
        "timestamp_us": message.timestamp_us,
    }
    if isinstance(message, FrameMessage):
        if message.pixel_format != PixelFormat.GRAY8:
            raise ProtocolError(f"pixel_format: {message.pixel_format!r} is not supported in v1")
        return encode_frame(message.image, **common)
    if isinstance(message, HelloMessage):
        return encode_hello(
            unique_id=message.unique_id,
            firmware=message.firmware,
            platform=message.platform,
            **common,
        )
    fields = dataclasses.asdict(message)
    del fields["camera_id"], fields["seq"], fields["timestamp_us"]
    return encode_status(**common, **fields)


class _Header(NamedTuple):
    """The 13 fields of `HEADER_FORMAT`, in order."""

    magic: bytes
    version: int
    msg_type: int
    camera_id: int
    pixel_format: int
    flags: int
    seq: int
    timestamp_us: int
    width: int
    height: int
    payload_len: int
    payload_crc: int
    header_crc: int


def _header_ok(h: _Header, max_payload: int) -> bool:
    """v1 rules a CRC-valid header must meet before its length is used."""
    if h.payload_len > max_payload:
        return False
    if h.msg_type == MessageType.FRAME:
        return h.pixel_format == PixelFormat.GRAY8 and h.payload_len == h.width * h.height > 0
    plain = h.pixel_format == PixelFormat.NONE and h.width == 0 and h.height == 0
    if h.msg_type == MessageType.HELLO:
        return plain and 0 < h.payload_len <= MAX_HELLO_SIZE
    return plain and h.msg_type == MessageType.STATUS and h.payload_len == STATUS_SIZE


def _decode(h: _Header, payload: bytes) -> Message | None:
    """Message from a CRC-valid v1 header and payload, or None if the payload breaks a rule."""
    msg_type, camera_id, seq, timestamp_us = h.msg_type, h.camera_id, h.seq, h.timestamp_us
    if msg_type == MessageType.FRAME:
        image = np.frombuffer(payload, dtype=np.uint8).reshape(h.height, h.width)  # read-only
        return FrameMessage(camera_id, seq, timestamp_us, image)
    if msg_type == MessageType.STATUS:
        fps_x100, sent, dropped, exposure_us, gain, temp = STATUS_STRUCT.unpack(payload)
        return StatusMessage(
            camera_id, seq, timestamp_us, fps_x100 / 100, sent, dropped, exposure_us,
            None if gain == I16_UNAVAILABLE else gain / 100,
            None if temp == I16_UNAVAILABLE else temp / 100,
        )  # fmt: skip
    body = parse_hello_payload(payload, h.version)
    if body is None:
        return None
    return HelloMessage(camera_id, seq, timestamp_us, *body)


class FrameParser:
    """Streaming parser: feed it byte chunks of any size, get decoded messages in stream order.

    Finds `MAGIC` with `bytearray.find`, checks the header CRC before trusting any field, and on a
    bad header, bad payload CRC or broken rule drops one byte and searches again (so a message
    hidden inside a corrupted one is still found). The buffer never holds more than
    `HEADER_SIZE + max_payload_size - 1` bytes between calls. One parser per serial stream.
    """

    def __init__(self, *, max_payload_size: int = MAX_PAYLOAD_SIZE) -> None:
        if not 0 < max_payload_size <= MAX_PAYLOAD_SIZE:
            raise ProtocolError(f"max_payload_size: must be in [1, {MAX_PAYLOAD_SIZE}]")
        self._max_payload = max_payload_size
        self._buf = bytearray()
        self._need = 0  # buffer length below which scanning cannot make progress
        self._counters = ParserCounters()
        self._last_seq: dict[int, int] = {}

    @property
    def counters(self) -> ParserCounters:
        """A snapshot (copy) of the counters."""
        return dataclasses.replace(self._counters)

    @property
    def buffered_bytes(self) -> int:
        """Bytes held back waiting for the rest of a message (or a possible magic start)."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (counted as dropped) and sequence history, e.g. after reopening."""
        self._counters.dropped_bytes += len(self._buf)
        self._buf.clear()
        self._need = 0
        self._last_seq.clear()

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        """Append `data` and return every message completed by it, in stream order."""
        self._buf += data
        out: list[Message] = []
        if len(self._buf) < self._need:  # still waiting for the same header or payload
            return out
        consumed = self._scan(out)
        del self._buf[:consumed]
        return out

    def _scan(self, out: list[Message]) -> int:
        """Decode from the buffer start; return how many leading bytes are done with."""
        buf, c = self._buf, self._counters
        n, pos = len(buf), 0
        self._need = 0
        with memoryview(buf) as view:
            while True:
                start = buf.find(MAGIC, pos)
                if start < 0:  # keep a trailing first magic byte: the next chunk may complete it
                    keep = 1 if n > pos and buf[n - 1] == MAGIC[0] else 0
                    c.dropped_bytes += n - pos - keep
                    return n - keep
                c.dropped_bytes += start - pos
                pos = start
                if n - pos < HEADER_SIZE:
                    self._need = HEADER_SIZE
                    return pos
                h = _Header._make(HEADER_STRUCT.unpack_from(buf, pos))
                known = h.version == PROTOCOL_VERSION
                if crc16_ccitt_false(view[pos : pos + HEADER_CRC_OFFSET]) != h.header_crc:
                    c.corrupted_headers += 1
                elif not known and h.payload_len > self._max_payload:
                    c.unsupported_version += 1
                elif known and not _header_ok(h, self._max_payload):
                    c.invalid_messages += 1
                else:
                    end = pos + HEADER_SIZE + h.payload_len
                    if end > n:  # header is sound: wait for the whole payload
                        self._need = end - pos
                        return pos
                    payload = bytes(view[pos + HEADER_SIZE : end])
                    if crc16_ccitt_false(payload) != h.payload_crc:
                        c.corrupted_payloads += 1
                    else:
                        msg = _decode(h, payload) if known else None
                        if msg is None:  # genuine message we cannot use: skip it whole
                            if known:
                                c.invalid_messages += 1
                            else:
                                c.unsupported_version += 1
                            c.dropped_bytes += end - pos
                        else:
                            c.frames_ok += 1
                            self._track(msg)
                            out.append(msg)
                        pos = end
                        continue
                c.dropped_bytes += 1  # resync: drop one byte, search for the next magic
                pos += 1

    def _track(self, msg: Message) -> None:
        last = self._last_seq.get(msg.camera_id)
        self._last_seq[msg.camera_id] = msg.seq
        if last is None or (isinstance(msg, HelloMessage) and msg.seq == 0):
            return  # first message from this camera id, or the camera restarted
        missing = (msg.seq - last - 1) % SEQ_MODULO
        if missing:
            self._counters.sequence_gaps += 1
            if missing < SEQ_MODULO // 2:
                self._counters.missed_messages += missing
