"""The shipped parameter file against real PX4: every name exists (but the board-only ones, which
SITL lacks for want of serial ports), every value lies in PX4's own range and is accepted, reads
back equal and makes PX4 clamp nothing (no "constrained" message while loading), and the live
check `companion check --autopilot` finds no difference after loading the file and exactly the
expected ones on a stock vehicle, with that drone's own file (vehicle id 2)."""

from __future__ import annotations

import json
import lzma
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from companion.param_check import BOARD_ONLY, INT32, read_params_file, same_value, stated_version
from companion.px4_params_file import render_file
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


def test_every_value_is_in_px4s_own_range_with_its_type(sitl: Any) -> None:
    """PX4's parameter metadata of the very build (etc/extras/parameters.json.xz)."""
    metadata = sitl.root / "etc" / "extras" / "parameters.json.xz"
    known = {p["name"]: p for p in json.loads(lzma.decompress(metadata.read_bytes()))["parameters"]}
    for row in ROWS:
        if row.name in BOARD_ONLY:
            continue
        meta = known[row.name]
        assert (meta["type"] == "Int32") == (row.param_type == INT32), row.name
        assert meta.get("min", row.value) <= row.value <= meta.get("max", row.value), row.name
        values = [v["value"] for v in meta.get("values", [])]
        assert not values or row.value in values, (row.name, values)


def test_the_file_states_the_px4_it_was_checked_against() -> None:
    text = SHIPPED_PARAMS.read_text()
    assert stated_version(text) == (1, 17)  # main 02e73e3b6f: after v1.17.0-beta1
    tarball = os.environ.get("PX4_SITL_TARBALL", "")
    commit = tarball.rsplit("-", 1)[-1].split(".")[0] if "sih-" in tarball else "02e73e3b6f"
    assert commit in text


def test_loading_the_file_makes_px4_clamp_nothing(shipped: Any) -> None:
    """MPC_XY_VEL_MAX alone made PX4 clamp MPC_XY_CRUISE and MPC_VEL_MANUAL ("Cruise speed has
    been constrained by max speed", critical), MPC_Z_VEL_MAX_UP/DN below the auto speeds too."""
    assert not [t for t in shipped.load_texts if "constrained" in t], shipped.load_texts


def test_live_check_finds_no_difference_after_loading(sitl: Any, shipped: Any) -> None:
    done = live_check(sitl, shipped, SHIPPED_PARAMS)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "0 difference(s)" in done.stdout
    for name in BOARD_ONLY:
        assert f"[warn] parameters  {name}: not on this board" in done.stdout
    assert "[  ok] autopilot   vehicle id 1: the autopilot's system id" in done.stdout
    # SITL's untagged build reports v0.0.0: a warning that the versions cannot be compared.
    assert "[warn] autopilot   the autopilot reports PX4 0.0.0 (an untagged build" in done.stdout


def test_live_check_lists_the_differences_of_a_stock_vehicle(
    sitl: Any, stock: Any, tmp_path: Path
) -> None:
    typo = tmp_path / "drone2-typo.params"  # the stock vehicle is system 2: its own file
    typo.write_text(render_file(SHIPPED_PARAMS, 2) + "2\t1\tCOM_OF_LOS_T\t1.0\t9\n")
    done = live_check(sitl, stock, typo)
    assert done.returncode == 1, done.stdout + done.stderr
    stock_values = {row.name: stock.gcs.get_param(row.name) for row in ROWS}
    expected = {
        row.name
        for row in ROWS
        if row.name not in BOARD_ONLY
        and not same_value(row.value, stock_values[row.name] or 0.0, row.param_type)
    }
    assert {"COM_OBL_RC_ACT", "MPC_XY_VEL_MAX", "GF_MAX_VER_DIST", "COM_RC_OVERRIDE"} <= expected
    failed = {
        line.split()[2].rstrip(":")
        for line in done.stdout.splitlines()
        if line.startswith("[FAIL] parameters  ") and "difference(s)" not in line
    }
    assert failed == expected | {"COM_OF_LOS_T"}, done.stdout
    assert "COM_OF_LOS_T: no such parameter: misspelled, or needs a newer PX4" in done.stdout
    assert "[  ok] autopilot   vehicle id 2: the autopilot's system id" in done.stdout
