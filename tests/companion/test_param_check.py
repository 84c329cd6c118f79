"""`companion check --autopilot`: the parameter file against a live autopilot, here the pymavlink
PX4 emulator over loopback UDP, through MAVSDK's param plugin (tests/px4: against real PX4).
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.cli import main
from companion.errors import ConfigError
from companion.param_check import (
    BOARD_ONLY,
    INT32,
    REAL32,
    AutopilotIdentity,
    ParamRow,
    check_autopilot,
    compare,
    identity_findings,
    read_params_file,
)
from companion.px4_params_file import render_file
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
from sim_harness.hil.px4_param_server import PX4_STOCK

SHIPPED = Path(__file__).resolve().parents[2] / "firmware_cfg" / "px4" / "companion.params"


@pytest.fixture
def emulator() -> Iterator[AutopilotEmulator]:
    with AutopilotEmulator(EmulatorConfig(free_udp_port(), heartbeat_rate_hz=20.0)) as emu:
        yield emu


def url_of(emulator: AutopilotEmulator) -> str:
    return f"udpin://127.0.0.1:{emulator.config.client_port}"


def load_with_mavsdk(url: str, rows: list[ParamRow]) -> None:
    """What QGroundControl's "load from file" does: PARAM_SET for every row."""
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.param import ParamAsync

    async def load() -> None:
        mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            await mavsdk.add_any_connection(url)
            system = await mavsdk.first_autopilot(10.0)
            assert system is not None
            param = ParamAsync(system)
            for row in rows:
                if row.param_type == INT32:
                    await param.set_param_int(row.name, round(row.value))
                else:
                    await param.set_param_float(row.name, row.value)
        finally:
            mavsdk.destroy()

    asyncio.run(load())


def test_the_shipped_file_reads_with_types(tmp_path: Path) -> None:
    rows = {row.name: row for row in read_params_file(SHIPPED)}
    assert rows["COM_OBL_RC_ACT"] == ParamRow("COM_OBL_RC_ACT", 5, INT32)
    assert rows["COM_OF_LOSS_T"] == ParamRow("COM_OF_LOSS_T", 1.0, REAL32)
    assert set(BOARD_ONLY) <= set(rows)
    bad = tmp_path / "bad.params"
    bad.write_text("# comment\n1\t1\tCOM_OF_LOSS_T\t1.0\n")
    with pytest.raises(ConfigError, match=r"bad.params:2: expected 5"):
        read_params_file(bad)


def test_compare_tells_board_only_from_misspelled_and_values_at_float32() -> None:
    rows = [
        ParamRow("MAV_1_CONFIG", 102, INT32),
        ParamRow("COM_OF_LOS_T", 1.0, REAL32),  # misspelled
        ParamRow("MPC_Z_VEL_MAX_DN", 0.75, REAL32),
        ParamRow("MPC_XY_VEL_MAX", 0.1, REAL32),
        ParamRow("GF_ACTION", 2, INT32),
    ]
    live: dict[str, tuple[str, float | None, str]] = {
        "MAV_1_CONFIG": ("missing", None, ""),
        "COM_OF_LOS_T": ("missing", None, ""),
        "MPC_Z_VEL_MAX_DN": ("ok", 0.75, ""),
        "MPC_XY_VEL_MAX": ("ok", 0.10000000149011612, ""),  # 0.1 as float32 reads back
        "GF_ACTION": ("ok", 3.0, ""),
    }
    found = {d.name: d for d in compare(rows, live)}
    assert set(found) == {"MAV_1_CONFIG", "COM_OF_LOS_T", "GF_ACTION"}
    assert found["MAV_1_CONFIG"].kind == "board-only" and not found["MAV_1_CONFIG"].is_failure
    assert found["COM_OF_LOS_T"].kind == "missing" and found["COM_OF_LOS_T"].is_failure
    assert found["MAV_1_CONFIG"].line().startswith("MAV_1_CONFIG: not on this board (serial-port")
    assert found["COM_OF_LOS_T"].line() == (
        "COM_OF_LOS_T: no such parameter: misspelled, or needs a newer PX4"
    )
    assert found["GF_ACTION"].line() == "GF_ACTION: 3 on the autopilot, 2 in the file"


def test_a_stock_emulated_px4_differs_where_the_file_changes_something(
    emulator: AutopilotEmulator,
) -> None:
    found = check_autopilot(url_of(emulator), SHIPPED, 10.0)
    rows, differences = found.rows, found.differences
    stock = emulator.param_values()  # PX4's defaults; COM_OF_LOSS_T 0.5 s (fast tests)
    expected = {r.name for r in rows if r.value != stock[r.name]}
    assert {d.name for d in differences} == expected
    assert {"COM_OBL_RC_ACT", "MAV_1_CONFIG", "GF_MAX_VER_DIST", "COM_RC_OVERRIDE"} <= expected
    assert all(d.kind == "different" for d in differences)  # the emulator plays a Pixracer
    assert found.identity == AutopilotIdentity(1, (1, 15, 0), "")  # the emulator: PX4 1.15.0
    assert found.stated_version == (1, 17)
    assert stock["COM_OBL_RC_ACT"] == PX4_STOCK["COM_OBL_RC_ACT"][0] == 0


def test_after_loading_the_file_the_check_passes_and_a_typo_fails(
    emulator: AutopilotEmulator, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = url_of(emulator)
    load_with_mavsdk(url, read_params_file(SHIPPED))
    assert emulator.param_values()["COM_OBL_RC_ACT"] == 5
    assert main(["check", "--autopilot", "--url", url, "--params", str(SHIPPED)]) == 0
    assert "0 difference(s)" in capsys.readouterr().out
    typo = tmp_path / "typo.params"
    typo.write_text(SHIPPED.read_text() + "1\t1\tCOM_OF_LOS_T\t1.0\t9\n")
    assert main(["check", "--autopilot", "--url", url, "--params", str(typo)]) == 1
    out = capsys.readouterr().out
    assert "COM_OF_LOS_T: no such parameter: misspelled, or needs a newer PX4" in out
    assert "1 difference(s)" in out


def test_a_file_for_another_drone_fails_and_another_px4_version_warns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """QGroundControl refuses a file whose vehicle id is not the drone's MAV_SYS_ID: the check
    says so before the pilot finds out in the field. The emulator runs PX4 1.15, the file is for
    1.17: a warning, not a failure."""
    config = EmulatorConfig(free_udp_port(), system_id=3, heartbeat_rate_hz=20.0)
    drone3 = tmp_path / "drone3.params"
    drone3.write_text(render_file(SHIPPED, 3))
    with AutopilotEmulator(config) as emulator:
        url = url_of(emulator)
        load_with_mavsdk(url, read_params_file(drone3))
        assert main(["check", "--autopilot", "--url", url, "--params", str(drone3)]) == 0
        out = capsys.readouterr().out
        assert "[  ok] autopilot   vehicle id 3: the autopilot's system id" in out
        assert (
            "[warn] autopilot   the autopilot runs PX4 1.15.0, the file was checked against 1.17"
        ) in out
        assert main(["check", "--autopilot", "--url", url, "--params", str(SHIPPED)]) == 1
    out = capsys.readouterr().out
    assert "[FAIL] autopilot   the file is for vehicle id 1, the autopilot is system 3" in out
    assert "0 difference(s)" in out  # the values are the same: only the vehicle id differs


def test_identity_findings_vehicle_id_and_version() -> None:
    rows = [ParamRow("GF_ACTION", 2, INT32, 4)]

    def verdicts(version: tuple[int, int, int] | None, stated: tuple[int, int] | None) -> list[str]:
        found = identity_findings(rows, stated, AutopilotIdentity(4, version, "02e73e3b6f99"))
        return [f"{verdict}: {line}" for verdict, line in found]

    assert verdicts((1, 17, 2), (1, 17)) == [
        "ok: vehicle id 4: the autopilot's system id",
        "ok: PX4 1.17.2: the version the file was checked against (1.17)",
    ]
    assert verdicts((1, 16, 0), (1, 17))[1].startswith("warn: the autopilot runs PX4 1.16.0, git")
    assert verdicts((2, 17, 0), (1, 17))[1].startswith("warn: the autopilot runs PX4 2.17.0")
    assert verdicts((0, 0, 0), (1, 17))[1] == (
        "warn: the autopilot reports PX4 0.0.0 (an untagged build, git 02e73e3b6f): cannot tell "
        "whether it is 1.17, the version the file was checked against"
    )
    assert verdicts(None, (1, 17))[1].startswith("warn: the autopilot did not report its version")
    assert verdicts((1, 17, 0), None)[1].startswith("warn: the file states no PX4 version")
    mixed = [*rows, ParamRow("GF_MAX_VER_DIST", 30.0, REAL32, 5)]
    found = identity_findings(mixed, (1, 17), AutopilotIdentity(4, (1, 17, 0)))
    assert found[0] == ("FAIL", "the file mixes vehicle ids 4, 5")


def test_the_shipped_altitude_ceiling_sits_inside_the_geofence_with_a_margin() -> None:
    """Issue 19 finding 3: ceiling == fence height let PX4 hold at 30.45 m, breach the fence and
    raise a geofence failsafe. Both count from the take-off point (EKF origin, home)."""
    import tomllib

    config = tomllib.loads((SHIPPED.parents[2] / "systemd" / "companion.toml").read_text())
    ceiling_m = config["control"]["altitude_ceiling_m"]
    fence_m = {row.name: row.value for row in read_params_file(SHIPPED)}["GF_MAX_VER_DIST"]
    assert ceiling_m + 3.0 <= fence_m
