"""`companion check`, `companion log summary`, `companion run` errors: real files, real devices."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion import cli
from companion.model_file import sha256_file
from companion.recorder import TOPIC_SETPOINT, FlightRecorder, RecorderConfig

FACES = ("front", "right", "back", "left", "up", "down")


@pytest.fixture
def ptys() -> Any:
    """Six real pty slaves standing in for the camera devices (character devices)."""
    fds, names = [], []
    for _ in FACES:
        master, slave = os.openpty()
        fds += [master, slave]
        names.append(os.ttyname(slave))
    yield names
    for fd in fds:
        os.close(fd)


def line_of(report: str, marker: str) -> str:
    return next(line for line in report.splitlines() if marker in line)


def write_config(tmp_path: Path, devices: list[str], model: Path, extra: str = "") -> Path:
    faces = "".join(
        f'[cameras.faces.{face}]\ndevice = "{device}"\ncamera_id = "{index + 1:024x}"\n'
        for index, (face, device) in enumerate(zip(FACES, devices, strict=True))
    )
    text = (
        f'[drone]\nid = "d4"\n[policy]\nmodel_path = "{model.name}"\n'
        f'sha256 = "{sha256_file(model)}"\n'
        f'[recorder]\ndirectory = "flights"\n{extra}\n[cameras]\n{faces}'
    )
    path = model.parent / "companion.toml"
    path.write_text(text)
    return path


def test_check_reports_ready_for_a_good_drone(
    tmp_path: Path, ptys: list[str], make_policy_file: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    from sim_harness.learning.export import add_reference

    model = make_policy_file("constant")
    add_reference(model)  # as every export records it
    assert cli.main(["check", "--config", str(write_config(tmp_path, ptys, model))]) == 0
    out = capsys.readouterr().out
    assert out.strip().splitlines()[-1] == "ready"
    assert "reference output within" in line_of(out, "] platform ")
    assert line_of(out, "] platform ").startswith("[  ok]")
    model_line = line_of(out, "] model ")
    assert model_line.startswith("[  ok]") and str(model) in model_line
    assert f"sha256 {sha256_file(model)} (pinned in the config)" in model_line
    up = line_of(out, "] camera up ")
    assert up.startswith("[  ok]") and ptys[4] in up
    assert "udpin://127.0.0.1:14540 (network link: not contacted here)" in out
    assert "(will be created)" in out and "GB free" in out


def test_check_fails_a_platform_that_computes_the_policy_wrongly(
    tmp_path: Path, ptys: list[str], make_policy_file: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    """The export's reference output moved by 8.9 m/s (as a faulty CPU would compute it)."""
    import json

    from companion.model_file import sidecar_path
    from sim_harness.learning.export import add_reference

    model = make_policy_file("constant")
    add_reference(model)
    sidecar = sidecar_path(model)
    record = json.loads(sidecar.read_text())
    record["reference"]["output_body_flu_mps"][0] += 8.9
    sidecar.write_text(json.dumps(record))
    assert cli.main(["check", "--config", str(write_config(tmp_path, ptys, model))]) == 1
    platform = line_of(capsys.readouterr().out, "] platform ")
    assert platform.startswith("[FAIL]") and "exceeds the tolerance" in platform


def test_check_names_every_problem_and_exits_1(
    tmp_path: Path, ptys: list[str], make_policy_file: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    model = make_policy_file("constant")
    devices = [*ptys[:5], str(tmp_path / "openmv-down")]
    extra = '[autopilot]\nurl = "serial:///dev/no-such-uart:921600"\n'
    config = write_config(tmp_path, devices, model, extra)
    model.write_bytes(model.read_bytes() + b"tampered")
    assert cli.main(["check", "--config", str(config)]) == 1
    out = capsys.readouterr().out
    assert "[FAIL] model" in out and "refused" in out
    down = line_of(out, "] camera down ")
    assert down.startswith("[FAIL]")
    assert f"{tmp_path / 'openmv-down'}: No such file or directory" in down
    assert "[FAIL] autopilot" in out and "/dev/no-such-uart" in out
    assert "NOT READY: 3 problem(s): model, camera down, autopilot" in out


def test_check_stops_at_an_invalid_config_and_lists_all_its_problems(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(
        '[drone]\nid = "a b"\n[policy]\nmodel_path = "m.pt"\n[cameras]\nbaud = 921600\n'
        "[daemon]\nrate_hz = 5.0\n"
    )
    assert cli.main(["check", "--config", str(path)]) == 1
    out = capsys.readouterr().out.splitlines()
    assert all(line.startswith("[FAIL] config") for line in out[:-1])
    problems = "\n".join(out[:-1])
    assert "drone.id: 'a b'" in problems
    assert "daemon.rate_hz: 5 is outside the allowed range [10, 100]" in problems
    assert "cameras.faces: missing" in problems
    assert "cameras.baud: 921600" in problems
    assert out[-1] == "NOT READY: 4 problem(s): config"


def test_run_with_a_bad_config_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["run", "--config", str(tmp_path / "missing.toml")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("companion: error: cannot read config file") and "\n" not in err


def test_log_summary_of_a_recorded_flight(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recorder = FlightRecorder(RecorderConfig(directory=tmp_path), drone_id="d4")
    with recorder:
        recorder.record_frame(np.zeros((64, 384), np.uint8))
        recorder.record(TOPIC_SETPOINT, {"vel_ned": [1.0, 0.0, 0.0], "yaw_ned_rad": 0.0})
        recorder.record_health("active -> hover", "warning", "left: stale")
    (log,) = recorder.files
    assert cli.main(["log", "summary", str(log)]) == 0
    out = capsys.readouterr().out
    assert f"{log}: complete" in out and "/control/setpoint" in out
    assert "warning active -> hover: left: stale" in out

    assert cli.main(["log", "summary", str(tmp_path / "none.mcap")]) == 2
    assert "no such flight log" in capsys.readouterr().err


@pytest.mark.parametrize("content", [b"time,vx,vy\n0.0,1.0,0.0\n", b"\x89MCAX0\r\n" * 4])
def test_log_summary_and_recover_refuse_a_file_that_is_not_mcap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes
) -> None:
    path = tmp_path / "flight.mcap"
    path.write_bytes(content)
    assert cli.main(["log", "summary", str(path)]) == 2
    captured = capsys.readouterr()
    assert "INCOMPLETE" not in captured.out
    err = captured.err.strip()
    assert err.startswith(f"companion: error: {path}: not an MCAP file") and "\n" not in err
    out = tmp_path / "recovered.mcap"
    assert cli.main(["log", "recover", str(path), str(out)]) == 2
    assert "not an MCAP file" in capsys.readouterr().err
    assert not out.exists()


def test_log_recover_completes_a_file_cut_by_a_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    recorder = FlightRecorder(RecorderConfig(directory=tmp_path / "logs"), drone_id="d4")
    with recorder:
        for index in range(20):
            recorder.record(TOPIC_SETPOINT, {"vel_ned": [float(index), 0.0, 0.0]})
    (log,) = recorder.files
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.read_bytes()[: log.stat().st_size - 200])  # footer and summary gone
    assert cli.main(["log", "summary", str(cut)]) == 0
    assert "INCOMPLETE" in capsys.readouterr().out
    out = tmp_path / "recovered.mcap"
    assert cli.main(["log", "recover", str(cut), str(out)]) == 0
    assert "20 messages recovered" in capsys.readouterr().out
    assert cli.main(["log", "summary", str(out)]) == 0
    assert f"{out}: complete" in capsys.readouterr().out
    assert cli.main(["log", "recover", str(cut), str(out)]) == 2  # never overwrites
    assert "already exists" in capsys.readouterr().err


def test_conventions_still_there(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["conventions"]) == 0
    assert "NED" in capsys.readouterr().out
