"""OpenMV Cam M7 script: 64x64 GRAY8 frames at 10 Hz to the companion over USB, protocol v1.

Copy to the camera's flash as main.py (OpenMV runs it at boot with __name__ == "__main__").
Optional: a file camera_id.txt on the camera's flash holding the slot number 0..254; without it
the header's camera_id is 255 (unassigned) and the companion maps the board unique id from HELLO.

Wire format: docs/camera-protocol.md. This file cannot import `companion`, so it carries its own
encoder; its constants must stay identical to companion/camera/protocol.py (a test compares the
bytes). Everything above "Camera side" runs under CPython too: the tests import this file with
stand-in `sensor`, `pyb`, `time`, `machine` and `micropython` modules.
"""

# ruff: noqa: UP032  (str.format, not f-strings: older OpenMV/MicroPython builds lack f-strings)

import array
import struct
import sys
import time

import pyb
import sensor

try:
    import machine
except ImportError:
    machine = None
try:
    import micropython
except ImportError:
    micropython = None

FIRMWARE_VERSION = "openmv-cam-1.0.0"

# Protocol constants: identical to companion/camera/protocol.py.
MAGIC = b"\xa5\x5a"
PROTOCOL_VERSION = 1
HEADER_FORMAT = "<2sBBBBHIQHHIHH"
HEADER_SIZE = 32
HEADER_CRC_OFFSET = 30
MSG_FRAME = 1
MSG_HELLO = 2
MSG_STATUS = 3
PIXFMT_NONE = 0
PIXFMT_GRAY8 = 1
PIXFMT_JPEG = 2  # reserved, not sent by v1
STATUS_FORMAT = "<HIIIhh"
I16_UNAVAILABLE = -32768
U32_MASK = 0xFFFFFFFF
UNASSIGNED_CAMERA_ID = 255

# Timing (ms) and files.
FRAME_PERIOD_MS = 100  # 10 Hz
STATUS_PERIOD_MS = 1000
HELLO_PERIOD_MS = 2000
WARMUP_MS = 2000  # auto gain/exposure settle before they are locked
IDLE_POLL_MS = 20  # DTR polling while the host has the port closed
CAMERA_ID_FILE = "camera_id.txt"


def _make_crc_table():
    table = array.array("H", [0] * 256)
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table[i] = crc & 0xFFFF
    return table


_CRC_TABLE = _make_crc_table()


def _crc16_py(data, crc=0xFFFF):
    table = _CRC_TABLE
    for byte in data:
        crc = ((crc << 8) & 0xFF00) ^ table[(crc >> 8) ^ byte]
    return crc


# Viper (native code, ~50x faster) where the port has an emitter; compiled through exec so that a
# build without one, or CPython, falls back to the table loop above instead of failing to load.
_CRC16_VIPER_SRC = """
@micropython.viper
def _crc16_viper(buf, n: int, crc: int) -> int:
    src = ptr8(buf)
    table = ptr16(_CRC_TABLE)
    i = 0
    while i < n:
        crc = ((crc << 8) & 0xFF00) ^ table[((crc >> 8) ^ src[i]) & 0xFF]
        i += 1
    return crc
"""


def _load_fast_crc():
    if sys.implementation.name != "micropython":
        return None
    scope = globals()
    try:
        exec(_CRC16_VIPER_SRC, scope)
        fast = scope["_crc16_viper"]
        return fast if fast(b"123456789", 9, 0xFFFF) == 0x29B1 else None
    except Exception:  # no native emitter on this build: keep the portable loop
        return None


_crc16_fast = _load_fast_crc()


def crc16(data, crc=0xFFFF):
    """CRC-16/CCITT-FALSE of a buffer (poly 0x1021, init 0xFFFF); 0x29B1 for b"123456789"."""
    if _crc16_fast is not None:
        return _crc16_fast(data, len(data), crc)
    return _crc16_py(data, crc)


def encode_header(msg_type, camera_id, pixel_format, seq, timestamp_us, width, height, payload):
    """32-byte header for `payload` (bytes-like); seq u32, timestamp_us u64."""
    header = bytearray(HEADER_SIZE)
    struct.pack_into(
        HEADER_FORMAT, header, 0, MAGIC, PROTOCOL_VERSION, msg_type, camera_id, pixel_format, 0,
        seq & U32_MASK, timestamp_us, width, height, len(payload), crc16(payload), 0,
    )  # fmt: skip
    struct.pack_into("<H", header, HEADER_CRC_OFFSET, crc16(memoryview(header)[:HEADER_CRC_OFFSET]))
    return header


def encode_message(msg_type, camera_id, pixel_format, seq, timestamp_us, width, height, payload):
    """Header + payload as one bytes object (HELLO/STATUS; FRAMEs are written in two parts)."""
    header = encode_header(
        msg_type, camera_id, pixel_format, seq, timestamp_us, width, height, payload
    )
    return bytes(header) + bytes(payload)


def hello_payload(uid_hex, firmware, platform):
    """Compact JSON, same bytes as companion's hello_payload (ASCII strings without quotes)."""
    text = '{{"uid":"{}","fw":"{}","proto":{},"omv":"{}"}}'.format(
        uid_hex, firmware, PROTOCOL_VERSION, platform
    )
    return text.encode()


def x100_i16(value):
    """Value in hundredths as int16, or I16_UNAVAILABLE for None."""
    if value is None:
        return I16_UNAVAILABLE
    scaled = round(value * 100)  # int on MicroPython too
    return max(-32767, min(32767, scaled))


def status_payload(fps_x100, frames_sent, frames_dropped, exposure_us, gain_x100, temp_x100):
    """18-byte STATUS payload (STATUS_FORMAT)."""
    return struct.pack(
        STATUS_FORMAT,
        max(0, min(0xFFFF, fps_x100)),
        frames_sent & U32_MASK,
        frames_dropped & U32_MASK,
        exposure_us & U32_MASK,
        gain_x100,
        temp_x100,
    )


def hex_id(raw):
    """Lowercase hex of a bytes object (machine.unique_id())."""
    return "".join("{:02x}".format(b) for b in raw)


class MicrosClock:
    """Microseconds since start as an unbounded int, from time.ticks_us (wraps at 2^30 on
    OpenMV). Call now_us() at least every 2^29 µs (~9 min); the loop calls it every <= 100 ms.
    """

    def __init__(self):
        self._last = time.ticks_us()
        self._total = 0

    def now_us(self):
        now = time.ticks_us()
        self._total += time.ticks_diff(now, self._last)
        self._last = now
        return self._total


# Camera side --------------------------------------------------------------------------------


def board_uid_hex():
    """The MCU's unique id (12 bytes on the STM32F7) as hex; identifies the camera in-band."""
    raw = machine.unique_id() if machine is not None else pyb.unique_id()
    return hex_id(raw)


def platform_version():
    """OpenMV firmware version if the `omv` module exists, else the MicroPython version."""
    try:
        import omv

        return "omv-" + omv.version_string()
    except (ImportError, AttributeError):
        return "py-{}.{}.{}".format(*sys.implementation.version[:3])


def load_camera_id(path=CAMERA_ID_FILE):
    """Slot number 0..254 from `path` on the camera's flash, else UNASSIGNED_CAMERA_ID."""
    try:
        with open(path) as f:
            value = int(f.read().strip())
    except (OSError, ValueError):
        return UNASSIGNED_CAMERA_ID
    return value if 0 <= value < UNASSIGNED_CAMERA_ID else UNASSIGNED_CAMERA_ID


def setup_sensor(warmup_ms=WARMUP_MS):
    """64x64 grayscale; auto gain/exposure settle for `warmup_ms`, then both are locked.

    Returns (exposure_us, gain_db or None), the locked values.
    """
    sensor.reset()
    sensor.set_pixformat(sensor.GRAYSCALE)
    if hasattr(sensor, "B64X64"):
        sensor.set_framesize(sensor.B64X64)
    else:  # older firmware: centre 64x64 window of QQVGA (narrower field of view)
        sensor.set_framesize(sensor.QQVGA)
        sensor.set_windowing((64, 64))
    sensor.skip_frames(time=warmup_ms)
    try:
        gain_db = sensor.get_gain_db()
    except (AttributeError, RuntimeError, OSError):
        gain_db = None
    exposure_us = sensor.get_exposure_us()
    if gain_db is None:
        sensor.set_auto_gain(False)
    else:
        sensor.set_auto_gain(False, gain_db=gain_db)
    sensor.set_auto_exposure(False, exposure_us=exposure_us)
    sensor.set_auto_whitebal(False)
    return exposure_us, gain_db


class Streamer:
    """Sends HELLO (at start and every 2 s), STATUS (every 1 s) and FRAMEs (10 Hz) over `usb`.

    One sequence counter (u32) numbers every message of every type, starting at 0 with a HELLO.
    """

    def __init__(self, usb, camera_id, exposure_us, gain_db):
        self.usb = usb
        self.camera_id = camera_id
        self.exposure_us = exposure_us
        self.gain_x100 = x100_i16(gain_db)
        self.clock = MicrosClock()
        self.seq = 0
        self.frames_sent = 0
        self.frames_dropped = 0
        self.uid_hex = board_uid_hex()
        self.platform = platform_version()
        self._fps_frames = 0
        self._fps_since_ms = time.ticks_ms()
        try:
            self._adc = pyb.ADCAll(12, 0x70000)  # internal channels: temperature, vref, vbat
        except (AttributeError, ValueError, OSError):
            self._adc = None

    def _write(self, data):
        try:
            written = self.usb.write(data)
        except OSError:  # USB write timed out (host stopped reading)
            return False
        return written == len(data)

    def send(self, msg_type, pixel_format, width, height, payload, timestamp_us):
        """Write one message; False if the USB write was short (the host will see a gap)."""
        header = encode_header(
            msg_type, self.camera_id, pixel_format, self.seq, timestamp_us, width, height, payload
        )
        self.seq = (self.seq + 1) & U32_MASK
        return self._write(header) and self._write(payload)

    def send_hello(self):
        payload = hello_payload(self.uid_hex, FIRMWARE_VERSION, self.platform)
        self.send(MSG_HELLO, PIXFMT_NONE, 0, 0, payload, self.clock.now_us())

    def temperature_c(self):
        if self._adc is None:
            return None
        try:
            return float(self._adc.read_core_temp())
        except (AttributeError, ValueError, OSError):
            return None

    def send_status(self, now_ms):
        elapsed_ms = time.ticks_diff(now_ms, self._fps_since_ms)
        fps_x100 = self._fps_frames * 100000 // elapsed_ms if elapsed_ms > 0 else 0
        self._fps_frames = 0
        self._fps_since_ms = now_ms
        payload = status_payload(
            fps_x100,
            self.frames_sent,
            self.frames_dropped,
            self.exposure_us,
            self.gain_x100,
            x100_i16(self.temperature_c()),
        )
        self.send(MSG_STATUS, PIXFMT_NONE, 0, 0, payload, self.clock.now_us())

    def send_frame(self):
        img = sensor.snapshot()
        timestamp_us = self.clock.now_us()  # when snapshot() returned
        pixels = img.bytearray()  # view of the frame buffer, no copy
        if self.send(MSG_FRAME, PIXFMT_GRAY8, img.width(), img.height(), pixels, timestamp_us):
            self.frames_sent += 1
            self._fps_frames += 1
        else:
            self.frames_dropped += 1

    def loop(self, max_frames=None):
        """Stream until `max_frames` FRAMEs were sent (forever if None)."""
        ticks_diff, ticks_add = time.ticks_diff, time.ticks_add
        connected = False
        now = time.ticks_ms()
        next_frame = next_hello = now
        next_status = ticks_add(now, STATUS_PERIOD_MS)
        while max_frames is None or self.frames_sent < max_frames:
            self.clock.now_us()  # keep the 64-bit extension of ticks_us current
            now = time.ticks_ms()
            if not self.usb.isconnected():  # host has not asserted DTR, or closed the port
                connected = False
                time.sleep_ms(IDLE_POLL_MS)
                continue
            if not connected:  # (re)connected: announce at once, restart the frame clock
                connected = True
                next_frame = next_hello = now
                self._fps_frames, self._fps_since_ms = 0, now
            if ticks_diff(now, next_hello) >= 0:
                self.send_hello()
                next_hello = ticks_add(now, HELLO_PERIOD_MS)
            if ticks_diff(now, next_status) >= 0:
                self.send_status(now)
                next_status = ticks_add(now, STATUS_PERIOD_MS)
            late_ms = ticks_diff(now, next_frame)
            if late_ms >= 0:
                missed = late_ms // FRAME_PERIOD_MS  # whole periods overrun: frames not taken
                self.frames_dropped += missed
                next_frame = ticks_add(next_frame, (missed + 1) * FRAME_PERIOD_MS)
                self.send_frame()
                continue
            wait_ms = min(-late_ms, ticks_diff(next_status, now), ticks_diff(next_hello, now))
            if wait_ms > 0:
                time.sleep_ms(wait_ms)


def run(max_frames=None, usb=None, camera_id=None):
    """Set up USB and the sensor, then stream (forever if `max_frames` is None); -> Streamer."""
    if usb is None:
        usb = pyb.USB_VCP()
    usb.setinterrupt(-1)  # a 0x03 byte from the host must not raise KeyboardInterrupt
    if camera_id is None:
        camera_id = load_camera_id()
    exposure_us, gain_db = setup_sensor()
    streamer = Streamer(usb, camera_id, exposure_us, gain_db)
    streamer.loop(max_frames)
    return streamer


if __name__ == "__main__":
    try:
        run()
    except Exception:  # any crash: reboot, the host then sees a fresh HELLO with seq 0
        time.sleep_ms(1000)
        if machine is not None:
            machine.reset()
        raise
