"""A PX4 emulator that MAVSDK talks to over MAVLink 2 on loopback UDP.

Wiring (the same as PX4 SITL): the client (MAVSDK) listens with `udpin://127.0.0.1:PORT`; the
emulator binds its own ephemeral port on 127.0.0.1 and sends everything to PORT, and MAVSDK
answers to the address the datagrams came from. The emulator can therefore start before or after
the client, and never needs to learn the client's address. Two listeners on one port do not fail
on Linux, so the harness must hand out distinct ports (`emulator_config.free_udp_port`).

The emulator runs in one background thread: it receives commands and setpoints, applies PX4's
mode and arming rules (`px4_logic`), steps a `VehicleBackend` (default: `FirstOrderVehicle`) at
the physics rate and streams telemetry like PX4 does for an onboard link. Test hooks: the logs of
setpoints, commands and mode changes; `pilot_switch_mode` (the RC pilot changes mode);
`set_link_alive(False)` (the link drops: nothing is sent and everything received is ignored);
`set_heartbeat_alive(False)` (only the heartbeat stops, everything else flows);
`set_failsafe(True)` (a PX4 failsafe such as a geofence breach: the heartbeat says CRITICAL).
Like PX4 >= 1.15 it sends CURRENT_MODE with each heartbeat and as soon as the mode changes, with
the intended mode (OFFBOARD while the offboard-loss failsafe waits to resume it), and reports
MAV_STATE_CRITICAL in the heartbeat during that failsafe.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from types import TracebackType

from pymavlink.dialects.v20 import common as mavlink

from sim_harness.errors import SimError
from sim_harness.hil import px4_commands as cmds
from sim_harness.hil import px4_messages as msgs
from sim_harness.hil.emulated_vehicle import FirstOrderVehicle, VehicleBackend, VehicleStateNed
from sim_harness.hil.emulator_config import LOOPBACK, EmulatorConfig
from sim_harness.hil.px4_logic import (
    LandedState,
    MavResult,
    ModeChange,
    Px4Logic,
    Px4LogicConfig,
    Px4Mode,
)
from sim_harness.hil.px4_messages import SetpointRecord
from sim_harness.hil.px4_param_server import ParamServer
from sim_harness.hil.px4_params import param_table, with_param

_MAX_WAIT_S = 0.02  # longest the thread sleeps: bounds how long stop() takes

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class CommandRecord:
    """One COMMAND_LONG / COMMAND_INT as received, with the result sent back."""

    t_s: float
    command: int
    params: tuple[float, ...]
    result: MavResult


class AutopilotEmulator:
    """PX4 over MAVLink/UDP for one vehicle. Use as a context manager, or start()/stop()."""

    def __init__(self, config: EmulatorConfig, backend: VehicleBackend | None = None) -> None:
        self.config = config
        if backend is None:
            backend = FirstOrderVehicle(
                pos_ned_m=(0.0, 0.0, -config.start_altitude_m), yaw_ned_rad=config.start_yaw_rad
            )
        self._backend = backend
        self._lock = threading.Lock()
        self._logic = Px4Logic(config.px4, config.start_mode, config.start_armed)
        self._params = ParamServer(param_table(config.px4), on_change=self._param_changed)
        self._state = backend.state()
        self._setpoints: deque[SetpointRecord] = deque(maxlen=config.log_capacity)
        self._commands: deque[CommandRecord] = deque(maxlen=config.log_capacity)
        self._link_alive = True
        self._heartbeat_alive = True
        self._failsafe_forced = False
        self._reported_mode: tuple[Px4Mode, Px4Mode] | None = None
        self._ignored_while_down = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._mav = mavlink.MAVLink(
            None, srcSystem=config.system_id, srcComponent=config.component_id
        )
        self._mav.robust_parsing = True
        self._t0_s = time.monotonic()
        self._client = (LOOPBACK, config.client_port)

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> AutopilotEmulator:
        """Bind the socket and start the thread. Returns self."""
        if self._thread is not None:
            raise SimError("autopilot emulator already started")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((LOOPBACK, 0))
        if sock.getsockname()[1] == self.config.client_port:  # the kernel reused the free port
            sock.close()
            return self.start()
        sock.setblocking(False)
        self._sock = sock
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="px4-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the thread (within about 20 ms) and close the socket. Idempotent."""
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None:
            thread.join(timeout_s)
            if thread.is_alive():
                logger.warning("autopilot emulator thread did not stop within %.1f s", timeout_s)
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> AutopilotEmulator:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def local_port(self) -> int:
        """The emulator's own UDP port (where the client's datagrams arrive)."""
        if self._sock is None:
            raise SimError("autopilot emulator not started")
        return int(self._sock.getsockname()[1])

    # -- observers (thread-safe) -------------------------------------------------------------

    @property
    def mode(self) -> Px4Mode:
        """The current flight mode."""
        with self._lock:
            return self._logic.mode

    @property
    def armed(self) -> bool:
        """Whether the motors are armed."""
        with self._lock:
            return self._logic.armed

    @property
    def landed_state(self) -> LandedState:
        """On the ground, in the air, taking off or landing."""
        with self._lock:
            return self._logic.landed_state(self._state)

    def vehicle_state(self) -> VehicleStateNed:
        """The latest vehicle state (NED, see `emulated_vehicle`)."""
        with self._lock:
            return self._state

    def setpoints(self) -> list[SetpointRecord]:
        """Every setpoint received (oldest first, at most `log_capacity`)."""
        with self._lock:
            return list(self._setpoints)

    def commands(self) -> list[CommandRecord]:
        """Every command received (oldest first), repeats included."""
        with self._lock:
            return list(self._commands)

    def mode_changes(self) -> list[ModeChange]:
        """Every flight-mode change (oldest first), with its reason."""
        with self._lock:
            return list(self._logic.mode_log)

    @property
    def ignored_while_down(self) -> int:
        """Datagrams received and dropped while the link was cut (`set_link_alive(False)`)."""
        with self._lock:
            return self._ignored_while_down

    # -- test hooks --------------------------------------------------------------------------

    def pilot_switch_mode(self, mode: Px4Mode) -> MavResult:
        """The RC pilot flips the mode switch (OFFBOARD still needs fresh setpoints)."""
        with self._lock:
            return self._logic.set_mode(self.now_s(), mode, "pilot switch")

    def set_failsafe(self, active: bool) -> None:
        """A failsafe other than offboard loss is active (True) or over (False)."""
        with self._lock:
            self._failsafe_forced = active

    def set_heartbeat_alive(self, alive: bool) -> None:
        """False: no HEARTBEAT is sent (telemetry, CURRENT_MODE and answers still are)."""
        with self._lock:
            self._heartbeat_alive = alive

    def set_link_alive(self, alive: bool) -> None:
        """False: stop sending and ignore everything received, as if the radio link were cut."""
        with self._lock:
            self._link_alive = alive

    # -- the thread --------------------------------------------------------------------------

    def now_s(self) -> float:
        """The emulator's clock (s): the time base of its setpoint, command and mode logs."""
        return time.monotonic() - self._t0_s

    @property
    def clock_origin_s(self) -> float:
        """`time.monotonic()` at this emulator's clock zero (to compare two emulators' logs)."""
        return self._t0_s

    def _run(self) -> None:
        sock = self._sock
        assert sock is not None
        cfg = self.config
        periods = {
            "physics": 1.0 / cfg.physics_rate_hz,
            "heartbeat": 1.0 / cfg.heartbeat_rate_hz,
            "telemetry": 1.0 / cfg.telemetry_rate_hz,
            "status": 1.0 / cfg.status_rate_hz,
        }
        now = self.now_s()
        due = dict.fromkeys(periods, now)
        last_physics = now
        try:
            while not self._stop.is_set():
                wait_s = min(_MAX_WAIT_S, max(0.0, min(due.values()) - self.now_s()))
                readable, _, _ = select.select([sock], [], [], wait_s)
                if readable:
                    self._receive(sock)
                now = self.now_s()
                self._report_mode_change()
                for name, period in periods.items():
                    if now < due[name]:
                        continue
                    # Fixed cadence; after a stall, restart from now instead of bursting.
                    due[name] = due[name] + period if now - due[name] < period else now + period
                    if name == "physics":
                        self._step_physics(now, now - last_physics)
                        last_physics = now
                    else:
                        self._send_stream(name, now)
        except OSError as exc:  # the socket was closed under us by stop()
            if not self._stop.is_set():
                logger.error("autopilot emulator stopped: %s", exc)

    def _receive(self, sock: socket.socket) -> None:
        while True:
            try:
                data, _addr = sock.recvfrom(65536)
            except BlockingIOError:
                return
            except ConnectionError:  # an ICMP error from an earlier send: nobody listened yet
                continue
            with self._lock:
                alive = self._link_alive
                if not alive:
                    self._ignored_while_down += 1
            if not alive:
                continue
            try:
                parsed = self._mav.parse_buffer(data) or []
            except mavlink.MAVError as exc:
                logger.debug("dropped a malformed datagram: %s", exc)
                continue
            for msg in parsed:
                try:
                    self._handle(msg)
                except Exception:  # one bad message must not take the emulator down
                    logger.exception("failed to handle %s", msg.get_type())

    def _modes(self) -> tuple[Px4Mode, Px4Mode]:
        """(mode flown, mode intended); call with the lock held."""
        logic = self._logic
        return logic.mode, Px4Mode.OFFBOARD if logic.offboard_intended else logic.mode

    def _report_mode_change(self) -> None:
        with self._lock:
            modes = self._modes()
        if modes != self._reported_mode:
            self._reported_mode = modes
            self._send(msgs.current_mode(self._mav, *modes))

    def _step_physics(self, now: float, dt_s: float) -> None:
        with self._lock:
            command = self._logic.update(now, self._state)
            self._state = self._backend.step(dt_s, command)

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        sock = self._sock
        if sock is None:
            return
        with self._lock:
            if not self._link_alive:
                return
        data = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        try:
            sock.sendto(data, self._client)
        except OSError as exc:  # e.g. ECONNREFUSED from an earlier send: nobody listens yet
            logger.debug("send failed: %s", exc)

    def _send_stream(self, name: str, now: float) -> None:
        mav = self._mav
        t_ms = int(now * 1000.0) & 0xFFFFFFFF
        with self._lock:
            state = self._state
            mode, armed = self._logic.mode, self._logic.armed
            in_air = self._logic.in_air(state)
            landed = self._logic.landed_state(state)
            modes = self._modes()
            failsafe = self._logic.offboard_intended or self._failsafe_forced
            heartbeat_alive = self._heartbeat_alive
        home = self.config.home
        if name == "heartbeat":
            out = [msgs.current_mode(mav, *modes)]
            if heartbeat_alive:
                out.append(msgs.heartbeat(mav, mode, armed, in_air, failsafe))
        elif name == "telemetry":
            out = [
                msgs.local_position(mav, t_ms, state),
                msgs.attitude_quaternion(mav, t_ms, state),
                msgs.attitude(mav, t_ms, state),
                msgs.global_position(mav, t_ms, state, home),
            ]
        else:
            out = [
                msgs.sys_status(mav),
                msgs.extended_sys_state(mav, landed),
                msgs.home_position(mav, home),
                msgs.gps_raw_int(mav, t_ms, state, home),
            ]
        for msg in out:
            self._send(msg)

    def _addressed_to_us(self, msg: mavlink.MAVLink_message) -> bool:
        system = getattr(msg, "target_system", 0)
        component = getattr(msg, "target_component", 0)
        return system in (0, self.config.system_id) and component in (0, self.config.component_id)

    def _handle(self, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        now = self.now_s()
        if kind == "SET_POSITION_TARGET_LOCAL_NED" and self._addressed_to_us(msg):
            with self._lock:
                record, command = msgs.decode_setpoint(now, msg, self._state.yaw_ned_rad)
                self._setpoints.append(record)
                if command is not None:
                    self._logic.on_setpoint(now, command)
        elif kind in ("COMMAND_LONG", "COMMAND_INT") and self._addressed_to_us(msg):
            self._handle_command(msg, now)
        elif kind.startswith("PARAM_") and self._addressed_to_us(msg):
            with self._lock:
                replies = self._params.handle(self._mav, msg)
            for reply in replies:
                self._send(reply)
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            self._send(self._mav.timesync_encode(time.monotonic_ns(), msg.ts1))

    def _param_changed(self, name: str, value: float) -> None:  # called with the lock held
        self._logic.config = with_param(self._logic.config, name, value)

    @property
    def px4_config(self) -> Px4LogicConfig:
        """PX4's rules in force (PARAM_SET of COM_OF_LOSS_T / COM_OBL_RC_ACT changes them)."""
        with self._lock:
            return self._logic.config

    def param_values(self) -> dict[str, float]:
        """The emulated parameter table (name -> value), as PARAM_SET left it."""
        with self._lock:
            return self._params.values()

    def _handle_command(self, msg: mavlink.MAVLink_message, now: float) -> None:
        command, params, home = int(msg.command), cmds.command_params(msg), self.config.home
        with self._lock:
            result = cmds.apply_command(self._logic, self._state, command, params, now, home)
            self._commands.append(CommandRecord(now, command, params, result))
        uid = 0x5058_3400_0000_0000 | (self.config.system_id << 8) | self.config.component_id
        after = cmds.follow_up(self._mav, command, params, result, home, uid)
        src_system, src_component = msg.get_srcSystem(), msg.get_srcComponent()
        self._send(
            self._mav.command_ack_encode(command, int(result), 0, 0, src_system, src_component)
        )
        if after is not None:
            self._send(after)
