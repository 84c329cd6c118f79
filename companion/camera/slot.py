"""Latest-value frame slots: what one camera link publishes and the rig reads (no queues).

Also maps each camera's own capture clock onto the host's monotonic clock, so that the daemon can
look up the drone's attitude at the moment a picture was taken.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True, eq=False)
class CameraFrame:
    """One 64x64 GRAY8 tile as received from a camera. Times in seconds of the host monotonic clock.

    Equality is identity (arrays do not compare to a bool): compare `image` with `np.array_equal`.
    """

    image: NDArray[np.uint8]  # (64, 64) uint8, row 0 at the top, read-only
    seq: int  # camera message sequence number (u32, wraps)
    capture_timestamp_us: int  # camera clock at capture, µs since the camera script started
    capture_time_s: float  # capture time estimated on the host clock (<= receive_time_s)
    receive_time_s: float  # host clock when the last byte of the frame was read
    camera_uid: str | None  # board unique id from this connection's HELLO; None before HELLO
    header_camera_id: int  # header slot byte (camera_id.txt on the camera, 255 = unassigned)
    device: str  # serial device path the frame came from


class FrameSource(Protocol):
    """Anything that holds the latest frame of one camera (a serial link, a slot, a simulator)."""

    def latest(self) -> CameraFrame | None:
        """The most recent frame, or None if none arrived yet."""
        ...


class LatestSlot:
    """Holds the most recent `CameraFrame`; each publish replaces the previous one.

    A single reference assignment, so one writer and any number of readers (asyncio tasks, or
    threads under CPython) never see a torn value.
    """

    def __init__(self) -> None:
        self._frame: CameraFrame | None = None
        self.on_publish: Callable[[], None] | None = None  # called after each publish

    def publish(self, frame: CameraFrame) -> None:
        """Replace the held frame (then tell `on_publish`, if set: the same thread)."""
        self._frame = frame
        if self.on_publish is not None:
            self.on_publish()

    def latest(self) -> CameraFrame | None:
        """The most recent frame, or None if none was published (or after `clear`)."""
        return self._frame

    def clear(self) -> None:
        """Forget the held frame."""
        self._frame = None


class CaptureClock:
    """Maps a camera's capture timestamps (µs since its script started) to host monotonic seconds.

    offset = host receive time - camera capture time is the clock offset plus the transport delay.
    Its running minimum is the best estimate of offset + the smallest delay, so
    `capture_host_s = capture_cam_s + min offset`, late by that smallest delay (a few ms over USB)
    and free of the jitter of individual reads. The minimum may rise by `drift_per_s` seconds per
    second of camera time, which tracks crystal drift (1e-3 allows 1000 ppm). A camera clock going
    backwards (camera reboot) or `reset()` (reconnect) starts over.
    """

    def __init__(self, drift_per_s: float = 1e-3) -> None:
        self._drift_per_s = drift_per_s
        self._offset_s: float | None = None
        self._last_cam_s = 0.0

    def reset(self) -> None:
        """Forget the estimate (new connection, camera reboot)."""
        self._offset_s = None

    def to_host(self, capture_timestamp_us: int, receive_time_s: float) -> float:
        """Host-clock capture time of a frame captured at `capture_timestamp_us`, received at
        `receive_time_s`; never later than `receive_time_s`."""
        cam_s = capture_timestamp_us * 1e-6
        sample_s = receive_time_s - cam_s
        if self._offset_s is None or cam_s < self._last_cam_s:
            self._offset_s = sample_s
        else:
            relaxed_s = self._offset_s + self._drift_per_s * (cam_s - self._last_cam_s)
            self._offset_s = min(sample_s, relaxed_s)
        self._last_cam_s = cam_s
        return min(cam_s + self._offset_s, receive_time_s)
