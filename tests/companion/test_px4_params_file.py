"""The shipped PX4 parameter file (what it sets and why) and `companion params file`: one file per
drone, since QGroundControl refuses a file whose vehicle id column is not the drone's MAV_SYS_ID."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from companion.cli import main
from companion.param_check import read_params_file, stated_version
from companion.px4_params_file import CHECKOUT_TEMPLATE, parse_id_list, render_file

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "firmware_cfg" / "px4" / "companion.params"
CONFIG = tomllib.loads((ROOT / "systemd" / "companion.toml").read_text())
VALUES = {row.name: row.value for row in read_params_file(SHIPPED)}
ORDER = [row.name for row in read_params_file(SHIPPED)]


def test_px4_flies_what_the_daemon_asks_in_every_axis_group() -> None:
    """Issue 19 finding 4: MPC_Z_VEL_MAX_UP 1.0 clipped a -1.21 m/s NED climb to -1.00. The
    daemon caps the 3-D speed, so each of PX4's per-axis caps must be at least that cap."""
    v_max_mps = CONFIG["control"]["v_max_mps"]
    for name in ("MPC_XY_VEL_MAX", "MPC_Z_VEL_MAX_UP", "MPC_Z_VEL_MAX_DN"):
        assert VALUES[name] >= v_max_mps, name
    # PX4 clamps (critical message) a stock MPC_Z_V_AUTO_UP (3 m/s) above MPC_Z_VEL_MAX_UP.
    assert VALUES["MPC_Z_VEL_MAX_UP"] >= 3.0


def test_cruise_and_manual_speeds_fit_under_the_maximum_before_it_is_set() -> None:
    """PX4 clamps MPC_XY_CRUISE / MPC_VEL_MANUAL above MPC_XY_VEL_MAX with a critical message,
    on every parameter change: the file lowers them first, to at most the new maximum."""
    for name in ("MPC_XY_CRUISE", "MPC_VEL_MANUAL"):
        assert VALUES[name] <= VALUES["MPC_XY_VEL_MAX"], name
        assert ORDER.index(name) < ORDER.index("MPC_XY_VEL_MAX"), name


def test_the_pilot_takes_over_and_rc_loss_returns_above_the_swarm_inside_the_fence() -> None:
    ceiling_m = CONFIG["control"]["altitude_ceiling_m"]
    assert int(VALUES["COM_RC_OVERRIDE"]) & 0b10  # sticks take over in OFFBOARD
    assert VALUES["NAV_RCL_ACT"] == 2  # RC loss: Return
    assert ceiling_m < VALUES["RTL_RETURN_ALT"] < VALUES["GF_MAX_VER_DIST"]
    assert VALUES["RTL_CONE_ANG"] == 0  # always climb to RTL_RETURN_ALT first
    assert VALUES["COM_ARM_WO_GPS"] == 0  # no arming without GNSS


def test_every_value_says_why_and_the_file_states_its_px4_version() -> None:
    text = SHIPPED.read_text()
    comments = "\n".join(line for line in text.splitlines() if line.startswith("#"))
    assert [name for name in VALUES if name not in comments] == []
    assert stated_version(text) == (1, 17)
    assert CHECKOUT_TEMPLATE == SHIPPED


def test_a_drones_file_differs_from_the_template_only_in_its_vehicle_id() -> None:
    text = render_file(SHIPPED, 7)
    lines = text.splitlines()
    assert lines[0].startswith("# Drone with MAV_SYS_ID 7: rendered from companion.params")
    template = SHIPPED.read_text().splitlines()
    assert len(lines) == len(template) + 1
    for rendered, original in zip(lines[1:], template, strict=True):
        if original.startswith("#"):
            assert rendered == original
        else:
            assert rendered.split("\t") == ["7", *original.split("\t")[1:]]
    assert stated_version(text) == (1, 17)


def test_params_file_cli_to_stdout_and_to_a_folder(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["params", "file", "--sysid", "3"]) == 0
    out = capsys.readouterr().out
    mine = tmp_path / "mine.params"
    mine.write_text(out)
    assert {row.vehicle_id for row in read_params_file(mine)} == {3}
    assert main(["params", "file", "--drones", "1-3,9", "--out", str(tmp_path / "all")]) == 0
    written = capsys.readouterr().out.split()
    assert [Path(p).name for p in written] == [f"drone{i}.params" for i in (1, 2, 3, 9)]
    for i in (1, 2, 3, 9):
        rows = read_params_file(tmp_path / "all" / f"drone{i}.params")
        assert {row.vehicle_id for row in rows} == {i}
        assert {row.name: row.value for row in rows} == VALUES


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--sysid", "0"], "--sysid 0: must be 1..250 (MAV_SYS_ID)"),
        (["--sysid", "251"], "--sysid 251: must be 1..250 (MAV_SYS_ID)"),
        (["--drones", "1-300", "--out", "x"], "--drones 300: must be 1..250 (MAV_SYS_ID)"),
        (["--drones", "5-2", "--out", "x"], "--drones '5-2': range 5-2 must go up"),
        (["--drones", "1-a", "--out", "x"], "--drones '1-a': expected ids and ranges"),
        (["--drones", "1-3"], "--drones needs --out DIR"),
        (["--sysid", "2", "--template", "/nonexistent"], "--template /nonexistent: no such"),
    ],
)
def test_params_file_bad_input_is_one_line_naming_the_field(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["params", "file", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"companion: error: {message}") and err.count("\n") == 1, err


def test_id_lists() -> None:
    assert parse_id_list("1-3") == [1, 2, 3]
    assert parse_id_list("4, 2,2-3") == [2, 3, 4]
    assert parse_id_list("250") == [250]
