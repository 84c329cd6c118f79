"""sd_notify over real unix datagram sockets, and when the daemon's outputs ping the watchdog."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.autopilot_types import AutopilotTelemetry, OffboardState
from companion.daemon_outputs import Outputs, TickTimes
from companion.health import Action, HealthDecision, HealthState
from companion.recorder import FlightRecorder, RecorderConfig
from companion.sdnotify import SdNotifier
from companion.telemetry import TelemetryConfig, TelemetryPublisher


@pytest.fixture
def abstract_socket() -> Iterator[tuple[socket.socket, str]]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    name = f"sdnotify-test-{os.getpid()}-{id(sock)}"
    sock.bind("\0" + name)
    sock.settimeout(1.0)
    yield sock, "@" + name
    sock.close()


def received(sock: socket.socket) -> list[str]:
    sock.setblocking(False)
    lines: list[str] = []
    try:
        while True:
            lines.extend(sock.recv(4096).decode().splitlines())
    except BlockingIOError:
        return lines


def test_messages_reach_a_path_socket(tmp_path: Path) -> None:
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        notifier = SdNotifier({"NOTIFY_SOCKET": str(path)})
        assert notifier.enabled and notifier.watchdog_interval_s is None
        assert notifier.ready("healthy")
        assert notifier.watchdog()
        assert notifier.stopping()
        notifier.close()
        assert received(sock) == ["READY=1", "STATUS=healthy", "WATCHDOG=1", "STOPPING=1"]


def test_abstract_namespace_and_watchdog_interval(
    abstract_socket: tuple[socket.socket, str],
) -> None:
    sock, address = abstract_socket
    env = {"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}
    notifier = SdNotifier(env)
    assert notifier.watchdog_interval_s == pytest.approx(2.5)  # half of WatchdogSec
    assert notifier.status("hover: left stale")
    assert received(sock) == ["STATUS=hover: left stale"]
    notifier.close()


@pytest.mark.parametrize(
    "env",
    [
        {},
        {"NOTIFY_SOCKET": "relative/name"},
        {"WATCHDOG_USEC": "5000000"},
    ],
)
def test_without_a_usable_socket_everything_is_a_no_op(env: dict[str, str]) -> None:
    notifier = SdNotifier(env)
    assert not notifier.enabled and notifier.watchdog_interval_s is None
    assert not notifier.ready() and not notifier.watchdog()


def test_watchdog_meant_for_another_process_is_ignored(
    abstract_socket: tuple[socket.socket, str],
) -> None:
    _, address = abstract_socket
    env = {"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}
    assert SdNotifier(env).watchdog_interval_s is None


def test_a_vanished_socket_is_logged_not_raised(tmp_path: Path) -> None:
    notifier = SdNotifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert not notifier.ready()


def test_outputs_send_ready_once_and_withhold_the_watchdog_for_late_ticks(
    tmp_path: Path, abstract_socket: tuple[socket.socket, str]
) -> None:
    sock, address = abstract_socket
    notifier = SdNotifier({"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "200000"})  # every 0.1 s
    outputs = Outputs(
        FlightRecorder(RecorderConfig(directory=tmp_path, enabled=False)),
        TelemetryPublisher(TelemetryConfig(enabled=False)),
        notifier,
        {},
        wall_ns_of=lambda t_s: int(t_s * 1e9),
        watchdog_max_late_s=0.5,
    )

    def tick(now_s: float, late_s: float, healthy: bool) -> None:
        state = HealthState.ACTIVE if healthy else HealthState.HOVER
        decision = HealthDecision(state, Action.WAIT, "", healthy, None)
        times = TickTimes(now_s, late_s, now_s, None, None)
        outputs.tick(decision, None, False, times, AutopilotTelemetry(), OffboardState.ACTIVE, {})

    tick(0.0, 0.0, healthy=False)
    assert received(sock) == ["WATCHDOG=1"]  # the loop is healthy even if the pipeline is not
    tick(0.05, 0.0, healthy=True)
    assert received(sock) == ["READY=1", "STATUS=healthy, active"]  # watchdog: not due yet
    tick(0.2, 0.6, healthy=True)  # this tick started 0.6 s after its deadline
    assert received(sock) == []
    tick(0.3, 0.0, healthy=True)
    assert received(sock) == ["WATCHDOG=1"]  # READY only once
    notifier.close()
