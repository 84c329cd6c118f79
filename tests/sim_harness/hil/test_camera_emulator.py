"""Camera emulator on real ptys, read by a plain pyserial host through the protocol parser."""

from __future__ import annotations

import itertools
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import serial

from companion.camera.layout import FACE_NAMES, split
from companion.camera.protocol import FrameMessage, FrameParser, HelloMessage, Message
from sim_harness.errors import SimError
from sim_harness.hil.camera_emulator import CameraEmulator

RATE_HZ = 50.0
TIMEOUT_S = 10.0  # liveness bound only; everything normally happens within a few frame periods
# A pty holds ~12 kB: under 3 frames, 60 ms at RATE_HZ. A host that a loaded machine does not
# schedule for longer makes the emulator drop frames (by design): the tests below allow for that
# by reading the emulator's own counters instead of assuming an unbroken stream.


def recording(n: int = 3) -> np.ndarray:
    return np.random.default_rng(7).integers(0, 256, (n, 64, 384), dtype=np.uint8)


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[CameraEmulator]:
    # No STATUS and no repeated HELLO within a test (one HELLO per connection): a camera's
    # sequence number then advances by exactly one per frame tick, whether sent or dropped.
    quiet = {"hello_period_s": 600.0, "status_period_s": 600.0}
    with CameraEmulator(tmp_path, source=recording(), rate_hz=RATE_HZ, **quiet) as emu:
        yield emu


def open_port(path: Path) -> serial.Serial:
    return serial.Serial(str(path), 115200, timeout=0.02)


def read_until(
    port: serial.Serial, parser: FrameParser, done: Callable[[list[Message]], bool]
) -> list[Message]:
    messages: list[Message] = []
    deadline = time.monotonic() + TIMEOUT_S
    while not done(messages):
        assert time.monotonic() < deadline, f"gave up after {len(messages)} messages"
        messages += parser.feed(port.read(65536))
    return messages


def frames(messages: list[Message]) -> list[FrameMessage]:
    return [m for m in messages if isinstance(m, FrameMessage)]


def wait_until(predicate: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_silent_until_opened_then_hello_and_recorded_frames(emulator: CameraEmulator) -> None:
    time.sleep(0.1)  # several frame periods with no host
    stats = emulator.stats("back")
    assert stats.frames_sent == 0 and stats.hellos_sent == 0 and not stats.host_connected
    tiles = split(recording())[:, FACE_NAMES.index("back")]  # (3, 64, 64)
    parser = FrameParser()
    with open_port(emulator.device_path("back")) as port:
        messages = read_until(port, parser, lambda m: len(frames(m)) >= 6)
    hello = messages[0]
    assert isinstance(hello, HelloMessage)
    assert (hello.seq, hello.unique_id, hello.camera_id) == (0, emulator.uid("back"), 2)
    got = frames(messages)
    assert got[0].seq == 1  # the first frame tick after the HELLO
    first = next(k for k in range(3) if np.array_equal(got[0].image, tiles[k]))
    for frame in got:  # the recording plays in a loop, one stitched frame (and seq) per tick
        assert np.array_equal(frame.image, tiles[(first + frame.seq - 1) % 3])
        assert frame.camera_id == 2 and not frame.image.flags.writeable
    assert all(b.seq > a.seq for a, b in itertools.pairwise(got))
    assert all(b.timestamp_us > a.timestamp_us for a, b in itertools.pairwise(got))
    counters = parser.counters
    assert counters.dropped_bytes == 0  # whole messages only, never a torn one
    # A gap is only ever a frame the emulator dropped because this host was not reading (none
    # on a quiet machine); the count only grows, so read after the port was closed.
    assert counters.missed_messages <= emulator.stats("back").frames_dropped


def test_reopen_announces_again_and_replug_reboots(emulator: CameraEmulator) -> None:
    path = emulator.device_path("left")
    with open_port(path) as port:
        first = read_until(port, FrameParser(), lambda m: len(frames(m)) >= 2)
    wait_until(lambda: not emulator.stats("left").host_connected, "the emulator to see the close")
    with open_port(path) as port:
        again = read_until(port, FrameParser(), lambda m: len(frames(m)) >= 1)
    assert isinstance(again[0], HelloMessage) and again[0].seq > first[-1].seq  # same boot
    assert emulator.stats("left").connections == 2

    old_target = os.readlink(path)
    with open_port(path) as port:
        read_until(port, FrameParser(), lambda m: len(m) >= 1)
        emulator.replug("left")  # while the host holds the old pty: it reads end of file
        with pytest.raises(serial.SerialException):
            for _ in range(100):
                port.read(65536)
    assert os.readlink(path) != old_target
    with open_port(path) as port:
        rebooted = read_until(port, FrameParser(), lambda m: len(frames(m)) >= 1)
    assert isinstance(rebooted[0], HelloMessage) and rebooted[0].seq == 0


def test_unplug_removes_the_device_and_stall_silences_it(emulator: CameraEmulator) -> None:
    path = emulator.device_path("up")
    emulator.unplug("up")
    assert not path.exists() and not emulator.stats("up").plugged
    with pytest.raises(serial.SerialException):
        open_port(path)
    emulator.replug("up")
    with open_port(path) as port:
        parser = FrameParser()
        read_until(port, parser, lambda m: len(frames(m)) >= 1)
        emulator.stall("up")
        at_stall = emulator.stats("up")  # seq: the next message's number; none is built now
        time.sleep(0.1)  # five frame periods
        after = emulator.stats("up")
        assert (after.seq, after.frames_sent) == (at_stall.seq, at_stall.frames_sent)
        # Only the rest of what was queued before the stall arrives (judged by seq, not by
        # when it arrives: a loaded machine may deliver it late).
        late = parser.feed(port.read(65536))
        assert all(m.seq < at_stall.seq for m in late)
        emulator.resume("up")
        read_until(port, parser, lambda m: any(f.seq >= at_stall.seq for f in frames(m)))


def test_host_that_stops_reading_makes_frames_drop_not_block(emulator: CameraEmulator) -> None:
    front, down = emulator.device_path("front"), emulator.device_path("down")
    with open_port(front) as idle, open_port(down) as busy:
        busy_parser = FrameParser()
        # The down camera keeps streaming while the front one has nowhere to write.
        read_until(
            busy,
            busy_parser,
            lambda m: len(frames(m)) >= 10 and emulator.stats("front").frames_dropped >= 5,
        )
        # Dropped frames are sequence gaps that the host counts once it reads again (what the
        # pty buffered comes first, then the gap: read until the gap shows, within TIMEOUT_S).
        parser = FrameParser()
        read_until(
            idle, parser, lambda m: len(frames(m)) >= 3 and parser.counters.missed_messages >= 5
        )


def test_tile_source_callable_and_bad_sources(tmp_path: Path) -> None:
    def gradient(t_s: float) -> np.ndarray:
        return np.full((6, 64, 64), np.arange(6, dtype=np.uint8)[:, None, None] * 40)

    with CameraEmulator(tmp_path / "a", source=gradient, rate_hz=RATE_HZ) as emu:
        assert emu.rig_config().faces["right"].camera_id == emu.uid("right")
        with open_port(emu.device_path("right")) as port:
            got = frames(read_until(port, FrameParser(), lambda m: len(frames(m)) >= 1))
        assert np.all(got[0].image == 40)
    with pytest.raises(SimError, match="recording"):
        CameraEmulator(tmp_path / "b", source=np.zeros((2, 64, 300), np.uint8))
    bad = CameraEmulator(tmp_path / "c", source=lambda t_s: np.zeros((6, 64, 64), np.float32))
    with pytest.raises(SimError, match="float32"):
        bad.start()
