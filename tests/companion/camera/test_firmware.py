"""The OpenMV script under CPython with stand-in MicroPython modules, decoded by the host parser."""

from __future__ import annotations

import binascii
import importlib.util
import types
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.camera import protocol as p
from companion.camera.protocol import FrameMessage, FrameParser, HelloMessage, StatusMessage

FIRMWARE = Path(__file__).resolve().parents[3] / "firmware_cfg" / "openmv" / "main.py"
TICKS_PERIOD = 1 << 30  # MicroPython ticks_ms/ticks_us wrap here
UNIQUE_ID = bytes.fromhex("3a0025000d51363036383832")
EXPOSURE_US = 12_345
GAIN_DB = 6.25
CORE_TEMP_C = 41.5


class FakeClock:
    """Microsecond clock behind stand-in `time`; starts 2.5 s before ticks_us wraps."""

    def __init__(self) -> None:
        self.us = TICKS_PERIOD - 2_500_000

    def ticks_us(self) -> int:
        return self.us % TICKS_PERIOD

    def ticks_ms(self) -> int:
        return (self.us // 1000) % TICKS_PERIOD

    @staticmethod
    def ticks_diff(a: int, b: int) -> int:
        return (a - b + TICKS_PERIOD // 2) % TICKS_PERIOD - TICKS_PERIOD // 2

    @staticmethod
    def ticks_add(a: int, delta: int) -> int:
        return (a + delta) % TICKS_PERIOD

    def sleep_ms(self, ms: int) -> None:
        self.us += ms * 1000


class FakeImage:
    def __init__(self, pixels: np.ndarray) -> None:
        self.pixels = pixels

    def width(self) -> int:
        return int(self.pixels.shape[1])

    def height(self) -> int:
        return int(self.pixels.shape[0])

    def bytearray(self) -> bytearray:
        return bytearray(self.pixels.tobytes())


class FakeSensor:
    """Records every call; snapshot() returns a deterministic 64x64 image and takes 8 ms."""

    GRAYSCALE = 4
    B64X64 = 40

    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
        self.images: list[np.ndarray] = []

    def _log(self, name: str, *args: Any, **kwargs: Any) -> None:
        self.calls.append((name, args, kwargs))

    def module(self) -> types.ModuleType:
        mod = types.ModuleType("sensor")
        mod.GRAYSCALE = self.GRAYSCALE  # type: ignore[attr-defined]
        mod.B64X64 = self.B64X64  # type: ignore[attr-defined]
        for name in ("reset", "set_pixformat", "set_framesize", "set_windowing", "set_auto_gain",
                     "set_auto_exposure", "set_auto_whitebal"):  # fmt: skip
            setattr(mod, name, lambda *a, _n=name, **k: self._log(_n, *a, **k))
        mod.skip_frames = self.skip_frames  # type: ignore[attr-defined]
        mod.snapshot = self.snapshot  # type: ignore[attr-defined]
        mod.get_exposure_us = lambda: EXPOSURE_US  # type: ignore[attr-defined]
        mod.get_gain_db = lambda: GAIN_DB  # type: ignore[attr-defined]
        return mod

    def skip_frames(self, n: int | None = None, time: int | None = None) -> None:
        self._log("skip_frames", n=n, time=time)
        self.clock.sleep_ms(time or 0)

    def snapshot(self) -> FakeImage:
        self._log("snapshot")
        self.clock.sleep_ms(8)
        k = len(self.images)
        pixels = ((np.arange(64 * 64).reshape(64, 64) * 3 + 17 * k) % 256).astype(np.uint8)
        self.images.append(pixels)
        return FakeImage(pixels)


class FakeUSB:
    """pyb.USB_VCP stand-in: collects writes; `connected_after` polls report no DTR first."""

    def __init__(self, connected_after: int = 0, disconnect_at: tuple[int, int] | None = None):
        self.data = bytearray()
        self.interrupt_char: int | None = None
        self.bytes_before_interrupt_set = 0
        self.polls = 0
        self.connected_after = connected_after
        self.disconnect_at = disconnect_at  # (first poll, last poll) without DTR
        self.writes_while_disconnected = 0
        self._connected = False

    def setinterrupt(self, char: int) -> None:
        self.interrupt_char = char
        self.bytes_before_interrupt_set = len(self.data)

    def isconnected(self) -> bool:
        self.polls += 1
        off = self.disconnect_at
        self._connected = self.polls > self.connected_after and not (
            off is not None and off[0] <= self.polls <= off[1]
        )
        return self._connected

    def write(self, buf: bytes | bytearray) -> int:
        if not self._connected:
            self.writes_while_disconnected += 1
        self.data += buf
        return len(buf)


class FakeADC:
    def __init__(self, resolution: int, mask: int) -> None:
        self.resolution, self.mask = resolution, mask

    def read_core_temp(self) -> float:
        return CORE_TEMP_C


class Camera:
    """The firmware module loaded with fresh stand-ins."""

    def __init__(self) -> None:
        self.clock = FakeClock()
        self.sensor = FakeSensor(self.clock)
        time_mod = types.ModuleType("time")
        for name in ("ticks_us", "ticks_ms", "ticks_diff", "ticks_add", "sleep_ms"):
            setattr(time_mod, name, getattr(self.clock, name))
        pyb = types.ModuleType("pyb")
        pyb.USB_VCP = FakeUSB  # type: ignore[attr-defined]
        pyb.ADCAll = FakeADC  # type: ignore[attr-defined]
        pyb.unique_id = lambda: UNIQUE_ID  # type: ignore[attr-defined]
        machine = types.ModuleType("machine")
        machine.unique_id = lambda: UNIQUE_ID  # type: ignore[attr-defined]
        stand_ins = {
            "sensor": self.sensor.module(),
            "pyb": pyb,
            "time": time_mod,
            "utime": time_mod,
            "machine": machine,
            "micropython": types.ModuleType("micropython"),
        }
        spec = importlib.util.spec_from_file_location("openmv_main_under_test", FIRMWARE)
        assert spec is not None and spec.loader is not None
        self.fw: Any = importlib.util.module_from_spec(spec)
        with mock.patch.dict("sys.modules", stand_ins):  # real `time` is back right after
            spec.loader.exec_module(self.fw)


@pytest.fixture(scope="module")
def firmware() -> Any:
    return Camera().fw


def decode(data: bytes | bytearray) -> tuple[list[p.Message], FrameParser]:
    parser = FrameParser()
    rng = np.random.default_rng(0)
    out: list[p.Message] = []
    view = bytes(data)
    i = 0
    while i < len(view):  # random USB-ish chunk sizes
        n = int(rng.integers(1, 700))
        out += parser.feed(view[i : i + n])
        i += n
    return out, parser


def test_protocol_constants_match_the_host(firmware: Any) -> None:
    assert firmware.MAGIC == p.MAGIC
    assert firmware.PROTOCOL_VERSION == p.PROTOCOL_VERSION
    assert firmware.HEADER_FORMAT == p.HEADER_FORMAT
    assert firmware.HEADER_SIZE == p.HEADER_SIZE
    assert firmware.HEADER_CRC_OFFSET == p.HEADER_CRC_OFFSET
    assert firmware.STATUS_FORMAT == p.STATUS_FORMAT
    assert firmware.I16_UNAVAILABLE == p.I16_UNAVAILABLE
    assert firmware.UNASSIGNED_CAMERA_ID == p.UNASSIGNED_CAMERA_ID
    message_types = (firmware.MSG_FRAME, firmware.MSG_HELLO, firmware.MSG_STATUS)
    assert message_types == tuple(p.MessageType)
    pixel_formats = (firmware.PIXFMT_NONE, firmware.PIXFMT_GRAY8, firmware.PIXFMT_JPEG)
    assert pixel_formats == tuple(p.PixelFormat)


@settings(max_examples=100, deadline=None)
@given(data=st.binary(max_size=600), init=st.integers(0, 0xFFFF))
def test_firmware_crc_equals_binascii(firmware: Any, data: bytes, init: int) -> None:
    assert firmware.crc16(data, init) == binascii.crc_hqx(data, init)
    assert firmware.crc16(memoryview(bytearray(data))) == binascii.crc_hqx(data, 0xFFFF)


def test_firmware_crc_test_vector(firmware: Any) -> None:
    assert firmware.crc16(b"123456789") == 0x29B1


def test_firmware_encoder_is_byte_identical_to_the_host(firmware: Any) -> None:
    fw = firmware
    pixels = ((np.arange(4096) * 7) % 256).astype(np.uint8).reshape(64, 64)
    frame = fw.encode_message(
        fw.MSG_FRAME, 3, fw.PIXFMT_GRAY8, 2**32 + 9, 2**40 + 1, 64, 64, bytearray(pixels.tobytes())
    )
    assert frame == p.encode_frame(pixels, camera_id=3, seq=9, timestamp_us=2**40 + 1)
    hello = fw.hello_payload(fw.hex_id(UNIQUE_ID), fw.FIRMWARE_VERSION, "omv-4.5.9")
    assert fw.encode_message(fw.MSG_HELLO, 3, 0, 0, 7, 0, 0, hello) == p.encode_hello(
        camera_id=3,
        seq=0,
        timestamp_us=7,
        unique_id=UNIQUE_ID,
        firmware=fw.FIRMWARE_VERSION,
        platform="omv-4.5.9",
    )
    status = fw.status_payload(997, 10, 2, 8000, fw.x100_i16(3.5), fw.x100_i16(None))
    assert fw.encode_message(fw.MSG_STATUS, 3, 0, 5, 8, 0, 0, status) == p.encode_status(
        camera_id=3,
        seq=5,
        timestamp_us=8,
        fps_hz=9.97,
        frames_sent=10,
        frames_dropped=2,
        exposure_us=8000,
        gain_db=3.5,
        temperature_c=None,
    )


def test_streams_hello_status_and_frames_the_host_decodes() -> None:
    cam = Camera()
    usb = FakeUSB()
    cam.fw.run(max_frames=25, usb=usb, camera_id=2)
    msgs, parser = decode(usb.data)
    c = parser.counters
    assert parser.buffered_bytes == 0
    assert (c.dropped_bytes, c.corrupted_headers, c.corrupted_payloads, c.invalid_messages) == (
        0,
        0,
        0,
        0,
    )
    assert c.sequence_gaps == 0 and c.frames_ok == len(msgs)
    assert [m.seq for m in msgs] == list(range(len(msgs)))
    assert all(m.camera_id == 2 for m in msgs)

    hello = msgs[0]
    assert isinstance(hello, HelloMessage)
    assert hello.unique_id == UNIQUE_ID.hex()
    assert hello.firmware == cam.fw.FIRMWARE_VERSION and hello.protocol_version == 1
    assert sum(isinstance(m, HelloMessage) for m in msgs) == 2  # t = 0 s and 2 s

    frames = [m for m in msgs if isinstance(m, FrameMessage)]
    assert len(frames) == 25 == len(cam.sensor.images)
    for frame, pixels in zip(frames, cam.sensor.images, strict=True):
        assert frame.image.shape == (64, 64) and np.array_equal(frame.image, pixels)
    stamps = np.array([m.timestamp_us for m in msgs])
    assert np.all(np.diff(stamps) >= 0)  # monotonic across the ticks_us wrap at ~0.5 s
    periods_us = np.diff([f.timestamp_us for f in frames])
    assert np.all(np.abs(periods_us - 100_000) <= 1_000)  # 10 Hz

    statuses = [m for m in msgs if isinstance(m, StatusMessage)]
    assert len(statuses) == 2  # t = 1 s and 2 s
    assert statuses[0].fps_hz == pytest.approx(10.0, abs=0.2)
    assert statuses[-1].frames_sent == 20 and statuses[-1].frames_dropped == 0
    assert statuses[-1].exposure_us == EXPOSURE_US and statuses[-1].gain_db == GAIN_DB
    assert statuses[-1].temperature_c == CORE_TEMP_C


def test_usb_interrupt_disabled_and_exposure_locked_after_warm_up() -> None:
    cam = Camera()
    usb = FakeUSB()
    cam.fw.run(max_frames=2, usb=usb, camera_id=0)
    assert usb.interrupt_char == -1 and usb.bytes_before_interrupt_set == 0
    names = [name for name, _, _ in cam.sensor.calls]
    calls = {name: (args, kwargs) for name, args, kwargs in cam.sensor.calls}
    assert names[:3] == ["reset", "set_pixformat", "set_framesize"]
    assert calls["set_pixformat"][0] == (FakeSensor.GRAYSCALE,)
    assert calls["set_framesize"][0] == (FakeSensor.B64X64,)
    warm_up = names.index("skip_frames")
    assert calls["skip_frames"][1]["time"] >= 1000
    for lock in ("set_auto_gain", "set_auto_exposure", "set_auto_whitebal"):
        assert names.index(lock) > warm_up
        assert calls[lock][0][0] is False
        assert names.index(lock) < names.index("snapshot")
    assert calls["set_auto_exposure"][1] == {"exposure_us": EXPOSURE_US}
    assert calls["set_auto_gain"][1] == {"gain_db": GAIN_DB}


def test_waits_for_dtr_and_announces_again_after_a_reconnect() -> None:
    cam = Camera()
    usb = FakeUSB(connected_after=30, disconnect_at=(50, 60))
    cam.fw.run(max_frames=20, usb=usb, camera_id=1)
    assert usb.writes_while_disconnected == 0
    msgs, parser = decode(usb.data)
    assert isinstance(msgs[0], HelloMessage)
    kinds = [type(m).__name__ for m in msgs]
    first_frame = kinds.index("FrameMessage")
    assert "HelloMessage" in kinds[first_frame:]  # re-announced after the reconnect
    assert sum(isinstance(m, FrameMessage) for m in msgs) == 20
    assert parser.counters.sequence_gaps == 0


def test_camera_id_file(firmware: Any, tmp_path: Path) -> None:
    path = tmp_path / "camera_id.txt"
    assert firmware.load_camera_id(str(path)) == firmware.UNASSIGNED_CAMERA_ID
    path.write_text("4\n")
    assert firmware.load_camera_id(str(path)) == 4
    for bad in ("x", "255", "-1"):
        path.write_text(bad)
        assert firmware.load_camera_id(str(path)) == firmware.UNASSIGNED_CAMERA_ID


def test_clock_extends_wrapping_ticks() -> None:
    cam = Camera()
    clock = cam.fw.MicrosClock()
    readings = []
    for _ in range(40):
        cam.clock.sleep_ms(100)
        readings.append(clock.now_us())
    assert readings == [100_000 * (i + 1) for i in range(40)]  # crosses the 2^30 µs wrap


class FlakyUSB(FakeUSB):
    """Times out on one write (the 4th: the first FRAME's pixels)."""

    def write(self, buf: bytes | bytearray) -> int:
        self.writes = getattr(self, "writes", 0) + 1
        if self.writes == 4:
            raise OSError(110, "ETIMEDOUT")
        return super().write(buf)


def test_a_failed_write_is_reported_and_the_host_resyncs() -> None:
    cam = Camera()
    usb = FlakyUSB()
    cam.fw.run(max_frames=12, usb=usb, camera_id=0)
    msgs, parser = decode(usb.data)
    c = parser.counters
    assert c.corrupted_payloads == 1  # the header went out, its pixels did not
    assert (c.sequence_gaps, c.missed_messages) == (1, 1)
    assert sum(isinstance(m, FrameMessage) for m in msgs) == 12
    status = next(m for m in msgs if isinstance(m, StatusMessage))
    assert status.frames_dropped == 1
