"""The shipped unit: its sandbox scored by systemd-analyze, what it does on a permanent error,
and the facts the package reads from it (writable directories, start and stop timeouts)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path, PurePosixPath

import pytest

from companion import cli, groundstation
from companion.service_unit import (
    LAUNCH_TIMEOUT_S,
    SHIPPED_UNIT,
    START_TIMEOUT_S,
    STOP_TIMEOUT_S,
    read_service_section,
    sandbox_of,
    timeout_s,
)

SCRIPT = SHIPPED_UNIT.parent / "check-security.sh"
needs_analyze = pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze missing (apt: systemd)"
)


def score(unit: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["bash", str(SCRIPT), str(unit)], capture_output=True, text=True)


@needs_analyze
def test_the_shipped_unit_scores_at_most_2() -> None:
    result = score(SHIPPED_UNIT)
    assert result.returncode == 0, result.stdout + result.stderr
    exposure = float(result.stdout.split("exposure ")[1].split()[0])
    assert exposure <= 2.0


@needs_analyze
def test_the_check_fails_without_the_sandbox_or_with_a_line_systemd_ignores(
    tmp_path: Path,
) -> None:
    text = SHIPPED_UNIT.read_text()
    bare = tmp_path / SHIPPED_UNIT.name
    bare.write_text(text[: text.index("# Sandbox")] + text[text.index("[Install]") :])
    result = score(bare)
    assert result.returncode == 1 and "is above 2.0" in result.stdout
    bare.write_text(text.replace("LockPersonality=yes", "LockPersonalty=yes"))
    result = score(bare)
    assert result.returncode == 1 and "Unknown key 'LockPersonalty'" in result.stdout
    bare.write_text(text.replace("[Service]", "[Service]\nMemoryDenyWriteExecute=yes"))
    result = score(bare)
    assert result.returncode == 1 and "breaks oneDNN" in result.stdout


def test_the_sandbox_keeps_what_the_daemon_needs() -> None:
    service = read_service_section(SHIPPED_UNIT)
    assert "MemoryDenyWriteExecute" not in service  # oneDNN's JIT (graph fusion)
    assert service["Type"] == ["notify"] and "WatchdogSec" in service
    assert service["Nice"] == ["-5"] and service["SupplementaryGroups"] == ["dialout"]
    families = service["RestrictAddressFamilies"][-1].split()
    assert {"AF_UNIX", "AF_INET", "AF_INET6"} <= set(families)
    assert service["DeviceAllow"] == ["char-tty* rw"]  # ttyACM (cameras), ttyS/ttyAMA/ttyUSB
    assert service["RuntimeDirectory"] == ["vision-swarm"]  # /run/vision-swarm/control.sock
    assert service["RuntimeDirectoryMode"] == ["0750"]
    sandbox = sandbox_of(SHIPPED_UNIT)
    assert sandbox.writable == (
        PurePosixPath("/var/lib/vision-swarm"),
        PurePosixPath("/run/vision-swarm"),
    )


def test_a_permanent_error_is_not_restarted() -> None:
    service = read_service_section(SHIPPED_UNIT)
    assert service["Restart"] == ["on-failure"]
    assert "2" in service["RestartPreventExitStatus"][-1].split()


def test_a_config_error_exits_2_before_any_flight_log(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    flights = tmp_path / "flights"
    config = tmp_path / "companion.toml"
    config.write_text(
        f'[drone]\nid = "d1"\n[policy]\nmodel_path = "m.pt"\n'
        f'[recorder]\ndirectory = "{flights}"\n[daemon]\nrate_hz = 5.0\n'
    )
    assert cli.main(["run", "--config", str(config)]) == 2  # the unit does not restart it
    assert "daemon.rate_hz" in capsys.readouterr().err
    assert not flights.exists() or not any(flights.iterdir())


def test_the_ground_waits_longer_than_systemd_for_a_start_or_a_restart() -> None:
    assert timeout_s(SHIPPED_UNIT, "TimeoutStartSec") == START_TIMEOUT_S
    assert timeout_s(SHIPPED_UNIT, "TimeoutStopSec") == STOP_TIMEOUT_S
    connect_s = float(dict(o.split("=") for o in groundstation.SSH_OPTIONS[1::2])["ConnectTimeout"])
    assert START_TIMEOUT_S + STOP_TIMEOUT_S + connect_s < LAUNCH_TIMEOUT_S  # restart = both
    args = cli.build_parser().parse_args(["ground", "launch", "--hosts", "d1"])
    assert args.timeout == LAUNCH_TIMEOUT_S


def test_time_values_as_systemd_writes_them(tmp_path: Path) -> None:
    unit = tmp_path / "x.service"
    unit.write_text("[Service]\nTimeoutStartSec=2min 30s\nTimeoutStopSec=90\n")
    assert timeout_s(unit, "TimeoutStartSec") == 150.0
    assert timeout_s(unit, "TimeoutStopSec") == 90.0
