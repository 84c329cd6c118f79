"""Ground station: SSH command lines (run through a stand-in ssh program, never a network), and
the live monitor against a real telemetry publisher on loopback Zenoh."""

from __future__ import annotations

import asyncio
import io
import json
import socket
import threading
from pathlib import Path

import pytest

from companion import cli
from companion.errors import ConfigError
from companion.groundstation import (
    DEFAULT_UNIT,
    SwarmTable,
    format_launch,
    launch,
    run_monitor,
    ssh_command,
)
from companion.telemetry import TelemetryConfig, TelemetryPublisher


def test_ssh_command_runs_one_systemctl_action_without_a_password_prompt() -> None:
    argv = ssh_command("drone3.local", "start", user="odroid", port=2222)
    assert argv == [
        "ssh",
        "-o",
        "BatchMode=yes",
        "-o",
        "ConnectTimeout=5",
        "-p",
        "2222",
        "odroid@drone3.local",
        "--",
        f"sudo -n systemctl start {DEFAULT_UNIT}",
    ]
    assert ssh_command("10.0.0.7", "stop")[-3:] == [
        "10.0.0.7",
        "--",
        f"sudo -n systemctl stop {DEFAULT_UNIT}",
    ]


@pytest.mark.parametrize(
    ("host", "action", "options", "message"),
    [
        ("-oProxyCommand=evil", "start", {}, r"ground\.hosts: '-oProxyCommand=evil'"),
        ("drone 1", "start", {}, r"ground\.hosts"),
        ("drone1", "rm", {}, r"ground\.action: 'rm' must be one of start"),
        ("drone1", "start", {"user": "root;reboot"}, r"ground\.user"),
        ("drone1", "start", {"unit": "x y"}, r"ground\.unit"),
        ("drone1", "start", {"port": 70000}, r"ground\.port: 70000 is outside"),
    ],
)
def test_ssh_command_refuses_what_could_inject(
    host: str, action: str, options: dict, message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        ssh_command(host, action, **options)


@pytest.fixture
def fake_ssh(tmp_path: Path) -> Path:
    """A stand-in for ssh: echoes its target and remote command; host 'down' fails, 'slow' hangs."""
    script = tmp_path / "fake-ssh"
    script.write_text(
        "#!/bin/sh\n"
        "for last; do :; done\n"
        'for a; do case "$a" in -*|BatchMode*|ConnectTimeout*) ;;\n'
        '  *) target="$a"; break;; esac; done\n'
        'case "$target" in\n'
        '  down) echo "ssh: connect to host down port 22: No route to host" >&2; exit 255;;\n'
        "  slow) sleep 30;;\n"
        "esac\n"
        'echo "$target: $last"\n'
    )
    script.chmod(0o755)
    return script


def test_launch_runs_every_host_in_parallel_and_reports_each(fake_ssh: Path) -> None:
    # The timeout must outlast starting a shell on a loaded machine (d1, d2: ~10 ms when quiet)
    # and stay far below the hung host's 30 s.
    results = asyncio.run(
        launch(["d1", "down", "slow", "d2"], "start", ssh=str(fake_ssh), timeout_s=3.0)
    )
    assert [r.host for r in results] == ["d1", "down", "slow", "d2"]
    assert [r.ok for r in results] == [True, False, False, True]
    assert results[0].output == f"d1: sudo -n systemctl start {DEFAULT_UNIT}"
    assert results[1].returncode == 255 and "No route to host" in results[1].output
    assert results[2].returncode is None and "no answer within 3 s" in results[2].output
    text = format_launch(results, "start")
    assert "down" in text and "FAILED (exit 255)" in text and "2/4 hosts ok" in text


def test_cli_launch_exit_status_and_dry_run(
    fake_ssh: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["ground", "launch", "--hosts", "d1", "d2", "--ssh", str(fake_ssh)]) == 0
    assert "2/2 hosts ok" in capsys.readouterr().out
    args = ["ground", "launch", "--hosts", "d1", "down", "--ssh", str(fake_ssh), "--action", "stop"]
    assert cli.main(args) == 1
    assert "1/2 hosts ok" in capsys.readouterr().out
    assert cli.main(["ground", "launch", "--hosts", "d1", "--dry-run", "--user", "pi"]) == 0
    assert (
        capsys.readouterr().out.strip().endswith(f"pi@d1 -- sudo -n systemctl start {DEFAULT_UNIT}")
    )
    assert cli.main(["ground", "launch", "--hosts=-x", "--dry-run"]) == 2
    assert "ground.hosts" in capsys.readouterr().err


def message(data: dict) -> bytes:
    return json.dumps(
        {"drone_id": "x", "seq": 1, "stamp_ns": 0, "age_s": 0.0, "data": data}
    ).encode()


def test_swarm_table_shows_each_drone_latest_values() -> None:
    now = [100.0]
    table = SwarmTable(clock=lambda: now[0])
    assert "(no drone heard yet)" in table.render()
    table.update(
        "swarm/d2/state",
        message({"health": "active", "flight_mode": "offboard", "armed": True,
                 "position_ned_m": [1.0, -2.0, -5.0]}),
    )  # fmt: skip
    table.update("swarm/d2/setpoint", message({"vel_ned": [0.5, 1.0, -0.25]}))
    table.update("swarm/d1/health", message({"state": "hover", "reason": "left: stale"}))
    table.update("swarm/d1/preview", b"\x89PNG...")
    table.update("swarm/d1/state", b"not json")
    now[0] = 101.5
    lines = table.render().splitlines()
    assert lines[0].split()[:3] == ["drone", "health", "mode"]
    d1, d2 = lines[1], lines[2]
    assert d1.split()[:2] == ["d1", "hover"] and "left: stale" in d1 and "1.5" in d1
    assert "offboard" in d2 and "yes" in d2 and "(+1.0, -2.0, -5.0)" in d2
    assert "(+0.50, +1.00, -0.25)" in d2
    assert table.drones() == ["d1", "d2"] and table.received == 5


def test_monitor_prints_a_drone_published_over_loopback_zenoh() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    config = TelemetryConfig(drone_id="d9", listen_endpoints=(f"tcp/127.0.0.1:{port}",))
    out = io.StringIO()
    done = threading.Event()

    def monitor() -> None:
        try:
            # 6 tables in 3 s; the asserts below need 3, the last one after the link is up (tens
            # of ms): margin for a loaded machine that wakes the monitor late.
            run_monitor([f"tcp/127.0.0.1:{port}"], interval_s=0.5, duration_s=3.0, out=out)
        finally:
            done.set()

    async def publish() -> None:
        async with TelemetryPublisher(config) as publisher:
            publisher.update_state({"health": "active", "flight_mode": "offboard", "armed": True})
            publisher.update_health({"state": "active", "reason": ""})
            thread = threading.Thread(target=monitor)
            thread.start()
            while not done.is_set():
                await publisher.publish_once()
                await asyncio.sleep(0.05)
            thread.join()

    asyncio.run(publish())
    tables = out.getvalue().strip().split("\n\n")
    assert len(tables) >= 3
    last = tables[-1].splitlines()
    assert last[1].split()[:4] == ["d9", "active", "offboard", "yes"]
