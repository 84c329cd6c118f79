"""`companion check` against the installed unit's sandbox: a recorder directory the service may
not write (ProtectSystem=strict) is reported before a flight, not at run time."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from companion import cli
from companion.check import run_checks
from companion.service_unit import SHIPPED_UNIT

FACES = ("front", "right", "back", "left", "up", "down")


@pytest.fixture
def config(tmp_path: Path, make_policy_file: Any) -> Any:
    """A good config (six ptys as cameras) whose recorder directory the test chooses."""
    fds: list[int] = []
    names = []
    for _ in FACES:
        master, slave = os.openpty()
        fds += [master, slave]
        names.append(os.ttyname(slave))
    model = make_policy_file("constant")

    def write(directory: Path) -> Path:
        faces = "".join(
            f'[cameras.faces.{f}]\ndevice = "{d}"\ncamera_id = "{i + 1:024x}"\n'
            for i, (f, d) in enumerate(zip(FACES, names, strict=True))
        )
        path = tmp_path / "companion.toml"
        path.write_text(
            f'[drone]\nid = "d4"\n[policy]\nmodel_path = "{model}"\n'
            f'[recorder]\ndirectory = "{directory}"\n[cameras]\n{faces}'
        )
        return path

    yield write
    for fd in fds:
        os.close(fd)


def unit_writing(tmp_path: Path, *lines: str) -> Path:
    """The shipped unit with its writable directories replaced (a drone's installed unit)."""
    text = SHIPPED_UNIT.read_text().replace("StateDirectory=vision-swarm\n", "")
    unit = tmp_path / "etc" / SHIPPED_UNIT.name
    unit.parent.mkdir(parents=True)
    unit.write_text(text.replace("ReadWritePaths=/var/lib/vision-swarm", "\n".join(lines)))
    return unit


def recorder_line(items: list[Any]) -> Any:
    return next(item for item in items if item.name == "recorder")


def test_a_recorder_outside_the_units_writable_paths_fails(
    tmp_path: Path, config: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    path = config(tmp_path / "logs")  # writable by this user, but not by the service
    assert cli.main(["check", "--config", str(path), "--unit", str(SHIPPED_UNIT)]) == 1
    out = capsys.readouterr().out
    line = next(line for line in out.splitlines() if "] recorder" in line)
    assert line.startswith("[FAIL]") and str(tmp_path / "logs") in line
    assert "read-only but for: /var/lib/vision-swarm, /run/vision-swarm" in line
    assert out.splitlines()[-1] == "NOT READY: 1 problem(s): recorder"


def test_a_recorder_inside_them_passes_and_drop_ins_count(tmp_path: Path, config: Any) -> None:
    state = tmp_path / "state"
    state.mkdir()
    unit = unit_writing(tmp_path, f"ReadWritePaths={state}")
    item = recorder_line(run_checks(config(state / "flights"), unit))
    assert item.verdict == "ok" and "(will be created)" in item.detail

    elsewhere = tmp_path / "usb-stick"
    elsewhere.mkdir()
    assert recorder_line(run_checks(config(elsewhere), unit)).verdict == "FAIL"
    dropin = unit.with_name(unit.name + ".d")
    dropin.mkdir()
    (dropin / "logs.conf").write_text(f"[Service]\nReadWritePaths=-{elsewhere}\n")
    assert recorder_line(run_checks(config(elsewhere), unit)).verdict == "ok"


def test_a_missing_read_write_path_fails(tmp_path: Path, config: Any) -> None:
    unit = unit_writing(tmp_path, f"ReadWritePaths={tmp_path / 'gone'}")
    item = recorder_line(run_checks(config(tmp_path / "gone" / "flights"), unit))
    assert item.verdict == "FAIL" and "does not exist" in item.detail


def test_the_state_directory_passes_before_the_first_start(tmp_path: Path, config: Any) -> None:
    """/var/lib/vision-swarm may not exist yet (systemd creates it at the first start)."""
    item = recorder_line(run_checks(config(Path("/var/lib/vision-swarm/flights")), SHIPPED_UNIT))
    assert item.verdict in ("ok", "warn") and "GB free" in item.detail


def test_without_an_installed_unit_the_check_says_so(tmp_path: Path, config: Any) -> None:
    item = recorder_line(run_checks(config(tmp_path / "logs"), tmp_path / "none.service"))
    assert item.verdict == "ok" and "the service's sandbox is not checked" in item.detail
