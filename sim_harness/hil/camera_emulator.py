"""Six emulated OpenMV cameras on real ptys, speaking camera protocol v1 byte for byte.

Each camera is a pty pair (`os.openpty`); the host side is reached through a stable symlink,
`<directory>/openmv-<face>` (like a udev name), to the pty slave. Messages are built with
`companion.camera.protocol`'s encoders, the ones the firmware's encoder is tested against.

Behaviour copied from firmware_cfg/openmv/main.py:

- A camera sends only while the host has the port open and configured. A pty has no DTR line, so
  "DTR high" is emulated as: the slave has been open (the master does not report POLLHUP) for
  `settle_s`, long enough for the host's open-time input flush, and is in raw mode (ICANON cleared,
  as pyserial's open leaves it). On every such connection it sends a HELLO at once, then a HELLO
  every `hello_period_s`, a STATUS every `status_period_s` and FRAMEs at `rate_hz`.
- One sequence counter per camera numbers every message; `replug` is a camera reboot (seq and
  capture clock restart at 0), reopening the port is not.
- Writes are non-blocking: a message is dropped (and counted, and its seq skipped) while the
  previous one is still waiting for the host to read, like a USB VCP whose host stopped polling.

Runs in one background thread (`start`/`close`, or `with CameraEmulator(...)`), so it serves a
pytest test, an asyncio daemon in the same process, or a daemon in another process. The control
methods (`stall`, `unplug`, `replug`, `inject`, `corrupt_frames`) are thread-safe.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import termios
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.camera.config import CameraRigConfig, FaceCameraConfig
from companion.camera.layout import FACE_NAMES, FACE_SIZE_PX, N_FACES
from companion.camera.protocol import HEADER_SIZE, encode_frame, encode_hello, encode_status
from sim_harness.errors import SimError
from sim_harness.hil.camera_sources import TileSource, as_tile_source, bar_pattern
from sim_harness.hil.camera_state import CameraStats, _Camera, default_uid

logger = logging.getLogger(__name__)

FIRMWARE = "openmv-emulator-1.0.0"
PLATFORM = "sim"
POLL_S = 0.02  # connection polling period, as the firmware polls DTR every 20 ms


class CameraEmulator:
    """Six cameras (FACE_NAMES) on ptys with symlinks `<directory>/<prefix><face>`.

    `source`: a `TileSource` (called once per frame tick for all six cameras), a recorded array
    (N, 64, 384) uint8 of stitched frames played in a loop, one per tick, or None: frames are
    pushed (`push`) by a simulator that renders them at capture time. `clock`: monotonic
    seconds, used for the schedule and the cameras' capture timestamps.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        *,
        source: TileSource | NDArray[np.uint8] | None = bar_pattern,
        rate_hz: float = 10.0,
        hello_period_s: float = 2.0,
        status_period_s: float = 1.0,
        settle_s: float = 0.05,
        uids: Mapping[str, str] | None = None,
        prefix: str = "openmv-",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not rate_hz > 0 or not hello_period_s > 0 or not status_period_s > 0:
            raise SimError("camera emulator: rate_hz and periods must be > 0")
        self._directory = Path(directory)
        self._source = None if source is None else as_tile_source(source)
        self._period_s = 1.0 / rate_hz
        self._hello_period_s = hello_period_s
        self._status_period_s = status_period_s
        self._settle_s = settle_s
        self._clock = clock
        uids = dict(uids or {})
        self._cameras = {
            face: _Camera(
                face=face,
                uid=uids.get(face, default_uid(face)).lower(),
                header_id=index,
                path=self._directory / f"{prefix}{face}",
            )
            for index, face in enumerate(FACE_NAMES)
        }
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start_s = 0.0
        self._next_frame_s = 0.0
        self._tick = 0

    def start(self) -> CameraEmulator:
        """Create the six ptys and symlinks and start streaming in a daemon thread."""
        if self._thread is not None:
            raise SimError("camera emulator: already started")
        if self._source is not None:
            self._tiles(0.0, 0)  # a source of the wrong shape fails here, not in the thread
        self._directory.mkdir(parents=True, exist_ok=True)
        now_s = self._clock()
        self._start_s = self._next_frame_s = now_s
        with self._lock:
            for cam in self._cameras.values():
                self._plug(cam, now_s)
        self._thread = threading.Thread(target=self._run, name="camera-emulator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread, close every pty master and remove the symlinks."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            for cam in self._cameras.values():
                self._unplug(cam)

    def __enter__(self) -> CameraEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def device_path(self, face: str) -> Path:
        """The stable symlink the host opens for `face`."""
        return self._camera(face).path

    def uid(self, face: str) -> str:
        """The board unique id `face`'s camera announces in HELLO."""
        return self._camera(face).uid

    def boot_time_s(self, face: str) -> float:
        """When `face`'s camera last booted, on the emulator's clock: its timestamps' zero."""
        with self._lock:
            return self._camera(face).boot_s

    def stats(self, face: str) -> CameraStats:
        """A copy of one camera's counters and state."""
        with self._lock:
            return CameraStats(**vars(self._camera(face).stats))

    def faces_config(self) -> dict[str, dict[str, str]]:
        """`[cameras.faces]` TOML tables that match this emulator (device and camera_id)."""
        return {
            face: {"device": str(cam.path), "camera_id": cam.uid}
            for face, cam in self._cameras.items()
        }

    def rig_config(self, **options: Any) -> CameraRigConfig:
        """A `CameraRigConfig` for these cameras; `options` set the other fields."""
        faces = {f: FaceCameraConfig(**d) for f, d in self.faces_config().items()}
        return CameraRigConfig(faces=faces, **options)

    def stall(self, face: str) -> None:
        """The camera's script hangs: nothing more is sent (the port stays open)."""
        with self._lock:
            self._camera(face).stats.stalled = True

    def resume(self, face: str) -> None:
        """Undo `stall`."""
        with self._lock:
            self._camera(face).stats.stalled = False

    def unplug(self, face: str) -> None:
        """Cable out: close the pty master (the host reads EOF) and remove the symlink."""
        with self._lock:
            self._unplug(self._camera(face))

    def replug(self, face: str) -> None:
        """Cable in: a new pty, the symlink re-pointed to it; the camera boots (seq 0)."""
        with self._lock:
            cam = self._camera(face)
            self._unplug(cam)
            self._plug(cam, self._clock())

    def inject(self, face: str, data: bytes) -> bool:
        """Queue raw bytes (garbage) between messages; False if the host is not connected."""
        with self._lock:
            cam = self._camera(face)
            if cam.master_fd is None or not cam.announced:
                return False
            cam.pending += data
            return True

    def corrupt_frames(self, face: str, count: int = 1) -> None:
        """Flip one payload byte in each of the next `count` FRAMEs (their payload CRC fails)."""
        with self._lock:
            self._camera(face).corrupt_left += count

    def push(
        self, tiles: NDArray[np.uint8], captured_s: float, send_at_s: NDArray[np.float64]
    ) -> None:
        """Pushed mode: six tiles (6, 64, 64) captured at `captured_s`; face k's FRAME goes out
        at `send_at_s[k]` (clock seconds), stamped with its capture time. A frame still waiting
        when the next one arrives is replaced and counted as dropped, as a camera's own
        double buffer would."""
        if tiles.shape != (N_FACES, FACE_SIZE_PX, FACE_SIZE_PX) or tiles.dtype != np.uint8:
            raise SimError(f"camera emulator: pushed {tiles.dtype} {tiles.shape}, expected uint8 "
                           f"({N_FACES}, {FACE_SIZE_PX}, {FACE_SIZE_PX})")  # fmt: skip
        with self._lock:
            for index, cam in enumerate(self._cameras.values()):
                if cam.pushed is not None:
                    cam.stats.frames_dropped += 1
                cam.pushed = (float(send_at_s[index]), captured_s, tiles[index])

    def _camera(self, face: str) -> _Camera:
        try:
            return self._cameras[face]
        except KeyError:
            raise SimError(f"camera emulator: unknown face {face!r}") from None

    def _plug(self, cam: _Camera, now_s: float) -> None:
        master_fd, slave_fd = os.openpty()
        slave_name = os.ttyname(slave_fd)
        os.close(slave_fd)  # only the host holds the slave: its open/close become visible
        os.set_blocking(master_fd, False)
        poller = select.poll()
        poller.register(master_fd, select.POLLIN)
        tmp = cam.path.with_name(cam.path.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(slave_name)
        os.replace(tmp, cam.path)  # atomic re-point, like udev
        cam.master_fd, cam.poller, cam.boot_s = master_fd, poller, now_s
        cam.open_since_s, cam.announced = None, False
        cam.pending.clear()
        cam.stats.plugged, cam.stats.host_connected, cam.stats.seq = True, False, 0

    def _unplug(self, cam: _Camera) -> None:
        if cam.master_fd is not None:
            os.close(cam.master_fd)
        cam.master_fd = cam.poller = None
        cam.open_since_s, cam.announced = None, False
        cam.pending.clear()
        cam.stats.plugged = cam.stats.host_connected = False
        cam.path.unlink(missing_ok=True)

    def _run(self) -> None:
        next_service_s = self._clock()
        try:
            while not self._stop.is_set():
                now_s = self._clock()
                with self._lock:
                    if now_s >= next_service_s:
                        next_service_s = now_s + POLL_S
                        for cam in self._cameras.values():
                            self._service(cam, now_s)
                    if self._source is None:
                        next_s = self._send_pushed(now_s)
                    elif now_s >= self._next_frame_s:
                        self._send_frames(now_s)
                    busy = any(cam.pending for cam in self._cameras.values())
                    for cam in self._cameras.values():
                        self._flush(cam)
                    due_s = next_s if self._source is None else self._next_frame_s
                    due_s = min(due_s, next_service_s)
                    wait_s = min(due_s - self._clock(), 0.002 if busy else POLL_S)
                self._stop.wait(max(wait_s, 0.0005))
        except Exception:
            logger.exception("camera emulator thread failed")
            raise

    def _host_state(self, cam: _Camera) -> tuple[bool, bool]:
        """(slave open, slave in raw mode), draining anything the host wrote."""
        assert cam.master_fd is not None and cam.poller is not None
        events = cam.poller.poll(0)
        if events and events[0][1] & select.POLLHUP:
            return False, False
        with contextlib.suppress(OSError):  # BlockingIOError once drained
            while os.read(cam.master_fd, 4096):
                pass
        raw = not termios.tcgetattr(cam.master_fd)[3] & termios.ICANON
        return True, raw

    def _service(self, cam: _Camera, now_s: float) -> None:
        if cam.master_fd is None:
            return
        is_open, raw = self._host_state(cam)
        if not is_open:
            if cam.open_since_s is not None:
                logger.debug("camera %s: host closed the port", cam.face)
            cam.open_since_s, cam.announced = None, False
            cam.stats.host_connected = False
            cam.pending.clear()
            return
        if cam.open_since_s is None:
            cam.open_since_s = now_s
        if not raw or now_s - cam.open_since_s < self._settle_s:
            return
        if not cam.announced:
            cam.announced = True
            cam.stats.host_connected = True
            cam.stats.connections += 1
            cam.next_hello_s = now_s
            cam.next_status_s = now_s + self._status_period_s
            cam.fps_frames, cam.fps_since_s = 0, now_s
        if cam.stats.stalled:
            return
        if now_s >= cam.next_hello_s:
            cam.next_hello_s = now_s + self._hello_period_s
            hello = encode_hello(camera_id=cam.header_id, seq=self._next_seq(cam),
                                 timestamp_us=self._camera_us(cam, now_s), unique_id=cam.uid,
                                 firmware=FIRMWARE, platform=PLATFORM)  # fmt: skip
            if self._queue(cam, hello):
                cam.stats.hellos_sent += 1
        if now_s >= cam.next_status_s:
            cam.next_status_s = now_s + self._status_period_s
            elapsed_s = max(now_s - cam.fps_since_s, 1e-6)
            status = encode_status(
                camera_id=cam.header_id, seq=self._next_seq(cam),
                timestamp_us=self._camera_us(cam, now_s),
                fps_hz=min(cam.fps_frames / elapsed_s, 655.0),
                frames_sent=cam.stats.frames_sent & 0xFFFFFFFF,
                frames_dropped=cam.stats.frames_dropped & 0xFFFFFFFF,
                exposure_us=10000, gain_db=0.0, temperature_c=35.0,
            )  # fmt: skip
            cam.fps_frames, cam.fps_since_s = 0, now_s
            self._queue(cam, status)

    def _send_frames(self, now_s: float) -> None:
        missed = int((now_s - self._next_frame_s) / self._period_s)
        self._next_frame_s += (missed + 1) * self._period_s
        tiles = self._tiles(now_s - self._start_s, self._tick)
        self._tick += 1
        for index, cam in enumerate(self._cameras.values()):
            self._send_frame(cam, tiles[index], now_s)

    def _send_pushed(self, now_s: float) -> float:
        """Send every pushed frame that is due; the clock time of the next one (or a poll)."""
        next_s = now_s + POLL_S
        for cam in self._cameras.values():
            if cam.pushed is None:
                continue
            send_at_s, captured_s, tile = cam.pushed
            if now_s >= send_at_s:
                cam.pushed = None
                self._send_frame(cam, tile, captured_s)
            else:
                next_s = min(next_s, send_at_s)
        return next_s

    def _send_frame(self, cam: _Camera, tile: NDArray[np.uint8], captured_s: float) -> None:
        if cam.master_fd is None or not cam.announced or cam.stats.stalled:
            return
        frame = bytearray(encode_frame(tile, camera_id=cam.header_id, seq=self._next_seq(cam),
                                       timestamp_us=self._camera_us(cam, captured_s)))  # fmt: skip
        if cam.corrupt_left > 0:
            cam.corrupt_left -= 1
            frame[(HEADER_SIZE + len(frame)) // 2] ^= 0x5A  # mid-payload
        if self._queue(cam, bytes(frame)):
            cam.stats.frames_sent += 1
            cam.fps_frames += 1
        else:
            cam.stats.frames_dropped += 1

    def _tiles(self, t_s: float, tick: int) -> NDArray[np.uint8]:
        tiles = self._source(t_s, tick)
        if tiles.shape != (N_FACES, FACE_SIZE_PX, FACE_SIZE_PX) or tiles.dtype != np.uint8:
            raise SimError(f"camera emulator: source gave {tiles.dtype} {tiles.shape}, expected "
                           f"uint8 ({N_FACES}, {FACE_SIZE_PX}, {FACE_SIZE_PX})")  # fmt: skip
        return tiles

    @staticmethod
    def _next_seq(cam: _Camera) -> int:
        seq = cam.stats.seq
        cam.stats.seq = (seq + 1) & 0xFFFFFFFF
        return seq

    @staticmethod
    def _camera_us(cam: _Camera, t_s: float) -> int:
        """The camera's capture clock at clock time `t_s`: µs since it booted (was plugged)."""
        return max(0, int((t_s - cam.boot_s) * 1e6))

    @classmethod
    def _queue(cls, cam: _Camera, message: bytes) -> bool:
        """Queue a whole message, or drop it (False) while the previous one is still pending."""
        cls._flush(cam)
        if cam.pending:
            return False
        cam.pending += message
        return True

    @staticmethod
    def _flush(cam: _Camera) -> None:
        if cam.master_fd is None or not cam.pending:
            return
        try:
            written = os.write(cam.master_fd, cam.pending)
        except BlockingIOError:
            return
        except OSError:  # host side gone mid-write: drop, the next poll sees it
            cam.pending.clear()
            return
        del cam.pending[:written]
