"""The shipped parameter file against real PX4: every name exists (but the board-only ones, which
SITL lacks for want of serial ports), every value is accepted and reads back equal, and the live
check `companion check --autopilot` finds no difference after loading the file and exactly the
expected ones on a stock vehicle."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

from companion.param_check import BOARD_ONLY, read_params_file, same_value
from sim_harness.hil.px4_params import SHIPPED_PARAMS

ROWS = read_params_file(SHIPPED_PARAMS)


def live_check(sitl: Any, vehicle: Any, params: Path) -> subprocess.CompletedProcess[str]:
    """`companion check --autopilot` in PX4's namespace, on the vehicle's companion link."""
    argv = [sys.executable, "-m", "companion.cli", "check", "--autopilot"]
    argv += ["--url", vehicle.url, "--params", str(params), "--timeout", "20"]
    return subprocess.run(
        sitl.namespace.command(argv), capture_output=True, text=True, timeout=120, check=False
    )


def test_every_name_exists_except_the_board_only_ones_and_a_typo_is_unknown(stock: Any) -> None:
    gcs = stock.gcs
    missing = {row.name for row in ROWS if gcs.get_param(row.name) is None}
    assert missing == set(BOARD_ONLY)  # MAV_1_CONFIG, SER_TEL2_BAUD: no serial ports in SITL
    assert gcs.get_param("COM_OF_LOS_T") is None  # misspelled: PX4 does not answer
    assert gcs.get_param("COM_OF_LOSS_T") is not None


def test_every_value_is_accepted_and_reads_back_equal(shipped: Any) -> None:
    by_name = {row.name: row for row in ROWS}
    assert set(shipped.loaded) == set(by_name) - set(BOARD_ONLY)
    for name, (value, echoed, read_back) in shipped.loaded.items():
        kind = by_name[name].param_type
        assert same_value(value, echoed, kind), (name, value, echoed)
        assert read_back is not None and same_value(value, read_back, kind), (name, read_back)


def test_live_check_finds_no_difference_after_loading(sitl: Any, shipped: Any) -> None:
    done = live_check(sitl, shipped, SHIPPED_PARAMS)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 difference(s)" in done.stdout
    for name in BOARD_ONLY:
        assert f"[warn] parameters  {name}: not on this autopilot" in done.stdout


def test_live_check_lists_the_differences_of_a_stock_vehicle(
    sitl: Any, stock: Any, tmp_path: Path
) -> None:
    typo = tmp_path / "typo.params"
    typo.write_text(SHIPPED_PARAMS.read_text() + "1\t1\tCOM_OF_LOS_T\t1.0\t9\n")
    done = live_check(sitl, stock, typo)
    assert done.returncode == 1, done.stdout + done.stderr
    stock_values = {row.name: stock.gcs.get_param(row.name) for row in ROWS}
    expected = {
        row.name
        for row in ROWS
        if row.name not in BOARD_ONLY
        and not same_value(row.value, stock_values[row.name] or 0.0, row.param_type)
    }
    assert {"COM_OBL_RC_ACT", "MPC_XY_VEL_MAX", "GF_MAX_VER_DIST"} <= expected
    failed = {
        line.split()[2].rstrip(":")
        for line in done.stdout.splitlines()
        if line.startswith("[FAIL] parameters  ") and "difference(s)" not in line
    }
    assert failed == expected | {"COM_OF_LOS_T"}, done.stdout
    assert "COM_OF_LOS_T: the autopilot has no such parameter" in done.stdout
