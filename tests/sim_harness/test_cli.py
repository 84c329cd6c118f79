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
        (["train", "--dataset", "data/x", "--dropout", "1"], "dropout"),
        (["dataset", "close-range", "data/x", "--min", "0.9", "--max", "0.5"], "close-range.max_m"),
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


def _must_not_run(*args, **kwargs):
    raise AssertionError("the work started before the output folder was checked")


@pytest.mark.parametrize(
    ("args", "work"),
    [
        (["fly"], "sim_harness.sim.cli.fly"),
        (["view", "--step", "3"], "sim_harness.sim.cli.fly"),
        (["demo"], "sim_harness.experiments.runner.run_suite"),
        (["experiments", "--suite", "bar"], "sim_harness.experiments.runner.run_suite"),
        (["dataset", "generate", "--preset", "smoke"], "sim_harness.dataset.cli.generate"),
        (["dataset", "aggregate", "--runs", "10"], "sim_harness.experiments.cli.aggregate"),
        (["dataset", "merge", "data/a", "data/b"], "sim_harness.dataset.cli.merge"),
        (["train", "--dataset", "data/quick-s0"], "sim_harness.learning.train.train"),
    ],
)
def test_an_unwritable_output_folder_is_refused_before_the_work(
    args, work, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(work, _must_not_run)
    assert main([*args, "--out", "/proc/forbidden"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("swarm-sim: error: out: cannot write to the folder /proc/forbidden (")
    assert err.endswith("); choose a writable folder") and "\n" not in err


def test_train_passes_the_head_dropout_through(monkeypatch, tmp_path) -> None:
    seen = []

    def capture(config):
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr("sim_harness.learning.train.train", capture)
    for extra, expected in (([], 0.5), (["--dropout", "0"], 0.0)):
        with pytest.raises(SystemExit):
            main(["train", "--dataset", "data/x", "--out", str(tmp_path / "run"), *extra])
        assert seen[-1].dropout == expected
