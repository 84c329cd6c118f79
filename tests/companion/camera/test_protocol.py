"""Camera wire protocol: encoders, header layout, hostile lengths, sequence numbers, HELLO rules
(fuzzing: `test_protocol_fuzz`)."""

from __future__ import annotations

import struct
import time
from typing import Any

import numpy as np
import pytest

from companion.camera import protocol as p
from companion.camera.protocol import (
    HEADER_SIZE,
    MAGIC,
    MAX_PAYLOAD_SIZE,
    FrameMessage,
    FrameParser,
    HelloMessage,
    MessageType,
    PixelFormat,
    ProtocolError,
    StatusMessage,
    crc16_ccitt_false,
    encode_frame,
    encode_hello,
    encode_message,
    encode_status,
)
from companion.errors import CompanionError

from .protocol_helpers import BUFFER_BOUND, decode_one, gray, raw_message, same

STATUS_ARGS: dict[str, Any] = {
    "camera_id": 0,
    "seq": 0,
    "timestamp_us": 0,
    "fps_hz": 10.0,
    "frames_sent": 0,
    "frames_dropped": 0,
    "exposure_us": 0,
}


# --- encoders, layout, round trips ------------------------------------------------------------


def test_crc_is_ccitt_false_test_vector() -> None:
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_ccitt_false(b"") == 0xFFFF


def test_header_layout_matches_the_documented_offsets() -> None:
    image = gray(64, 64)
    data = encode_frame(image, camera_id=5, seq=0x11223344, timestamp_us=0x0102030405060708)
    assert struct.calcsize(p.HEADER_FORMAT) == HEADER_SIZE == 32
    assert len(data) == 32 + 4096
    assert data[0:2] == b"\xa5\x5a" and data[2] == 1 and data[3] == 1 and data[4] == 5
    assert data[5] == 1 and data[6:8] == b"\x00\x00"
    assert data[8:12] == bytes.fromhex("44332211")
    assert data[12:20] == bytes.fromhex("0807060504030201")
    assert data[20:22] == b"\x40\x00" and data[22:24] == b"\x40\x00"
    assert data[24:28] == (4096).to_bytes(4, "little")
    assert int.from_bytes(data[28:30], "little") == crc16_ccitt_false(image.tobytes())
    assert int.from_bytes(data[30:32], "little") == crc16_ccitt_false(data[:30])
    assert data[32:] == image.tobytes()


def test_frame_round_trip_gives_a_read_only_image() -> None:
    image = gray(64, 64, seed=1)
    data = encode_frame(image, camera_id=2, seq=7, timestamp_us=123_456_789)
    msg = decode_one(data)
    assert isinstance(msg, FrameMessage)
    assert (msg.camera_id, msg.seq, msg.timestamp_us) == (2, 7, 123_456_789)
    assert msg.pixel_format is PixelFormat.GRAY8
    assert msg.image.dtype == np.uint8 and msg.image.shape == (64, 64)
    assert np.array_equal(msg.image, image)
    assert not msg.image.flags.writeable
    assert encode_message(msg) == data


def test_non_square_and_non_contiguous_frames_round_trip() -> None:
    image = gray(10, 30)[:, ::2]  # (10, 15), a strided view
    msg = decode_one(encode_frame(image, camera_id=0, seq=0, timestamp_us=0))
    assert isinstance(msg, FrameMessage) and np.array_equal(msg.image, image)


def test_hello_round_trip() -> None:
    data = encode_hello(
        camera_id=255,
        seq=0,
        timestamp_us=2**63,
        unique_id=bytes.fromhex("001a2b3c4d5e6f7081920304"),
        firmware="openmv-cam-1.0.0",
        platform="omv-4.5.0",
    )
    msg = decode_one(data)
    assert msg == HelloMessage(
        255, 0, 2**63, "001a2b3c4d5e6f7081920304", "openmv-cam-1.0.0", 1, "omv-4.5.0"
    )
    assert encode_message(msg) == data
    assert b'"uid":"001a2b3c4d5e6f7081920304"' in data


@pytest.mark.parametrize(("gain_db", "temperature_c"), [(6.25, 41.5), (None, None), (-3.0, -12.75)])
def test_status_round_trip(gain_db: float | None, temperature_c: float | None) -> None:
    data = encode_status(
        camera_id=1,
        seq=2**32 - 1,
        timestamp_us=5,
        fps_hz=9.97,
        frames_sent=1234,
        frames_dropped=3,
        exposure_us=8000,
        gain_db=gain_db,
        temperature_c=temperature_c,
    )
    assert len(data) == HEADER_SIZE + p.STATUS_SIZE
    msg = decode_one(data)
    assert msg == StatusMessage(1, 2**32 - 1, 5, 9.97, 1234, 3, 8000, gain_db, temperature_c)
    assert encode_message(msg) == data


@pytest.mark.parametrize(
    "bad",
    [
        lambda: encode_frame(np.zeros((4, 4), np.uint16), camera_id=0, seq=0, timestamp_us=0),
        lambda: encode_frame(np.zeros((4, 4, 1), np.uint8), camera_id=0, seq=0, timestamp_us=0),
        lambda: encode_frame(np.zeros((0, 4), np.uint8), camera_id=0, seq=0, timestamp_us=0),
        lambda: encode_frame(np.zeros((257, 256), np.uint8), camera_id=0, seq=0, timestamp_us=0),
        lambda: encode_frame(np.zeros((4, 4), np.uint8), camera_id=256, seq=0, timestamp_us=0),
        lambda: encode_frame(np.zeros((4, 4), np.uint8), camera_id=0, seq=2**32, timestamp_us=0),
        lambda: encode_frame(np.zeros((4, 4), np.uint8), camera_id=0, seq=-1, timestamp_us=0),
        lambda: encode_frame(np.zeros((4, 4), np.uint8), camera_id=0, seq=0, timestamp_us=-1),
        lambda: encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="xyz", firmware="f"),
        lambda: encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="", firmware="f"),
        lambda: encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="ab cd", firmware="f"),
        lambda: encode_status(**{**STATUS_ARGS, "fps_hz": 1000.0}),
        lambda: encode_status(**{**STATUS_ARGS, "temperature_c": 400.0}),
        lambda: encode_status(**{**STATUS_ARGS, "gain_db": float("nan")}),
        lambda: encode_status(**{**STATUS_ARGS, "frames_sent": 2**32}),
    ],
)
def test_encoder_misuse_raises_protocol_error(bad: object) -> None:
    with pytest.raises(ProtocolError) as info:
        bad()  # type: ignore[operator]
    assert isinstance(info.value, CompanionError)


def test_largest_frame_fits_and_parser_limits_are_validated() -> None:
    msg = decode_one(encode_frame(gray(256, 256), camera_id=0, seq=0, timestamp_us=0))
    assert isinstance(msg, FrameMessage) and msg.image.shape == (256, 256)
    with pytest.raises(ProtocolError):
        FrameParser(max_payload_size=MAX_PAYLOAD_SIZE + 1)


# --- hostile lengths, hidden frames, rules ----------------------------------------------------


def test_huge_claimed_length_is_rejected_without_buffering() -> None:
    parser = FrameParser()
    bogus = raw_message(width=0xFFFF, height=0xFFFF, payload_len=0xFFFFFFFF)
    assert parser.feed(bogus + bytes(100_000)) == []
    assert parser.counters.invalid_messages == 1
    assert parser.buffered_bytes == 0


def test_a_plausible_length_buffers_at_most_one_max_message() -> None:
    parser = FrameParser()
    head = encode_frame(gray(256, 256), camera_id=0, seq=0, timestamp_us=0)[:HEADER_SIZE]
    parser.feed(head)
    rng = np.random.default_rng(3)
    for _ in range(50):
        parser.feed(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
        assert parser.buffered_bytes < BUFFER_BOUND
    assert parser.counters.corrupted_payloads == 1
    assert parser.counters.frames_ok == 0


def test_a_valid_frame_hidden_in_a_corrupted_one_is_found() -> None:
    inner = encode_frame(gray(4, 5, seed=9), camera_id=1, seq=3, timestamp_us=4)
    outer = bytearray(
        encode_frame(
            np.frombuffer(b"\x00" * 10 + inner + b"\x00" * 10, np.uint8).reshape(1, -1),
            camera_id=1,
            seq=2,
            timestamp_us=3,
        )
    )
    outer[HEADER_SIZE + 2] ^= 0x10  # payload CRC now fails
    parser = FrameParser()
    got = parser.feed(bytes(outer))
    assert len(got) == 1 and same(got[0], decode_one(inner))
    assert parser.counters.corrupted_payloads == 1


@pytest.mark.parametrize(
    "message",
    [
        raw_message(width=4, height=4, payload=bytes(15)),  # GRAY8 length != width*height
        raw_message(pixel_format=PixelFormat.JPEG, width=4, height=4, payload=bytes(16)),
        raw_message(msg_type=9, pixel_format=0, payload=b"x"),
        raw_message(msg_type=MessageType.STATUS, pixel_format=0, payload=bytes(17)),
        raw_message(msg_type=MessageType.HELLO, pixel_format=0, payload=b"{not json"),
        raw_message(msg_type=MessageType.HELLO, pixel_format=0, payload=b'{"uid":"zz"}'),
        raw_message(
            msg_type=MessageType.HELLO, pixel_format=0, payload=b'{"uid":"ab","fw":1,"proto":1}'
        ),
    ],
)
def test_crc_valid_messages_breaking_a_rule_are_counted_invalid(message: bytes) -> None:
    parser = FrameParser()
    follower = encode_frame(gray(2, 2), camera_id=0, seq=1, timestamp_us=0)
    got = parser.feed(message + follower)
    assert len(got) == 1 and same(got[0], decode_one(follower))
    assert parser.counters.invalid_messages == 1
    assert parser.counters.dropped_bytes == len(message)


def test_other_protocol_versions_are_counted_and_skipped_whole() -> None:
    v2 = raw_message(version=2, msg_type=7, payload=MAGIC + bytes(40))
    v3_huge = raw_message(version=3, payload_len=10**9)
    follower = encode_frame(gray(3, 3), camera_id=0, seq=0, timestamp_us=0)
    parser = FrameParser()
    got = parser.feed(v2 + v3_huge + follower)
    assert len(got) == 1 and same(got[0], decode_one(follower))
    c = parser.counters
    assert c.unsupported_version == 2
    assert c.corrupted_headers == 0 and c.invalid_messages == 0
    assert c.dropped_bytes == len(v2) + len(v3_huge)


# --- sequence numbers -------------------------------------------------------------------------


def frame_bytes(camera_id: int, seq: int) -> bytes:
    return encode_frame(gray(2, 2), camera_id=camera_id, seq=seq, timestamp_us=seq)


def test_sequence_gaps_are_counted_per_camera() -> None:
    parser = FrameParser()
    stream = [(1, 0), (2, 10), (1, 1), (2, 11), (1, 2), (1, 5), (2, 12), (1, 6)]
    parser.feed(b"".join(frame_bytes(c, s) for c, s in stream))
    c = parser.counters
    assert (c.frames_ok, c.sequence_gaps, c.missed_messages) == (8, 1, 2)


def test_sequence_wraps_restarts_and_repeats() -> None:
    parser = FrameParser()
    parser.feed(frame_bytes(0, 2**32 - 2) + frame_bytes(0, 2**32 - 1) + frame_bytes(0, 0))
    assert parser.counters.sequence_gaps == 0  # wrap is not a gap
    parser.feed(frame_bytes(0, 0))  # repeat: a gap event, but no messages missing
    assert (parser.counters.sequence_gaps, parser.counters.missed_messages) == (1, 0)
    hello = encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="ab", firmware="f")
    parser.feed(frame_bytes(0, 50) + hello + frame_bytes(0, 1))  # reboot: HELLO with seq 0
    assert (parser.counters.sequence_gaps, parser.counters.missed_messages) == (2, 49)


def test_reset_drops_buffered_bytes_and_history() -> None:
    parser = FrameParser()
    data = frame_bytes(0, 5)
    parser.feed(data[:-1])
    assert parser.buffered_bytes == len(data) - 1
    parser.reset()
    assert parser.buffered_bytes == 0 and parser.counters.dropped_bytes == len(data) - 1
    parser.feed(frame_bytes(0, 9))
    assert parser.counters.sequence_gaps == 0
    snapshot = parser.counters
    snapshot.frames_ok = 99  # a copy: the parser's own counters are untouched
    assert parser.counters.frames_ok == 1


# --- cost -------------------------------------------------------------------------------------


def test_parsing_is_cheap_on_frames_and_on_garbage() -> None:
    one = encode_frame(gray(64, 64), camera_id=0, seq=0, timestamp_us=0)
    stream = one * 500
    noise = np.random.default_rng(5).integers(0, 256, 4_000_000, dtype=np.uint8).tobytes()
    parser = FrameParser()
    # CPU time of this thread, not wall time: what parsing costs, which a loaded machine that
    # shares the cores out does not change.
    start = time.thread_time()
    n = 0
    for i in range(0, len(stream), 1000):  # USB-sized chunks
        n += len(parser.feed(stream[i : i + 1000]))
    for i in range(0, len(noise), 65536):
        parser.feed(noise[i : i + 65536])
    elapsed = time.thread_time() - start
    assert n == 500
    assert elapsed < 2.0  # typically ~0.05 s: 500 frames (2 MB) plus 4 MB of noise


# --- HELLO rules at their boundaries (docs/camera-protocol.md, "HELLO payload") ----------------


def hello_bytes(body: bytes) -> bytes:
    """A CRC-valid v1 HELLO carrying `body` as its payload, whatever it holds."""
    return raw_message(msg_type=MessageType.HELLO, pixel_format=PixelFormat.NONE, payload=body)


def hello_json(uid: str = "ab", fw: str = "f", proto: object = 1, omv: str = "") -> bytes:
    import json

    return json.dumps({"uid": uid, "fw": fw, "proto": proto, "omv": omv}).encode()


@pytest.mark.parametrize(
    ("body", "accepted"),
    [
        (hello_json(uid="ab"), True),  # shortest uid: 2 digits
        (hello_json(uid="a"), False),  # odd count
        (hello_json(uid="0" * 64), True),  # longest: 64 digits
        (hello_json(uid="0" * 66), False),
        (hello_json(uid="3a0025000d51363036383832"), True),  # STM32F7: 12 bytes
        (hello_json(uid="3A0025000D51363036383832"), False),  # uppercase: not what a camera sends
        (hello_json(uid="aB"), False),
        (hello_json(proto=1), True),
        (hello_json(proto=0), False),
        (hello_json(proto=-1), False),
        (hello_json(proto=2), False),  # a v2 script inside a v1 header
        (hello_json(proto=True), False),
        (hello_json(proto=1.0), False),
        (hello_json(fw="x" * 64), True),
        (hello_json(fw="x" * 65), False),
        (hello_json(omv="~ !"), True),  # printable ASCII edges
        (hello_json(fw="caf\u00e9"), False),  # ASCII bytes (\u00e9 escape) but not ASCII text
        (hello_json(fw="a\tb"), False),  # a control character
        ('{"uid":"ab","fw":"café","proto":1}'.encode(), False),  # UTF-8: not ASCII JSON
        (b'{"uid":"ab","fw":"f","proto":1}', True),  # omv is optional
        (b'["ab","f",1]', False),  # not an object
    ],
)
def test_hello_rules_at_their_boundaries(body: bytes, accepted: bool) -> None:
    parser = FrameParser()
    got = parser.feed(hello_bytes(body))
    assert (len(got) == 1) is accepted
    assert parser.counters.invalid_messages == (0 if accepted else 1)
    if accepted:
        assert isinstance(got[0], HelloMessage) and got[0].protocol_version == 1


def test_hello_encoder_refuses_what_the_parser_would_reject() -> None:
    for firmware in ("x" * 65, "caf\u00e9", "a\nb"):
        with pytest.raises(ProtocolError, match="firmware/platform"):
            encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="ab", firmware=firmware)
    with pytest.raises(ProtocolError, match="unique_id"):
        encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="0" * 66, firmware="f")
    # The encoder normalizes a hex id typed in uppercase; the wire carries it lowercase.
    msg = decode_one(
        encode_hello(camera_id=0, seq=0, timestamp_us=0, unique_id="ABCD", firmware="f")
    )
    assert isinstance(msg, HelloMessage) and msg.unique_id == "abcd"
