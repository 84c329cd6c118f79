"""A ground station on PX4's GCS link (pymavlink): the pilot in tests, and the eyes that read PX4's
own state.

It sends to PX4's GCS port (SITL instance N: 18570 + N, which answers whoever sent) with its own
heartbeat (a GCS, system 255), and a background thread keeps what PX4 reports: every HEARTBEAT's
mode and armed flag (with receive times, so mode changes are timed), LOCAL_POSITION_NED, the
POSITION_TARGET_LOCAL_NED PX4 flies, GLOBAL_POSITION_INT, STATUSTEXT, COMMAND_ACK and PARAM_VALUE.
Commands are COMMAND_LONG with retries until PX4's ACK. Times: `time.monotonic()` seconds.

Parameters: PX4 answers PARAM_REQUEST_READ for every name it has and says nothing for a name it
does not know (`get_param` returns None after `timeout_s`); INT32 values travel bytewise in the
float field (`decode_param_value`).
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sim_harness.errors import SimError
from sim_harness.hil.netns import NetNamespace
from sim_harness.hil.px4_logic import MavResult, Px4Mode

GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = 190
PARAM_INT32 = mavlink.MAV_PARAM_TYPE_INT32  # 6
PARAM_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32  # 9
_INT_TYPES = range(1, 9)  # UINT8 .. INT64: sent bytewise in the float


class GroundStationError(SimError):
    """PX4 did not answer, or refused."""


def decode_param_value(value: float, param_type: int) -> float:
    """A PARAM_VALUE's number: INT32 and smaller are the float's bytes reinterpreted."""
    if param_type in _INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    return float(value)


def encode_param_value(value: float, param_type: int) -> float:
    """The float field PARAM_SET carries for `value` of `param_type` (bytewise for integers)."""
    if param_type in _INT_TYPES:
        return float(struct.unpack("<f", struct.pack("<i", round(value)))[0])
    return float(value)


@dataclass(frozen=True)
class ModeSample:
    """One HEARTBEAT: receive time, decoded mode (None: not a PX4 mode we know), armed, and
    MAV_STATE (PX4 says CRITICAL or EMERGENCY while a failsafe is active)."""

    t_s: float
    mode: Px4Mode | None
    custom_mode: int
    armed: bool
    system_status: int = mavlink.MAV_STATE_ACTIVE

    @property
    def failsafe(self) -> bool:
        return self.system_status in (mavlink.MAV_STATE_CRITICAL, mavlink.MAV_STATE_EMERGENCY)


@dataclass(frozen=True)
class PositionSample:
    """LOCAL_POSITION_NED: receive time; NED position (m) and velocity (m/s)."""

    t_s: float
    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float

    @property
    def speed_xy_mps(self) -> float:
        return math.hypot(self.vx, self.vy)


class GroundStation:
    """The pilot's ground station for one PX4. Context manager, or start()/stop()."""

    def __init__(
        self,
        port: int,
        namespace: NetNamespace | None = None,
        target_system: int = 1,
        history: int = 20_000,
    ) -> None:
        self.port = port
        self.namespace = namespace
        self.target_system = target_system
        self._lock = threading.Lock()
        self.modes: deque[ModeSample] = deque(maxlen=history)
        self.positions: deque[PositionSample] = deque(maxlen=history)
        self.targets: deque[tuple[float, Any]] = deque(maxlen=history)  # POSITION_TARGET_LOCAL_NED
        self.texts: deque[tuple[float, str]] = deque(maxlen=2000)
        self.global_position: Any = None
        self.sys_status: Any = None
        self._acks: deque[tuple[float, int, int]] = deque(maxlen=200)
        self._params: dict[str, tuple[float, float]] = {}  # name -> (receive time, value)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._conn: Any = None

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> GroundStation:
        url = f"udpout:127.0.0.1:{self.port}"
        if self.namespace is not None:
            with self.namespace.entered():  # the socket lives in PX4's namespace
                self._conn = mavutil.mavlink_connection(
                    url, source_system=GCS_SYSTEM_ID, source_component=GCS_COMPONENT_ID
                )
        else:
            self._conn = mavutil.mavlink_connection(
                url, source_system=GCS_SYSTEM_ID, source_component=GCS_COMPONENT_ID
            )
        self._heartbeat()
        self._thread = threading.Thread(target=self._run, name="gcs", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> GroundStation:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- what PX4 reports --------------------------------------------------------------------

    @property
    def mode(self) -> Px4Mode | None:
        with self._lock:
            return self.modes[-1].mode if self.modes else None

    @property
    def armed(self) -> bool:
        with self._lock:
            return bool(self.modes) and self.modes[-1].armed

    def position(self) -> PositionSample | None:
        with self._lock:
            return self.positions[-1] if self.positions else None

    def positions_since(self, t_s: float) -> list[PositionSample]:
        with self._lock:
            return [p for p in self.positions if p.t_s >= t_s]

    def modes_since(self, t_s: float) -> list[ModeSample]:
        with self._lock:
            return [m for m in self.modes if m.t_s >= t_s]

    def mode_changes(self, since_s: float = 0.0) -> list[ModeSample]:
        """The heartbeats whose mode differs from the one before (the first one counts)."""
        with self._lock:
            samples = list(self.modes)
        changes, previous = [], None
        for sample in samples:
            if sample.mode is not previous:
                if sample.t_s >= since_s:
                    changes.append(sample)
                previous = sample.mode
        return changes

    def texts_since(self, t_s: float) -> list[str]:
        with self._lock:
            return [text for t, text in self.texts if t >= t_s]

    @property
    def home_alt_amsl_m(self) -> float | None:
        """Home altitude AMSL (m) from GLOBAL_POSITION_INT (alt minus relative alt)."""
        gp = self.global_position
        return None if gp is None else (gp.alt - gp.relative_alt) / 1000.0

    @property
    def height_above_home_m(self) -> float | None:
        """Height above home (m): GLOBAL_POSITION_INT's relative_alt, the reference NAV_TAKEOFF's
        target is given in (`takeoff`). Not LOCAL_POSITION_NED's -z: the local frame's origin is
        where PX4's estimator started, which can sit tenths of a metre off the ground (0.74 m above
        it on a loaded machine, where a take-off to 4.59 m then held at a local 3.85 m)."""
        gp = self.global_position
        return None if gp is None else gp.relative_alt / 1000.0

    def wait_until(self, condition: Callable[[], bool], timeout_s: float, what: str) -> float:
        """Seconds until `condition` held (polled every 20 ms); raises after `timeout_s`."""
        start = time.monotonic()
        while not condition():
            if time.monotonic() - start > timeout_s:
                raise GroundStationError(f"timed out after {timeout_s:g} s waiting for {what}")
            time.sleep(0.02)
        return time.monotonic() - start

    def wait_ready(self, timeout_s: float = 30.0) -> float:
        """Until PX4 passes its pre-arm checks (SYS_STATUS PREARM_CHECK healthy) with a local
        position: what "ready for takeoff" means to a ground station. Returns the seconds."""

        def ready() -> bool:
            status = self.sys_status
            bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
            healthy = status is not None and bool(status.onboard_control_sensors_health & bit)
            return healthy and self.position() is not None

        return self.wait_until(ready, timeout_s, "PX4 ready to arm")

    # -- commands ----------------------------------------------------------------------------

    def command(
        self, command: int, *params: float, timeout_s: float = 3.0, retries: int = 3
    ) -> MavResult:
        """COMMAND_LONG to the autopilot until its ACK (re-sent every timeout/retries s)."""
        values = [float(p) for p in params] + [0.0] * (7 - len(params))
        each_s = timeout_s / retries
        for attempt in range(retries):
            sent_s = time.monotonic()
            self._send(
                lambda mav, a=attempt: mav.command_long_encode(
                    self.target_system, 1, command, a, *values
                )
            )
            while time.monotonic() - sent_s < each_s:
                with self._lock:
                    found = [r for t, c, r in self._acks if c == command and t >= sent_s]
                if found:
                    return MavResult(found[0])
                time.sleep(0.01)
        raise GroundStationError(f"no COMMAND_ACK for command {command} within {timeout_s:g} s")

    def set_mode(self, mode: Px4Mode) -> MavResult:
        """DO_SET_MODE as QGroundControl sends it (custom mode: main, sub)."""
        main, sub = mode.value
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, base, main, sub)

    def arm(self, arm: bool = True) -> MavResult:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if arm else 0.0)

    def takeoff(self, altitude_m: float) -> MavResult:
        """NAV_TAKEOFF to `altitude_m` above home (PX4 wants AMSL in param 7)."""
        self.wait_until(lambda: self.home_alt_amsl_m is not None, 10.0, "GLOBAL_POSITION_INT")
        home = self.home_alt_amsl_m
        assert home is not None
        nan = math.nan
        return self.command(mavlink.MAV_CMD_NAV_TAKEOFF, -1, 0, 0, nan, nan, nan, home + altitude_m)

    def arm_and_take_off(self, altitude_m: float, timeout_s: float = 40.0) -> float:
        """Ready, arm, take off and wait until PX4 holds (AUTO_LOITER) near `altitude_m`."""
        start = time.monotonic()
        self.wait_ready(timeout_s)
        for result in (self.arm(), self.takeoff(altitude_m)):
            if result is not MavResult.ACCEPTED:
                raise GroundStationError(f"arm/takeoff refused: {result.name}")

        what = f"HOLD at {altitude_m:g} m after takeoff"
        self.wait_until(lambda: self.holding_at(altitude_m), timeout_s, what)
        return time.monotonic() - start

    def holding_at(self, altitude_m: float, tolerance_m: float = 0.5) -> bool:
        """PX4 in HOLD within `tolerance_m` under `altitude_m` above home (or higher)."""
        height = self.height_above_home_m
        high_enough = height is not None and height > altitude_m - tolerance_m
        return self.mode is Px4Mode.HOLD and high_enough

    def get_param(self, name: str, timeout_s: float = 1.0) -> float | None:
        """PARAM_REQUEST_READ by name; None when PX4 does not answer (it has no such name)."""
        sent_s = time.monotonic()
        for _ in range(3):
            self._send(
                lambda mav: mav.param_request_read_encode(self.target_system, 1, name.encode(), -1)
            )
            deadline = time.monotonic() + timeout_s / 3
            while time.monotonic() < deadline:
                with self._lock:
                    got = self._params.get(name)
                if got is not None and got[0] >= sent_s:
                    return got[1]
                time.sleep(0.005)
        return None

    def set_param(self, name: str, value: float, param_type: int, timeout_s: float = 2.0) -> float:
        """PARAM_SET; returns the value PX4 echoes back (raises when it does not answer)."""
        sent_s = time.monotonic()
        encoded = encode_param_value(value, param_type)
        for _ in range(3):
            self._send(
                lambda mav: mav.param_set_encode(
                    self.target_system, 1, name.encode(), encoded, param_type
                )
            )
            deadline = time.monotonic() + timeout_s / 3
            while time.monotonic() < deadline:
                with self._lock:
                    got = self._params.get(name)
                if got is not None and got[0] >= sent_s:
                    return got[1]
                time.sleep(0.005)
        raise GroundStationError(f"PARAM_SET {name}: no PARAM_VALUE within {timeout_s:g} s")

    # -- the thread --------------------------------------------------------------------------

    def _send(self, build: Callable[[Any], Any]) -> None:
        conn = self._conn
        if conn is not None:
            with self._lock:
                msg = build(conn.mav)
                conn.mav.send(msg)

    def _heartbeat(self) -> None:
        self._send(
            lambda mav: mav.heartbeat_encode(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )
        )

    def _run(self) -> None:
        next_heartbeat_s = time.monotonic() + 1.0
        while not self._stop.is_set():
            conn = self._conn
            if conn is None:
                return
            if time.monotonic() >= next_heartbeat_s:
                self._heartbeat()
                next_heartbeat_s += 1.0
            try:
                msg = conn.recv_match(blocking=True, timeout=0.05)
            except OSError:  # closed under us by stop()
                return
            if msg is not None and msg.get_srcSystem() == self.target_system:
                self._on_message(msg, time.monotonic())

    def _on_message(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        with self._lock:
            if kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                mode = Px4Mode.from_custom_mode(msg.custom_mode)
                self.modes.append(ModeSample(now, mode, msg.custom_mode, armed, msg.system_status))
            elif kind == "LOCAL_POSITION_NED":
                fields = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
                self.positions.append(PositionSample(now, *fields))
            elif kind == "POSITION_TARGET_LOCAL_NED":
                self.targets.append((now, msg))
            elif kind == "GLOBAL_POSITION_INT":
                self.global_position = msg
            elif kind == "SYS_STATUS":
                self.sys_status = msg
            elif kind == "STATUSTEXT":
                self.texts.append((now, str(msg.text)))
            elif kind == "COMMAND_ACK":
                self._acks.append((now, int(msg.command), int(msg.result)))
            elif kind == "PARAM_VALUE":
                name = str(msg.param_id)
                self._params[name] = (now, decode_param_value(msg.param_value, msg.param_type))
