"""One emulated camera's state and counters (the camera emulator's bookkeeping)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES


def default_uid(face: str) -> str:
    """A stable 12-byte board unique id (24 hex digits) per face, like the STM32F7's."""
    return f"e0c0{FACE_NAMES.index(face):04x}0d5136303638383{FACE_NAMES.index(face)}"


@dataclass
class CameraStats:
    """What one emulated camera did (a copy)."""

    frames_sent: int = 0  # FRAMEs fully queued to the host
    frames_dropped: int = 0  # FRAMEs dropped because the host was not reading
    hellos_sent: int = 0
    connections: int = 0  # times the host opened and configured the port
    host_connected: bool = False
    plugged: bool = True
    stalled: bool = False
    seq: int = 0  # next sequence number


@dataclass
class _Camera:
    face: str
    uid: str
    header_id: int
    path: Path
    master_fd: int | None = None
    poller: Any = None  # select.poll object on master_fd
    boot_s: float = 0.0
    open_since_s: float | None = None  # host port open and raw since (None: not)
    announced: bool = False
    next_hello_s: float = 0.0
    next_status_s: float = 0.0
    pending: bytearray = field(default_factory=bytearray)
    corrupt_left: int = 0
    pushed: tuple[float, float, NDArray[np.uint8]] | None = None  # (send at, captured at, tile)
    fps_frames: int = 0
    fps_since_s: float = 0.0
    stats: CameraStats = field(default_factory=CameraStats)


__all__ = ["CameraStats", "_Camera", "default_uid"]
