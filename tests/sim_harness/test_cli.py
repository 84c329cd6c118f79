"""`swarm-sim` writes what it promises and fails with one clear line."""

import json
import subprocess
import sys

import pytest

from sim_harness.cli import main


@pytest.mark.slow
def test_fly_writes_summary_log_and_figures(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    code = main(
        [
            "fly",
            "--scenario",
            "common",
            "--agents",
            "4",
            "--seed",
            "1",
            "--duration",
            "5",
            "--out",
            str(out),
            "--no-progress",
        ]
    )
    assert code == 0
    for name in (
        "summary.json",
        "timing.json",
        "steps.npz",
        "flight.png",
        "trajectories.png",
        "distances.png",
        "order.png",
    ):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_agents"] == 4 and summary["seed"] == 1
    assert summary["duration_s"] == pytest.approx(5.0)
    assert "common" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (["fly", "--agents", "0"], "scenario.n_agents"),
        (["fly", "--vmax", "-2"], "flocking.v_max_mps"),
        (["fly", "--scenario", "spiral"], "unknown name 'spiral'"),
        (["fly", "--physics-hz", "95"], "rates.physics_hz"),
    ],
)
def test_bad_input_is_one_clear_line_and_exit_2(args, field, tmp_path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "sim_harness.cli", *args, "--out", str(tmp_path / "x")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("swarm-sim: error:")
    assert field in lines[0]
    assert not (tmp_path / "x").exists()  # nothing half-written
