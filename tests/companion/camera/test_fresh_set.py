"""The tick follows a fresh six-frame set: `Rig.has_new_set` and `FreshSetWaiter` on a real
event loop, woken by the slots the camera links publish into."""

from __future__ import annotations

import asyncio
import time

import numpy as np

from companion.camera.config import CameraRigConfig, FaceCameraConfig
from companion.camera.fresh_set import FreshSetWaiter
from companion.camera.layout import FACE_NAMES
from companion.camera.rig import Rig
from companion.camera.slot import CameraFrame, LatestSlot


def make_config() -> CameraRigConfig:
    faces = {f: FaceCameraConfig(device=f"/dev/x-{f}", camera_id=f"{i + 1:024x}")
             for i, f in enumerate(FACE_NAMES)}  # fmt: skip
    return CameraRigConfig(faces=faces)


def frame(face: str, seq: int) -> CameraFrame:
    index = FACE_NAMES.index(face)
    return CameraFrame(image=np.zeros((64, 64), np.uint8), seq=seq, capture_timestamp_us=0,
                       capture_time_s=0.0, receive_time_s=0.0, camera_uid=f"{index + 1:024x}",
                       header_camera_id=index, device=f"/dev/x-{face}")  # fmt: skip


def publish_all(slots: dict[str, LatestSlot], seq: int, skip: str | None = None) -> None:
    for face, slot in slots.items():
        if face != skip:
            slot.publish(frame(face, seq))


def test_a_new_set_needs_a_new_frame_on_every_face() -> None:
    slots = {face: LatestSlot() for face in FACE_NAMES}
    rig = Rig(make_config(), slots)
    assert not rig.has_new_set(None)  # nothing received yet
    publish_all(slots, 1)
    assert rig.has_new_set(None)
    assert rig.latest_seqs() == (1,) * 6
    used = rig.latest_seqs()
    assert not rig.has_new_set(used)
    publish_all(slots, 2, skip="down")  # five of six: not yet
    assert not rig.has_new_set(used)
    slots["down"].publish(frame("down", 0))  # a rebooted camera
    assert rig.has_new_set(used)


def test_waiter_returns_on_the_sixth_frame_and_at_the_deadline_otherwise() -> None:
    slots = {face: LatestSlot() for face in FACE_NAMES}
    rig = Rig(make_config(), slots)
    publish_all(slots, 1)
    used = rig.latest_seqs()

    async def scenario() -> tuple[float, float, float]:
        stop = asyncio.Event()
        waiter = FreshSetWaiter(rig, stop, time.monotonic)
        loop = asyncio.get_running_loop()
        start = time.monotonic()
        loop.call_later(0.05, publish_all, slots, 2)
        await waiter.wait(used, start + 5.0)  # woken by the publish, long before 5 s
        woken = time.monotonic() - start
        start = time.monotonic()
        loop.call_later(0.05, publish_all, slots, 3, "up")
        await waiter.wait(rig.latest_seqs(), start + 0.3)  # "up" never comes: the floor
        floor = time.monotonic() - start
        start = time.monotonic()
        loop.call_later(0.05, stop.set)
        await waiter.wait(rig.latest_seqs(), start + 5.0)
        return woken, floor, time.monotonic() - start

    woken, floor, stopped = asyncio.run(scenario())
    assert 0.05 <= woken < 2.0  # not before the set was complete; margins hold under load
    assert 0.3 <= floor < 2.5
    assert 0.05 <= stopped < 2.0
