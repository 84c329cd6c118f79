"""The PX4 emulator: its rules (pure, in simulated time) and its MAVLink face (raw pymavlink)."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.errors import ConfigError
from companion.frames import euler_zyx_from_quat, quat_to_rotmat
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.emulated_vehicle import (
    FirstOrderVehicle,
    VelocityCommand,
    attitude_from_thrust,
)
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
from sim_harness.hil.px4_logic import LandedState, MavResult, Px4Logic, Px4LogicConfig, Px4Mode

FAST = {"heartbeat_rate_hz": 20.0, "status_rate_hz": 10.0}
GUARD_S = 10.0  # liveness bound for waits that end as soon as their message or state arrives


class RawClient:
    """Stands where MAVSDK stands: listens on the client port, answers to the emulator's port."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.05)
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=196)
        self.mav.robust_parsing = True
        self.emulator_addr: tuple[str, int] | None = None

    def close(self) -> None:
        self.sock.close()

    def send(self, msg: mavlink.MAVLink_message) -> None:
        assert self.emulator_addr is not None, "receive something first"
        self.sock.sendto(msg.pack(self.mav), self.emulator_addr)
        self.mav.seq = (self.mav.seq + 1) % 256

    def receive(
        self, match: Callable[[mavlink.MAVLink_message], bool], timeout_s: float = GUARD_S
    ) -> mavlink.MAVLink_message | None:
        """The first received message that matches, or None after `timeout_s` (a hang guard)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                data, addr = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            self.emulator_addr = addr
            for msg in self.mav.parse_buffer(data) or []:
                if match(msg):
                    return msg
        return None

    def of_type(self, kind: str, timeout_s: float = GUARD_S) -> mavlink.MAVLink_message:
        msg = self.receive(lambda m: m.get_type() == kind, timeout_s)
        assert msg is not None, f"no {kind} within {timeout_s} s"
        return msg

    def command(self, command: int, *params: float) -> MavResult:
        padded = [*params, *([0.0] * (7 - len(params)))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *padded))
        ack = self.receive(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command)
        assert ack is not None, f"no ACK for command {command}"
        return MavResult(ack.result)

    def velocity_setpoint(self, frame: int, vel: tuple[float, float, float], yaw: float) -> None:
        mask = 0b0000_1001_1100_0111  # position, acceleration and yaw rate ignored (as MAVSDK)
        self.send(
            self.mav.set_position_target_local_ned_encode(
                0, 1, 1, frame, mask, 0, 0, 0, *vel, 0, 0, 0, yaw, 0
            )
        )


@pytest.fixture
def wire() -> Iterator[Callable[..., tuple[AutopilotEmulator, RawClient]]]:
    made: list[tuple[AutopilotEmulator, RawClient]] = []

    def make(**overrides: object) -> tuple[AutopilotEmulator, RawClient]:
        port = free_udp_port()
        client = RawClient(port)
        hovering = overrides.pop("hovering", False)
        kwargs = {**FAST, **overrides}
        config = (
            EmulatorConfig.hovering(port, **kwargs) if hovering else EmulatorConfig(port, **kwargs)
        )
        emulator = AutopilotEmulator(config).start()
        made.append((emulator, client))
        client.of_type("HEARTBEAT")
        return emulator, client

    yield make
    for emulator, client in made:
        emulator.stop()
        client.close()


def wait_for(condition: Callable[[], bool], timeout_s: float = GUARD_S) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


# -- PX4 modes and rules, in simulated time -------------------------------------------------


def test_px4_custom_mode_encoding_matches_px4() -> None:
    assert Px4Mode.OFFBOARD.custom_mode == 6 << 16
    assert Px4Mode.HOLD.custom_mode == (4 << 16) | (3 << 24)
    assert Px4Mode.POSCTL.custom_mode == 3 << 16
    for mode in Px4Mode:
        assert Px4Mode.from_custom_mode(mode.custom_mode) is mode
    assert Px4Mode.from_main_sub(4, 0) is None
    assert Px4Mode.from_main_sub(9, 0) is None


def test_offboard_needs_fresh_setpoints_and_falls_back_to_hold() -> None:
    vehicle = FirstOrderVehicle(pos_ned_m=(0, 0, -5))
    hold = Px4LogicConfig(offboard_loss_mode=Px4Mode.HOLD)  # COM_OBL_RC_ACT 5, our file
    logic = Px4Logic(hold, Px4Mode.POSCTL, armed=True)
    assert logic.set_mode(0.0, Px4Mode.OFFBOARD, "test") is MavResult.DENIED
    logic.on_setpoint(1.0, VelocityCommand(np.array([1.0, 0.0, 0.0])))
    assert logic.set_mode(1.6, Px4Mode.OFFBOARD, "test") is MavResult.DENIED  # 0.6 s old
    assert logic.set_mode(1.4, Px4Mode.OFFBOARD, "test") is MavResult.ACCEPTED
    command = logic.update(1.45, vehicle.state())
    assert command is not None
    np.testing.assert_allclose(command.vel_ned_mps, [1.0, 0.0, 0.0])
    command = logic.update(1.6, vehicle.state())  # 0.6 s without a setpoint
    assert logic.mode is Px4Mode.HOLD
    assert command is not None
    np.testing.assert_allclose(command.vel_ned_mps, 0.0)
    assert logic.mode_log[-1].reason == "offboard setpoints lost"


def test_stock_offboard_loss_is_position_mode_and_setpoints_resume_offboard() -> None:
    """PX4's defaults (COM_OBL_RC_ACT 0), and what PX4 SITL showed: after the loss failsafe,
    OFFBOARD stays the intended mode; setpoints coming back resume it with no request. A mode
    change cancels that; so does the resume itself (a second loss needs a new failsafe)."""
    state = FirstOrderVehicle(pos_ned_m=(0, 0, -5)).state()
    logic = Px4Logic(Px4LogicConfig(), Px4Mode.POSCTL, armed=True)
    forward = VelocityCommand(np.array([1.0, 0.0, 0.0]))
    logic.on_setpoint(0.0, forward)
    assert logic.set_mode(0.1, Px4Mode.OFFBOARD, "test") is MavResult.ACCEPTED
    logic.update(0.6, state)  # 0.6 s without a setpoint: COM_OF_LOSS_T is 0.5 s here
    assert logic.mode is Px4Mode.POSCTL and logic.offboard_intended
    logic.update(5.0, state)
    assert logic.mode is Px4Mode.POSCTL  # no setpoint: stays in the failsafe
    logic.on_setpoint(9.0, forward)  # e.g. a restarted companion's first setpoint
    command = logic.update(9.02, state)
    assert logic.mode is Px4Mode.OFFBOARD and logic.mode_log[-1].reason == (
        "offboard setpoints regained"
    )
    assert command is not None and command.vel_ned_mps[0] == 1.0
    logic.update(9.6, state)  # lost again
    assert logic.mode is Px4Mode.POSCTL
    assert logic.set_mode(9.7, Px4Mode.HOLD, "pilot") is MavResult.ACCEPTED
    logic.on_setpoint(10.0, forward)
    logic.update(10.02, state)
    assert logic.mode is Px4Mode.HOLD and not logic.offboard_intended  # the pilot's choice holds


def test_disarm_is_refused_in_the_air_unless_forced() -> None:
    flying = FirstOrderVehicle(pos_ned_m=(0, 0, -3)).state()
    logic = Px4Logic(Px4LogicConfig(), Px4Mode.POSCTL, armed=True)
    assert logic.arm(0.0, False, False, flying) is MavResult.DENIED
    assert logic.armed
    assert logic.arm(0.0, True, False, flying) is MavResult.ACCEPTED  # a repeat: same answer
    assert logic.arm(0.0, False, True, flying) is MavResult.ACCEPTED
    assert not logic.armed


def fly(logic: Px4Logic, vehicle: FirstOrderVehicle, t_s: float, seconds: float) -> float:
    dt = 0.02
    for _ in range(round(seconds / dt)):
        t_s += dt
        vehicle.step(dt, logic.update(t_s, vehicle.state()))
    return t_s


def test_takeoff_climbs_then_holds_and_land_disarms_on_touchdown() -> None:
    vehicle = FirstOrderVehicle()
    logic = Px4Logic(Px4LogicConfig(takeoff_altitude_m=2.0), Px4Mode.HOLD, armed=False)
    assert logic.takeoff(0.0, None) is MavResult.DENIED  # disarmed
    assert logic.land(0.0) is MavResult.DENIED
    logic.arm(0.0, True, False, vehicle.state())
    assert logic.takeoff(0.0, None) is MavResult.ACCEPTED
    assert logic.landed_state(vehicle.state()) is LandedState.TAKEOFF
    t = fly(logic, vehicle, 0.0, 4.0)
    assert logic.mode is Px4Mode.HOLD
    assert vehicle.state().altitude_m == pytest.approx(2.0, abs=0.3)
    assert logic.landed_state(vehicle.state()) is LandedState.IN_AIR
    assert logic.land(t) is MavResult.ACCEPTED
    t = fly(logic, vehicle, t, 1.0)
    assert logic.landed_state(vehicle.state()) is LandedState.LANDING
    fly(logic, vehicle, t, 5.0)
    assert vehicle.state().altitude_m == 0.0
    assert not logic.armed


# -- the kinematic model --------------------------------------------------------------------


def test_first_order_vehicle_follows_velocity_and_slews_yaw() -> None:
    vehicle = FirstOrderVehicle(pos_ned_m=(0, 0, -5))
    command = VelocityCommand(np.array([1.0, 0.5, -0.2]), yaw_ned_rad=math.pi / 2)
    state = vehicle.step(0.02, command)
    roll, pitch, _ = euler_zyx_from_quat(state.q_ned_frd_wxyz)
    assert float(pitch) < 0.0  # nose down to accelerate (FRD: pitch up is positive)
    max_turn = vehicle.params.yaw_rate_max_rad_s * 0.02
    assert state.yaw_ned_rad == pytest.approx(max_turn)  # rate-limited slew
    for _ in range(150):  # 3 s = 10 time constants
        state = vehicle.step(0.02, command)
    np.testing.assert_allclose(state.vel_ned_mps, [1.0, 0.5, -0.2], atol=1e-3)
    assert state.yaw_ned_rad == pytest.approx(math.pi / 2, abs=1e-3)
    roll, pitch, _ = euler_zyx_from_quat(state.q_ned_frd_wxyz)
    assert abs(float(roll)) < 1e-3 and abs(float(pitch)) < 1e-3  # cruising: level


def test_attitude_tilts_body_z_and_keeps_the_euler_yaw() -> None:
    rng = np.random.default_rng(7)
    for _ in range(50):
        body_z = rng.normal(size=3)
        body_z[2] = abs(body_z[2]) + 0.3  # thrust with an upward component
        yaw = float(rng.uniform(-math.pi, math.pi))
        q = attitude_from_thrust(body_z, yaw)
        np.testing.assert_allclose(quat_to_rotmat(q)[:, 2], body_z / np.linalg.norm(body_z))
        assert float(euler_zyx_from_quat(q)[2]) == pytest.approx(yaw)


def test_vehicle_never_goes_below_the_ground() -> None:
    vehicle = FirstOrderVehicle(pos_ned_m=(0, 0, -0.5))
    down = VelocityCommand(np.array([0.0, 0.0, 2.0]))
    for _ in range(100):
        state = vehicle.step(0.02, down)
        assert state.pos_ned_m[2] <= 0.0
    assert state.vel_ned_mps[2] == 0.0
    assert vehicle.step(0.02, None).pos_ned_m[2] == 0.0  # motors off on the ground


def test_config_refuses_hovering_disarmed_and_bad_ports() -> None:
    with pytest.raises(ConfigError, match="start_armed"):
        EmulatorConfig(14540, start_altitude_m=5.0)
    with pytest.raises(ConfigError, match="client_port"):
        EmulatorConfig(70000)


# -- over the wire ----------------------------------------------------------------------------


def test_heartbeat_and_telemetry_look_like_px4_on_the_ground(wire) -> None:
    _, client = wire()
    hb = client.of_type("HEARTBEAT")
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert Px4Mode.from_custom_mode(hb.custom_mode) is Px4Mode.HOLD
    status = client.of_type("SYS_STATUS")
    needed = mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_PREARM_CHECK
    assert status.onboard_control_sensors_health & needed == needed
    assert client.of_type("EXTENDED_SYS_STATE").landed_state == LandedState.ON_GROUND
    for kind in ("LOCAL_POSITION_NED", "ATTITUDE_QUATERNION", "ATTITUDE", "HOME_POSITION"):
        client.of_type(kind)
    glob = client.of_type("GLOBAL_POSITION_INT")
    assert glob.lat == round(47.397742e7) and glob.relative_alt == 0


def test_hovering_start_reports_armed_in_air(wire) -> None:
    _, client = wire(hovering=True, altitude_m=5.0)
    hb = client.of_type("HEARTBEAT")
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert Px4Mode.from_custom_mode(hb.custom_mode) is Px4Mode.POSCTL
    assert client.of_type("LOCAL_POSITION_NED").z == pytest.approx(-5.0)
    assert client.of_type("EXTENDED_SYS_STATE").landed_state == LandedState.IN_AIR
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0.0) is MavResult.DENIED


def test_requested_messages_follow_their_ack(wire) -> None:
    _, client = wire()
    request = mavlink.MAV_CMD_REQUEST_MESSAGE
    assert client.command(request, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) is MavResult.ACCEPTED
    version = client.of_type("AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert client.command(request, mavlink.MAVLINK_MSG_ID_HOME_POSITION) is MavResult.ACCEPTED
    assert client.command(request, 99999) is MavResult.UNSUPPORTED
    assert client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 245, 1e6) is MavResult.ACCEPTED
    assert client.command(mavlink.MAV_CMD_DO_REPOSITION) is MavResult.UNSUPPORTED


def test_offboard_over_the_wire_refused_then_accepted_then_lost(wire) -> None:
    emulator, client = wire(hovering=True, px4=Px4LogicConfig(offboard_loss_mode=Px4Mode.HOLD))
    set_mode = mavlink.MAV_CMD_DO_SET_MODE
    flag = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    loss_timeout_s = emulator.config.px4.offboard_loss_timeout_s  # COM_OF_LOSS_T, 0.5 s
    assert client.command(set_mode, flag, 6, 0) is MavResult.DENIED  # no setpoint yet
    # Each request follows a fresh setpoint, as from MAVSDK's stream, so that a loaded machine
    # that delays the test between the two requests cannot let the first one's setpoint expire.
    client.velocity_setpoint(mavlink.MAV_FRAME_LOCAL_NED, (1.0, 0.5, -0.2), math.pi / 2)
    assert client.command(set_mode, flag, 6, 0) is MavResult.ACCEPTED
    client.velocity_setpoint(mavlink.MAV_FRAME_LOCAL_NED, (1.0, 0.5, -0.2), math.pi / 2)
    assert client.command(set_mode, flag, 6, 0) is MavResult.ACCEPTED  # a retry
    record = emulator.setpoints()[-1]
    assert (record.frame, record.type_mask) == (mavlink.MAV_FRAME_LOCAL_NED, 0b1001_1100_0111)
    assert (record.vx_mps, record.vy_mps) == (1.0, 0.5)
    assert record.vz_mps == pytest.approx(-0.2) and record.yaw_rad == pytest.approx(math.pi / 2)
    assert record.uses_velocity and record.uses_yaw and not record.uses_yaw_rate
    # No further setpoints: PX4 falls back to HOLD once the last one is loss_timeout_s old.
    assert wait_for(lambda: emulator.mode is Px4Mode.HOLD)
    entered, lost = emulator.mode_changes()[-2:]  # judged on the emulator's own timestamps
    assert (entered.old, entered.new) == (Px4Mode.POSCTL, Px4Mode.OFFBOARD)
    assert (lost.old, lost.new, lost.reason) == (
        Px4Mode.OFFBOARD,
        Px4Mode.HOLD,
        "offboard setpoints lost",
    )
    # Never early; late by at most a physics step (20 ms), plus 1 s of margin for a thread
    # that a loaded machine did not schedule.
    assert loss_timeout_s < lost.t_s - record.t_s < loss_timeout_s + 1.0
    hb = client.receive(
        lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == Px4Mode.HOLD.custom_mode
    )
    assert hb is not None
    assert [c.result for c in emulator.commands()] == [
        MavResult.DENIED,
        MavResult.ACCEPTED,
        MavResult.ACCEPTED,
    ]


def test_body_frame_velocity_is_rotated_by_the_heading(wire) -> None:
    # Facing east. This test is about the frame, not the loss timeout: a generous one, so that a
    # loaded machine pausing the test's 20 Hz stream cannot drop the vehicle to HOLD.
    patient = Px4LogicConfig(offboard_loss_timeout_s=5.0)
    emulator, client = wire(hovering=True, start_yaw_rad=math.pi / 2, px4=patient)
    flag = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    client.velocity_setpoint(mavlink.MAV_FRAME_BODY_NED, (1.0, 0.0, 0.0), math.pi / 2)
    assert client.command(mavlink.MAV_CMD_DO_SET_MODE, flag, 6, 0) is MavResult.ACCEPTED
    for _ in range(25):  # stream at 20 Hz for 1.25 s (4 time constants)
        client.velocity_setpoint(mavlink.MAV_FRAME_BODY_NED, (1.0, 0.0, 0.0), math.pi / 2)
        client.receive(lambda m: False, timeout_s=0.05)
    assert emulator.mode is Px4Mode.OFFBOARD
    state = emulator.vehicle_state()
    assert state.vel_ned_mps[1] > 0.9  # forward = east
    assert abs(state.vel_ned_mps[0]) < 0.05
    assert state.pos_ned_m[1] > 0.6


def test_pilot_switch_and_lost_link(wire) -> None:
    emulator, client = wire(hovering=True)
    assert emulator.pilot_switch_mode(Px4Mode.OFFBOARD) is MavResult.DENIED  # no setpoints
    assert emulator.pilot_switch_mode(Px4Mode.ALTCTL) is MavResult.ACCEPTED
    assert Px4Mode.from_custom_mode(client.of_type("HEARTBEAT").custom_mode) is not None
    emulator.set_link_alive(False)
    client.receive(lambda m: False, timeout_s=0.25)  # let what was in flight drain
    assert client.receive(lambda m: True, timeout_s=0.3) is None  # silence
    ignored = emulator.ignored_while_down
    client.velocity_setpoint(mavlink.MAV_FRAME_LOCAL_NED, (1.0, 0.0, 0.0), 0.0)
    # The emulator reads (and drops) it while the link is still down: wait until it did.
    assert wait_for(lambda: emulator.ignored_while_down > ignored)
    emulator.set_link_alive(True)
    assert client.of_type("HEARTBEAT").custom_mode == Px4Mode.ALTCTL.custom_mode
    assert emulator.setpoints() == []  # what arrived while the link was down was dropped


def test_stop_is_prompt_and_idempotent() -> None:
    emulator = AutopilotEmulator(EmulatorConfig(free_udp_port())).start()
    port = emulator.local_port
    emulator.stop()
    emulator.stop()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", port))  # the emulator's port was released


def test_parameters_read_list_set_and_unknown_names(wire) -> None:
    """PX4's parameter protocol: the table (stock PX4 defaults), PARAM_ERROR for an unknown name,
    and COM_OBL_RC_ACT / COM_OF_LOSS_T set over the wire change the offboard-loss rule."""
    emulator, client = wire(hovering=True)
    client.send(client.mav.param_request_list_encode(1, 1))
    first = client.of_type("PARAM_VALUE")
    names = {first.param_id}
    while len(names) < first.param_count:
        names.add(client.of_type("PARAM_VALUE").param_id)
    assert {"COM_OBL_RC_ACT", "COM_OF_LOSS_T", "MAV_1_CONFIG", "SER_TEL2_BAUD"} <= names
    client.send(client.mav.param_request_read_encode(1, 1, b"COM_OF_LOS_T", -1))
    error = client.of_type("PARAM_ERROR")
    assert (error.param_id, error.error) == ("COM_OF_LOS_T", mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
    five = np.frombuffer(np.int32(5).tobytes(), dtype=np.float32)[0]  # INT32 travels bytewise
    client.send(client.mav.param_set_encode(1, 1, b"COM_OBL_RC_ACT", five, 6))
    echo = client.receive(
        lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OBL_RC_ACT"
    )
    assert echo is not None and echo.param_value == five and echo.param_type == 6
    client.send(client.mav.param_set_encode(1, 1, b"COM_OF_LOSS_T", 2.0, 9))
    client.receive(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "COM_OF_LOSS_T")
    assert emulator.param_values()["COM_OBL_RC_ACT"] == 5
    assert wait_for(
        lambda: emulator.config.px4 is not None and _loss_rule(emulator) == (2.0, "HOLD")
    )


def _loss_rule(emulator: AutopilotEmulator) -> tuple[float, str]:
    config = emulator._logic.config
    return config.offboard_loss_timeout_s, config.offboard_loss_mode.name
