"""Serial camera links against the pty camera emulator: real ptys, pyserial, the real parser."""

from __future__ import annotations

import asyncio
import os
import re
import termios
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from companion.camera.layout import FACE_NAMES, split
from companion.camera.protocol import MAGIC
from companion.camera.rig import Rig, RigImage
from companion.camera.serial_link import SerialCameraLink, links_from_config, run_links
from companion.camera.slot import CameraFrame
from sim_harness.hil.camera_emulator import CameraEmulator

TIMEOUT_S = 10.0  # liveness bound only; everything normally happens within a few frame periods
CLOCK_OFFSET_S = 1000.0


def clock() -> float:
    """The injected host clock: monotonic, shifted so that its values are recognisable."""
    return time.monotonic() + CLOCK_OFFSET_S


def recording(n: int = 50) -> np.ndarray:
    """Recorded stitched frames; 50 distinct ones loop once a second at 50 Hz, so two frames a
    loaded machine received a few ticks apart never show the same recorded tile."""
    return np.random.default_rng(11).integers(0, 256, (n, 64, 384), dtype=np.uint8)


def recorded_tile_index(frame: CameraFrame, face: str, rec: np.ndarray) -> int:
    """Which recorded stitched frame this face's tile came from; fails if none matches exactly."""
    tiles = split(rec)[:, FACE_NAMES.index(face)]
    matches = [k for k in range(len(tiles)) if np.array_equal(frame.image, tiles[k])]
    assert len(matches) == 1, "received tile matches no recorded tile"
    return matches[0]


@pytest.fixture
def emulator(tmp_path: Path) -> Iterator[CameraEmulator]:
    with CameraEmulator(tmp_path, source=recording(), rate_hz=50.0, status_period_s=0.2) as emu:
        yield emu


def link_for(emu: CameraEmulator, face: str, **options: float) -> SerialCameraLink:
    options = {"reconnect_min_s": 0.02, "reconnect_max_s": 0.2} | options
    return SerialCameraLink(str(emu.device_path(face)), clock=clock, **options)


async def wait_for(predicate: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + TIMEOUT_S
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.01)


def run_with(links: list[SerialCameraLink], body: Callable[[], Awaitable[None]]) -> None:
    """Run the links in the background while `body` runs, then cancel them."""

    async def main() -> None:
        task = asyncio.create_task(run_links(links))
        try:
            await body()
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task

    asyncio.run(main())


def identified(link: SerialCameraLink, uid: str) -> Callable[[], bool]:
    def check() -> bool:
        frame = link.latest()
        return frame is not None and frame.camera_uid == uid

    return check


def test_frames_flow_into_the_slot_with_the_right_bytes(emulator: CameraEmulator) -> None:
    link = link_for(emulator, "right")
    uid = emulator.uid("right")

    async def body() -> None:
        start_s = clock()
        await wait_for(identified(link, uid), "an identified frame")
        await wait_for(lambda: link.status().camera_status is not None, "a STATUS")
        frame = link.latest()
        assert frame is not None
        assert frame.image.shape == (64, 64) and frame.image.dtype == np.uint8
        assert not frame.image.flags.writeable
        first = recorded_tile_index(frame, "right", recording())
        assert start_s <= frame.receive_time_s <= clock()  # from the injected clock
        assert frame.capture_time_s <= frame.receive_time_s
        assert frame.header_camera_id == 1 and frame.device == str(emulator.device_path("right"))
        await wait_for(lambda: link.latest() is not frame, "the next frame")
        following = link.latest()
        assert following is not None and following.seq > frame.seq
        assert recorded_tile_index(following, "right", recording()) != first
        status = link.status()
        assert status.connected and status.camera_uid == uid and status.header_camera_id == 1
        assert status.frames_ok >= 2 and status.counters.frames_ok > status.frames_ok
        assert status.connects == 1 and status.reconnects == 0
        assert status.last_frame_age_s is not None and status.last_frame_age_s >= 0.0
        # The port really runs at 115200 baud (the slave's termios as the link left them).
        fd = os.open(emulator.device_path("right"), os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            ispeed, ospeed = termios.tcgetattr(fd)[4:6]
        finally:
            os.close(fd)
        assert ispeed == ospeed == termios.B115200

    run_with([link], body)


def test_six_links_and_the_rig_rebuild_the_recorded_image(tmp_path: Path) -> None:
    still = recording(1)
    with CameraEmulator(tmp_path, source=still, rate_hz=50.0) as emu:
        config = emu.rig_config(reconnect_min_s=0.02, reconnect_max_s=0.2)
        links = links_from_config(config, clock=clock)
        rig = Rig(config, links)

        async def body() -> None:
            await wait_for(lambda: rig.snapshot(clock()).ready, "a ready rig")
            snapshot = rig.snapshot(clock())
            assert isinstance(snapshot, RigImage)
            assert np.array_equal(snapshot.image, still[0])
            assert snapshot.camera_uids == tuple(emu.uid(face) for face in FACE_NAMES)
            assert snapshot.oldest_capture_time_s <= min(snapshot.receive_times_s)

        run_with(list(links.values()), body)


def test_garbage_and_corrupted_frames_are_dropped_and_counted(emulator: CameraEmulator) -> None:
    link = link_for(emulator, "front")
    rng = np.random.default_rng(3)
    noise = bytes(b for b in rng.integers(0, 256, 3000, dtype=np.uint8).tobytes() if b != 0xA5)
    fake_header = MAGIC + rng.integers(0, 256, 40, dtype=np.uint8).tobytes()

    async def body() -> None:
        await wait_for(identified(link, emulator.uid("front")), "an identified frame")
        before = link.status()
        assert emulator.inject("front", noise)
        await asyncio.sleep(0.05)
        assert emulator.inject("front", fake_header)
        emulator.corrupt_frames("front", 2)
        dropped = emulator.stats("front").frames_dropped

        def two_bad_payloads() -> bool:
            # The emulator corrupts the next frames it builds; one it then drops (this host was
            # not scheduled for > 3 frame periods: a loaded machine) never arrives. Corrupt one
            # more for each drop, so that two corrupted payloads do arrive.
            nonlocal dropped
            now = emulator.stats("front").frames_dropped
            if now > dropped:
                emulator.corrupt_frames("front", now - dropped)
                dropped = now
            return link.status().counters.corrupted_payloads >= 2

        await wait_for(two_bad_payloads, "2 bad payloads")
        await wait_for(lambda: link.status().frames_ok >= before.frames_ok + 5, "more frames")
        after = link.status()
        assert after.counters.dropped_bytes >= before.counters.dropped_bytes + len(noise) + 2 * 4128
        assert after.counters.corrupted_headers >= 1
        assert after.connected and after.connects == 1
        frame = link.latest()
        assert frame is not None
        recorded_tile_index(frame, "front", recording())  # still exact bytes

    run_with([link], body)


def test_unplug_then_replug_reconnects_by_itself(emulator: CameraEmulator) -> None:
    link = link_for(emulator, "back")
    uid = emulator.uid("back")

    async def body() -> None:
        await wait_for(identified(link, uid), "an identified frame")
        # Far enough into this boot (~1 s) that the next boot's frames cannot catch up with
        # `old.seq` before the test reads one, however late a loaded machine lets it look.
        await wait_for(lambda: (f := link.latest()) is not None and f.seq >= 50, "50 messages")
        emulator.unplug("back")
        await wait_for(lambda: not link.status().connected, "the link to notice the unplug")
        assert "end of file" in str(link.status().last_error)
        old = link.latest()
        assert old is not None  # the last frame stays, and ages
        await wait_for(lambda: "open failed" in str(link.status().last_error), "a failed reopen")
        replugged_s = clock()
        emulator.replug("back")
        await wait_for(lambda: link.status().connects == 2, "the reconnect")

        def fresh_identified() -> bool:
            frame = link.latest()
            return (
                frame is not None and frame.receive_time_s > replugged_s and frame.camera_uid == uid
            )

        await wait_for(fresh_identified, "frames after the replug")
        status = link.status()
        assert status.connected and status.reconnects == 1
        new = link.latest()
        assert new is not None and new.seq < old.seq  # the camera rebooted: seq restarted

    run_with([link], body)


def test_silent_camera_is_reopened_and_recovers(emulator: CameraEmulator) -> None:
    link = link_for(emulator, "left", silence_timeout_s=0.2)

    async def body() -> None:
        await wait_for(identified(link, emulator.uid("left")), "an identified frame")
        emulator.stall("left")
        await wait_for(lambda: "silent" in str(link.status().last_error), "the silence watchdog")
        await wait_for(lambda: link.status().connects >= 2, "a reopen")
        emulator.resume("left")
        resumed_s = clock()

        def fresh() -> bool:
            frame = link.latest()
            return frame is not None and frame.receive_time_s > resumed_s

        await wait_for(fresh, "frames after resume")

    run_with([link], body)


def test_second_reader_cannot_steal_the_port(emulator: CameraEmulator) -> None:
    first, second = link_for(emulator, "down"), link_for(emulator, "down")

    async def body() -> None:
        await wait_for(identified(first, emulator.uid("down")), "frames on the first link")
        task = asyncio.create_task(second.run())
        try:
            await wait_for(lambda: second.status().last_error is not None, "the second open")
        finally:
            task.cancel()
        assert "lock" in str(second.status().last_error)
        assert second.status().connects == 0 and first.status().connected

    run_with([first], body)


def garbage(blocks: int, seed: int = 3) -> bytes:
    """`blocks` fake message starts: MAGIC then 40 random bytes without 0xA5, so each block is
    exactly one bad header (its CRC fails) and nothing in it can start another message."""
    rng = np.random.default_rng(seed)
    out = bytearray()
    for _ in range(blocks):
        body = rng.integers(0, 256, 40, dtype=np.uint8)
        body[body == 0xA5] = 0x00
        out += MAGIC + body.tobytes()
    return bytes(out)


def test_garbage_on_the_line_shows_in_counters_and_last_error_and_fps_is_measured(
    emulator: CameraEmulator,
) -> None:
    link = link_for(emulator, "front")
    junk = garbage(12)

    async def body() -> None:
        await wait_for(identified(link, emulator.uid("front")), "an identified frame")
        # 50 Hz from the emulator: the 2 s window fills (a loaded machine may drop a few).
        await wait_for(lambda: link.status().fps >= 20.0, "the frame rate to build up")
        assert link.status().fps <= 51.0
        before = link.status()
        assert before.last_error is None and before.last_error_age_s is None
        assert emulator.inject("front", junk)
        await wait_for(
            lambda: "bad header" in (link.status().last_error or ""), "the garbage reported"
        )
        after = link.status()
        assert after.counters.corrupted_headers - before.counters.corrupted_headers == 12
        assert after.counters.dropped_bytes - before.counters.dropped_bytes == len(junk)
        # e.g. "bad header x12, 504 bytes dropped in the last 1.0 s" (a window boundary may
        # split the burst in two: the counts are the counters' business, the words the operator's;
        # on a loaded machine the emulator may drop a frame in the same window, which the line
        # then also names: "bad header x12, sequence gap x1, 504 bytes dropped ...")
        assert re.fullmatch(
            r"bad header x\d+(, [a-z ]+ x\d+)*, \d+ bytes dropped in the last \d+\.\d s",
            after.last_error or "",
        )
        assert after.last_error_age_s is not None and 0.0 <= after.last_error_age_s < TIMEOUT_S
        assert after.connected  # garbage is reported, not a reason to drop the camera
        frames = after.frames_ok
        await wait_for(lambda: link.status().frames_ok > frames + 5, "frames after the garbage")

    run_with([link], body)
