"""One asyncio reader per OpenMV camera on USB serial: open, parse, publish latest frame, reconnect.

Reading: the port is opened by pyserial (which leaves the fd non-blocking) and read with
`loop.add_reader` + `os.read`, on the event loop itself. Why not a thread: the work per read is
one syscall and one `FrameParser.feed` (CRC in C), about 41 kB/s per camera; an fd callback adds
no thread hand-off latency, no locks around the slot and the parser, and cancellation is simply
`remove_reader` + close. A read error, an end of file (pty master gone, USB hang-up) or an
epoll HUP/ERR (which wakes the reader) ends the connection.

Connecting (`SerialCameraLink.run`): open at `baud` (never 921600/12000000: OpenMV IDE debug
mode) with DTR low and exclusive (flock) access, flush the input, hold DTR low for `dtr_low_s`,
flush again, raise DTR. The camera sends only while DTR is high and announces itself with a HELLO
on every rising edge, so that HELLO lands in an empty buffer. A pty (the emulator) has no DTR
(ENOTTY): there the input is flushed once and the wait is skipped.

Lost connection, failed open or `silence_timeout_s` without a byte -> close, wait (exponential
backoff from `reconnect_min_s` to `reconnect_max_s`, reset once a connection delivered a valid
message) and reopen the same path. I/O errors never escape `run`.

Each valid 64x64 FRAME is published into a `LatestSlot` (see `companion.camera.slot`) with the host
receive time from the injected monotonic clock and the camera's capture time mapped onto it.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import serial

from companion.camera.config import DEFAULT_BAUD, CameraRigConfig, validate_baud
from companion.camera.layout import FACE_SIZE_PX
from companion.camera.link_stats import ErrorWindow, FrameRate
from companion.camera.protocol import (
    FrameMessage,
    FrameParser,
    HelloMessage,
    Message,
    ParserCounters,
    StatusMessage,
)
from companion.camera.slot import CameraFrame, CaptureClock, LatestSlot
from companion.validation import require_range

logger = logging.getLogger(__name__)

READ_SIZE = 65536  # bytes per os.read; a pty hands out at most 4095 at a time
CHECK_PERIOD_S = 0.1  # how often the silence watchdog looks (asyncio time)
ERROR_LOG_EVERY_S = 10.0  # while errors go on, log them at most this often (last_error: always)


@dataclass(frozen=True)
class LinkStatus:
    """Snapshot of one link, for health reporting. Times in seconds (host monotonic clock)."""

    device: str
    connected: bool  # port open and not yet lost
    camera_uid: str | None  # board unique id from this connection's HELLO, None before it
    header_camera_id: int | None  # header slot byte from that HELLO (255 = unassigned)
    firmware: str | None  # HELLO `fw`
    frames_ok: int  # 64x64 FRAMEs published since the link was created
    rejected_frames: int  # valid FRAMEs of another size, not published
    counters: ParserCounters  # parser counters over all connections (copy)
    connects: int  # successful opens
    reconnects: int  # successful opens after a lost connection
    last_frame_age_s: float | None  # now - receive time of the latest frame; None: no frame yet
    last_error: str | None  # why the last connection ended, the last open failed, or the
    # parser errors of the last 1 s window that held any ("bad header x12 in the last 1.0 s")
    last_error_age_s: float | None  # now - when last_error was set; None: no error yet
    fps: float  # 64x64 frames published per second over the last 2 s
    camera_status: StatusMessage | None  # latest STATUS from the camera (fps, drops, exposure)


class SerialCameraLink:
    """Reads one camera's serial device forever (`run`) and keeps its latest frame (`latest`).

    `clock` is the host monotonic clock in seconds (injected for tests); backoff and watchdog
    delays use the event loop's own timer.
    """

    def __init__(
        self,
        device: str,
        *,
        baud: int = DEFAULT_BAUD,
        reconnect_min_s: float = 0.1,
        reconnect_max_s: float = 2.0,
        silence_timeout_s: float = 2.0,
        dtr_low_s: float = 0.05,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.device = device
        self._baud = validate_baud("baud", baud)
        self._reconnect_min_s = require_range("reconnect_min_s", reconnect_min_s, 0.0, 60.0,
                                              low_inclusive=False)  # fmt: skip
        self._reconnect_max_s = require_range("reconnect_max_s", reconnect_max_s,
                                              self._reconnect_min_s, 60.0)  # fmt: skip
        self._silence_timeout_s = require_range("silence_timeout_s", silence_timeout_s, 0.0, 60.0,
                                                low_inclusive=False)  # fmt: skip
        self._dtr_low_s = require_range("dtr_low_s", dtr_low_s, 0.0, 1.0)
        self._clock = clock
        self._slot = LatestSlot()
        self._parser = FrameParser()
        self._capture_clock = CaptureClock()
        self._port: serial.Serial | None = None
        self._lost: asyncio.Event | None = None
        self._last_byte_s = 0.0
        self._got_message = False
        self._hello: HelloMessage | None = None
        self._camera_status: StatusMessage | None = None
        self._frames_ok = 0
        self._rejected_frames = 0
        self._connects = 0
        self._last_error: str | None = None
        self._last_error_s = 0.0
        self._frame_rate = FrameRate()
        self._error_window = ErrorWindow()
        self._last_error_log_s: float | None = None

    @classmethod
    def from_config(
        cls, face: str, config: CameraRigConfig, *, clock: Callable[[], float] = time.monotonic
    ) -> SerialCameraLink:
        """The link for one face of a validated rig config."""
        return cls(
            config.faces[face].device,
            baud=config.baud,
            reconnect_min_s=config.reconnect_min_s,
            reconnect_max_s=config.reconnect_max_s,
            silence_timeout_s=config.silence_timeout_s,
            clock=clock,
        )

    @property
    def slot(self) -> LatestSlot:
        """The latest-value slot this link publishes into."""
        return self._slot

    def latest(self) -> CameraFrame | None:
        """The most recent 64x64 frame (kept across reconnects; judge it by its receive time)."""
        return self._slot.latest()

    def status(self) -> LinkStatus:
        """A snapshot of the link's state and counters."""
        frame = self._slot.latest()
        hello = self._hello
        now_s = self._clock()
        return LinkStatus(
            device=self.device,
            connected=self._port is not None and self._lost is not None and not self._lost.is_set(),
            camera_uid=None if hello is None else hello.unique_id,
            header_camera_id=None if hello is None else hello.camera_id,
            firmware=None if hello is None else hello.firmware,
            frames_ok=self._frames_ok,
            rejected_frames=self._rejected_frames,
            counters=self._parser.counters,
            connects=self._connects,
            reconnects=max(0, self._connects - 1),
            last_frame_age_s=None if frame is None else now_s - frame.receive_time_s,
            last_error=self._last_error,
            camera_status=self._camera_status,
            last_error_age_s=None if self._last_error is None else now_s - self._last_error_s,
            fps=self._frame_rate.fps(now_s),
        )

    async def run(self) -> None:
        """Connect, read until the connection is lost, back off, reconnect; until cancelled."""
        delay_s = self._reconnect_min_s
        try:
            while True:
                if await self._connect():
                    await self._pump()
                    if self._got_message:
                        delay_s = self._reconnect_min_s
                await asyncio.sleep(delay_s)
                delay_s = min(2.0 * delay_s, self._reconnect_max_s)
        finally:
            self._close()

    async def _connect(self) -> bool:
        """Open the port and raise DTR; False (reason in `last_error`) if that failed."""
        port = serial.Serial()
        port.port = self.device
        port.baudrate = self._baud
        port.timeout = 0
        port.exclusive = True  # flock: a second reader would steal half the bytes
        port.dtr = False  # raised below, after the input was flushed
        try:
            port.open()
            self._port = port
            has_dtr = _set_dtr(port, False)
            port.reset_input_buffer()
            if has_dtr:
                if self._dtr_low_s > 0:  # the camera polls DTR every 20 ms: let it see it low
                    await asyncio.sleep(self._dtr_low_s)
                    port.reset_input_buffer()
                _set_dtr(port, True)
        except (serial.SerialException, OSError) as exc:
            self._close()
            reason = f"open failed: {exc}"
            if reason != self._last_error:
                logger.warning("camera %s: %s", self.device, reason)
            self._set_error(reason)
            return False
        self._connects += 1
        self._parser.reset()
        self._capture_clock.reset()
        self._hello = None
        self._camera_status = None
        self._got_message = False
        self._last_byte_s = self._clock()
        logger.info("camera %s: connected (%d)", self.device, self._connects)
        return True

    async def _pump(self) -> None:
        """Read until the connection is lost or silent for `silence_timeout_s`, then close."""
        port = self._port
        assert port is not None
        loop = asyncio.get_running_loop()
        lost = self._lost = asyncio.Event()
        fd = port.fileno()
        check_s = min(CHECK_PERIOD_S, self._silence_timeout_s)
        loop.add_reader(fd, self._on_readable, fd)
        try:
            while not lost.is_set():
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(lost.wait(), check_s)
                silent_s = self._clock() - self._last_byte_s
                if not lost.is_set() and silent_s > self._silence_timeout_s:
                    self._mark_lost(f"silent for {silent_s:.2f} s")
        finally:
            loop.remove_reader(fd)
            lost.set()
            self._close()
        logger.warning("camera %s: connection lost: %s", self.device, self._last_error)

    def _on_readable(self, fd: int) -> None:
        try:
            data = os.read(fd, READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._mark_lost(f"read error: {exc.strerror or exc}")
            return
        if not data:
            self._mark_lost("end of file (device closed or unplugged)")
            return
        now_s = self._clock()
        self._last_byte_s = now_s
        for message in self._parser.feed(data):
            self._handle(message, now_s)
        errors = self._error_window.update(self._parser.counters, now_s)
        if errors is not None:
            self._set_error(errors)
            last_log_s = self._last_error_log_s
            if last_log_s is None or now_s - last_log_s >= ERROR_LOG_EVERY_S:
                self._last_error_log_s = now_s
                logger.warning("camera %s: %s", self.device, errors)

    def _set_error(self, reason: str) -> None:
        self._last_error = reason
        self._last_error_s = self._clock()

    def _mark_lost(self, reason: str) -> None:
        self._set_error(reason)
        if self._lost is not None and not self._lost.is_set():
            self._lost.set()
            if self._port is not None and self._port.fd is not None:
                asyncio.get_running_loop().remove_reader(self._port.fd)

    def _handle(self, message: Message, now_s: float) -> None:
        self._got_message = True
        if isinstance(message, FrameMessage):
            if message.image.shape != (FACE_SIZE_PX, FACE_SIZE_PX):
                self._rejected_frames += 1
                return
            hello = self._hello
            self._slot.publish(
                CameraFrame(
                    image=message.image,
                    seq=message.seq,
                    capture_timestamp_us=message.timestamp_us,
                    capture_time_s=self._capture_clock.to_host(message.timestamp_us, now_s),
                    receive_time_s=now_s,
                    camera_uid=None if hello is None else hello.unique_id,
                    header_camera_id=message.camera_id,
                    device=self.device,
                )
            )
            self._frames_ok += 1
            self._frame_rate.add(now_s)
        elif isinstance(message, HelloMessage):
            previous = self._hello
            if message.seq == 0 and previous is not None:  # camera script restarted
                self._capture_clock.reset()
            if previous is None or previous.unique_id != message.unique_id:
                logger.info("camera %s: HELLO from camera %s (slot %d, %s)", self.device,
                            message.unique_id, message.camera_id, message.firmware)  # fmt: skip
            self._hello = message
        elif isinstance(message, StatusMessage):
            self._camera_status = message

    def _close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError) as exc:  # device already gone
                logger.debug("camera %s: close: %s", self.device, exc)


def _set_dtr(port: serial.Serial, level: bool) -> bool:
    """Set DTR; False if the port has no modem lines (a pty: ENOTTY/EINVAL)."""
    try:
        port.dtr = level
    except OSError as exc:
        if exc.errno not in (errno.ENOTTY, errno.EINVAL):
            raise
        return False
    return True


def links_from_config(
    config: CameraRigConfig, *, clock: Callable[[], float] = time.monotonic
) -> dict[str, SerialCameraLink]:
    """One link per face (FACE_NAMES order), keyed by face name."""
    return {face: SerialCameraLink.from_config(face, config, clock=clock) for face in config.faces}


async def run_links(links: Iterable[SerialCameraLink] | Mapping[str, SerialCameraLink]) -> None:
    """Run every link under one TaskGroup until cancelled (links never fail on I/O errors)."""
    items = list(links.values()) if isinstance(links, Mapping) else list(links)
    async with asyncio.TaskGroup() as group:
        for link in items:
            group.create_task(link.run(), name=f"camera-link {link.device}")


__all__ = [
    "LinkStatus",
    "SerialCameraLink",
    "links_from_config",
    "run_links",
]
