"""Helpers of the camera protocol tests: raw headers, chunked feeds, message equality."""

from __future__ import annotations

import itertools
import struct

import numpy as np

from companion.camera import protocol as p
from companion.camera.protocol import (
    HEADER_SIZE,
    MAGIC,
    MAX_PAYLOAD_SIZE,
    FrameMessage,
    FrameParser,
    Message,
    MessageType,
    PixelFormat,
    crc16_ccitt_false,
)

BUFFER_BOUND = HEADER_SIZE + MAX_PAYLOAD_SIZE


def gray(height: int, width: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (height, width), dtype=np.uint8)


def raw_message(
    *,
    version: int = 1,
    msg_type: int = MessageType.FRAME,
    camera_id: int = 0,
    pixel_format: int = PixelFormat.GRAY8,
    seq: int = 0,
    timestamp_us: int = 0,
    width: int = 0,
    height: int = 0,
    payload: bytes = b"",
    payload_len: int | None = None,
) -> bytes:
    """Any header with valid CRCs, rules or not."""
    length = len(payload) if payload_len is None else payload_len
    head = bytearray(p.HEADER_STRUCT.pack(
        MAGIC, version, msg_type, camera_id, pixel_format, 0, seq, timestamp_us, width, height,
        length, crc16_ccitt_false(payload), 0,
    ))  # fmt: skip
    struct.pack_into("<H", head, 30, crc16_ccitt_false(head[:30]))
    return bytes(head) + payload


def feed_chunks(parser: FrameParser, data: bytes, cuts: list[int]) -> list[Message]:
    out: list[Message] = []
    bounds = [0, *sorted(c % (len(data) + 1) for c in cuts), len(data)]
    for a, b in itertools.pairwise(bounds):
        out += parser.feed(data[a:b])
        assert parser.buffered_bytes < BUFFER_BOUND
    return out


def same(a: Message, b: Message) -> bool:
    if isinstance(a, FrameMessage) and isinstance(b, FrameMessage):
        return (a.camera_id, a.seq, a.timestamp_us) == (b.camera_id, b.seq, b.timestamp_us) and (
            np.array_equal(a.image, b.image)
        )
    return a == b


def decode_one(data: bytes) -> Message:
    parser = FrameParser()
    msgs = parser.feed(data)
    assert len(msgs) == 1 and parser.counters.frames_ok == 1 and parser.buffered_bytes == 0
    return msgs[0]
