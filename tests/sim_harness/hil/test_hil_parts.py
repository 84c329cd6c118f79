"""The HIL harness's parts, each with real pieces: pushed pty cameras, the shared-memory pose
board, the world vehicle's frames, the per-drone daemon config, fault plans."""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
import serial

from companion.camera.layout import FACE_NAMES
from companion.camera.protocol import FrameMessage, FrameParser
from companion.config import config_from_dict
from companion.errors import ConfigError
from companion.frames import quat_from_yaw
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.camera_side import PoseBoard
from sim_harness.hil.drone import SHIPPED_CONFIG, DroneSetup, HilDrone, toml_text
from sim_harness.hil.emulated_vehicle import VelocityCommand
from sim_harness.hil.faults import KINDS, load_plan, parse_plan
from sim_harness.hil.plans import PLANS_DIR
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.px4_params import SHIPPED_PARAMS, logic_config, read_params
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN, WorldVehicle, home_of, states_ned

TIMEOUT_S = 10.0


def test_pushed_frames_carry_their_capture_time_and_leave_at_their_send_time(
    tmp_path: Path,
) -> None:
    with CameraEmulator(tmp_path, source=None, hello_period_s=600, status_period_s=600) as cams:
        tiles = np.stack([np.full((64, 64), 10 * (k + 1), np.uint8) for k in range(6)])
        parser = FrameParser()
        with serial.Serial(str(cams.device_path("left")), 115200, timeout=0.02) as port:
            deadline = time.monotonic() + TIMEOUT_S
            while not cams.stats("left").host_connected:
                assert time.monotonic() < deadline
                parser.feed(port.read(4096))
            captured = time.monotonic()
            send_at = captured + np.linspace(0.05, 0.30, 6)  # left (index 3) at +0.20 s
            cams.push(tiles, captured, send_at)
            got: list[FrameMessage] = []
            while not got:
                assert time.monotonic() < deadline
                got = [m for m in parser.feed(port.read(8192)) if isinstance(m, FrameMessage)]
            arrived = time.monotonic()
        frame = got[0]
        assert np.array_equal(frame.image, tiles[FACE_NAMES.index("left")])
        # Not before its send time; stamped with the capture instant on the camera's own clock.
        assert arrived >= send_at[FACE_NAMES.index("left")]
        boot = cams.boot_time_s("left")
        assert frame.timestamp_us == pytest.approx((captured - boot) * 1e6, abs=2)


def test_a_frame_replaced_before_it_left_is_counted_as_dropped(tmp_path: Path) -> None:
    with CameraEmulator(tmp_path, source=None) as cams:
        tiles = np.zeros((6, 64, 64), np.uint8)
        later = time.monotonic() + 60.0
        cams.push(tiles, time.monotonic(), np.full(6, later))
        cams.push(tiles, time.monotonic(), np.full(6, later))
        assert all(cams.stats(face).frames_dropped == 1 for face in FACE_NAMES)
        with pytest.raises(Exception, match="expected uint8"):
            cams.push(np.zeros((6, 64, 64), np.float32), 0.0, np.zeros(6))  # type: ignore[arg-type]


def test_pose_board_round_trip_between_two_handles() -> None:
    writer = PoseBoard(3)
    try:
        reader = PoseBoard(3, writer.name)
        pos = np.arange(9.0).reshape(3, 3)
        q = quat_from_yaw(np.array([0.0, 1.0, 2.0]))
        writer.write(pos, q)
        got_pos, got_q = reader.read()
        assert np.array_equal(got_pos, pos) and np.array_equal(got_q, q)
        reader.close()
    finally:
        writer.close()


def test_world_vehicle_speaks_its_own_px4_frames() -> None:
    """A drone 3 m east and 4 m north of the world origin, 5 m up, with its home under it:
    local NED is (0, 0, -5); flying east in the world is +y (east) in NED; facing north in ENU
    (yaw pi/2) is yaw 0 in NED."""
    home = np.array([3.0, 4.0, 0.0])
    pos = np.array([[3.0, 4.0, 5.0]])
    vel = np.array([[1.5, 0.0, 0.0]])
    q = quat_from_yaw(np.array([math.pi / 2]))
    (state,) = states_ned(pos, vel, q, home[None, :])
    assert np.allclose(state.pos_ned_m, [0.0, 0.0, -5.0])
    assert np.allclose(state.vel_ned_mps, [0.0, 1.5, 0.0])
    assert state.yaw_ned_rad == pytest.approx(0.0, abs=1e-9)
    vehicle = WorldVehicle(home, state)
    vehicle.step(0.02, VelocityCommand(vel_ned_mps=np.array([1.0, 2.0, -0.5])))
    assert np.allclose(vehicle.velocity_setpoint_enu(), [2.0, 1.0, 0.5])  # ENU of NED (1, 2, -0.5)
    assert math.isnan(vehicle.yaw_setpoint_enu())  # no yaw in the setpoint: the vehicle's own rule
    vehicle.step(0.02, VelocityCommand(vel_ned_mps=np.zeros(3), yaw_ned_rad=0.0))
    assert vehicle.yaw_setpoint_enu() == pytest.approx(math.pi / 2)  # facing north
    vehicle.step(0.02, None)  # disarmed: it falls
    assert vehicle.velocity_setpoint_enu()[2] < 0.0
    vehicle.step(0.02, VelocityCommand(vel_ned_mps=np.array([math.nan, 0.0, 0.0])))
    assert np.array_equal(vehicle.velocity_setpoint_enu(), np.zeros(3))
    # Each drone's home is where it stands: 111 km per degree of latitude, north is +lat.
    north = home_of(DEFAULT_ORIGIN, np.array([0.0, 1000.0, 0.0]))
    assert (north.lat_deg - DEFAULT_ORIGIN.lat_deg) * 111_000 == pytest.approx(1000.0, rel=0.01)


def test_each_drone_gets_the_shipped_config_with_its_own_wiring(tmp_path: Path) -> None:
    class Cameras:
        def faces_config(self) -> dict[str, dict[str, str]]:
            return {f: {"device": f"/tmp/x-{f}", "camera_id": f"{k:024x}"}
                    for k, f in enumerate(FACE_NAMES)}  # fmt: skip

    home = np.array([10.0, -2.0, 0.0])
    goal_local = np.array([20.0, 2.0, 5.0])
    setup = DroneSetup(2, home, goal_local, tmp_path / "drone3")
    state = states_ned(np.array([[10.0, -2.0, 5.0]]), np.zeros((1, 3)),
                       quat_from_yaw(np.zeros(1)), home[None])[0]  # fmt: skip
    model = tmp_path / "policy.pt"
    drone = HilDrone(setup, WorldVehicle(home, state), Cameras(), DEFAULT_ORIGIN, model)  # type: ignore[arg-type]
    try:
        doc = tomllib.loads(toml_text(drone.config_document()))
        shipped = tomllib.loads(SHIPPED_CONFIG.read_text())
        config = config_from_dict(doc)  # the daemon's own validation accepts it
        assert config.drone.id == "drone3"
        assert drone.px4.config.system_id == 3
        assert config.control.migration_point_enu == pytest.approx(tuple(goal_local))
        assert doc["autopilot"]["url"] == f"udpin://127.0.0.1:{drone.px4.config.client_port}"
        assert all(e.startswith("tcp/127.0.0.1:") for e in doc["telemetry"]["listen_endpoints"])
        assert doc["telemetry"]["multicast_scouting"] is False
        # Everything an operator did not have to change per drone is the shipped file's.
        low_pass = shipped["control"].get("low_pass_cutoff_hz")  # unset in the shipped file: off
        assert doc["control"].get("low_pass_cutoff_hz") == low_pass
        assert doc["daemon"]["failsafe_after_s"] == shipped["daemon"]["failsafe_after_s"]
    finally:
        drone.px4.stop()


def test_fault_plans_validate_and_name_the_field(tmp_path: Path) -> None:
    for path in sorted(PLANS_DIR.glob("*.toml")):  # the shipped examples load for three drones
        assert load_plan(path, 3).events
    plan = parse_plan({"event": [{"at_s": 2, "drone": 1, "kind": "camera_stall",
                                  "duration_s": 1}]}, 3)  # fmt: skip
    assert plan.end_s > 3.0 and plan.events[0].face == "front"
    bad = [
        ({"at_s": 1, "drone": 4, "kind": "daemon_sigkill"}, r"event\[0\]\.drone: 4 is outside"),
        ({"at_s": 1, "drone": 1, "kind": "explode"}, r"event\[0\]\.kind"),
        ({"at_s": 1, "drone": 1, "kind": "camera_unplug"}, r"event\[0\]\.duration_s"),
        ({"at_s": 1, "drone": 1, "kind": "camera_stall", "face": "top", "duration_s": 1},
         r"event\[0\]\.face"),
        ({"at_s": "soon", "drone": 1, "kind": "pilot_mode"}, r"event\[0\]\.at_s: expected float"),
        ({"at_s": 1, "drone": 1, "kind": "pilot_mode", "dur": 2}, r"unknown field"),
    ]  # fmt: skip
    for event, message in bad:
        with pytest.raises(ConfigError, match=message):
            parse_plan({"event": [event]}, 3)
    with pytest.raises(ConfigError, match="at least one"):
        parse_plan({}, 3)
    twice = {"at_s": 1, "drone": 2, "kind": "daemon_sigterm"}
    with pytest.raises(ConfigError, match="only once"):
        parse_plan({"event": [twice, {**twice, "kind": "daemon_sigkill"}]}, 3)
    broken = tmp_path / "broken.toml"
    broken.write_text("[[event]\n")
    with pytest.raises(ConfigError, match="cannot read"):
        load_plan(broken, 3)
    assert len(KINDS) == 8


def test_emulated_px4_takes_the_offboard_loss_rule_from_the_shipped_parameter_file(
    tmp_path: Path,
) -> None:
    config = logic_config()
    assert config.offboard_loss_timeout_s == read_params(SHIPPED_PARAMS)["COM_OF_LOSS_T"] == 1.0
    assert config.offboard_loss_mode is Px4Mode.HOLD  # COM_OBL_RC_ACT 5
    land = tmp_path / "land.params"
    land.write_text("# comment\n1\t1\tCOM_OF_LOSS_T\t0.7\t9\n1\t1\tCOM_OBL_RC_ACT\t4\t6\n")
    assert (logic_config(land).offboard_loss_timeout_s, logic_config(land).offboard_loss_mode) == (
        0.7,
        Px4Mode.LAND,
    )
    land.write_text("1\t1\tCOM_OF_LOSS_T\tsoon\t9\n")
    with pytest.raises(ConfigError, match=r"land.params:1: COM_OF_LOSS_T"):
        logic_config(land)
