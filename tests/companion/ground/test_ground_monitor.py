"""The live monitor: bad endpoints refused in one line, silent drones and unreachable endpoints
made obvious, battery / GPS / per-camera frame rates shown when the drone publishes them."""

from __future__ import annotations

import asyncio
import io
import json
import socket
import threading

import pytest

from companion import cli
from companion.ground_monitor import SwarmTable, run_monitor
from companion.telemetry import TelemetryConfig, TelemetryPublisher


def message(data: dict) -> bytes:
    return json.dumps(
        {"drone_id": "x", "seq": 1, "stamp_ns": 0, "age_s": 0.0, "data": data}
    ).encode()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.parametrize(
    "args",
    [
        ["--connect", "192.168.1.21:7447"],
        ["--connect", "tcp/127.0.0.1:7447", "tcp/drone2"],
        ["--connect", "tcp/drone2:70000"],
        ["--connect", "tcp/drone2:0"],
        ["--listen", "0.0.0.0:7447"],
    ],
)
def test_a_malformed_endpoint_is_one_line_naming_the_option_and_form(
    args: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["ground", "monitor", *args, "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"monitor {args[0]}: " in err and "is not an endpoint tcp/HOST:PORT" in err


def test_battery_gps_and_camera_rates_are_shown_and_dashes_when_absent() -> None:
    table = SwarmTable(clock=lambda: 10.0)
    cameras = {face: {"fps": 10.0, "bad_headers": 0} for face in ("front", "right", "back")}
    cameras |= {"left": {"fps": 7.46}, "up": {"fps": 0.0}, "down": {"connected": False}}
    table.update(
        "swarm/d1/state",
        message({"health": "active", "battery": {"remaining_pct": 87.4, "voltage_v": 15.83},
                 "gps": {"fix_type": "FIX_3D", "satellites": 12}}),
    )  # fmt: skip
    table.update("swarm/d1/health", message({"state": "active", "cameras": cameras}))
    table.update("swarm/d2/state", message({"health": "active"}))
    header, d1, d2 = table.render().splitlines()[:3]
    assert "battery" in header and "gps" in header and "camera fps" in header
    assert "87% 15.8V" in d1 and "FIX_3D 12sat" in d1 and "F10 R10 B10 L7.5 U0.0 D-" in d1
    columns = d2.split()
    assert columns[:4] == ["d2", "active", "?", "?"] and columns[4:6] == ["-", "-"]


def test_a_drone_silent_past_the_threshold_is_stale_and_said_so() -> None:
    now = [0.0]
    table = SwarmTable(clock=lambda: now[0], stale_after_s=2.0)
    table.update("swarm/d1/health", message({"state": "active"}))
    table.update("swarm/d2/health", message({"state": "active"}))
    now[0] = 2.0  # exactly at the threshold: not yet
    assert table.stale() == [] and "STALE" not in table.render()
    table.update("swarm/d2/health", message({"state": "active"}))
    now[0] = 2.1
    assert table.stale() == ["d1"]
    lines = table.render().splitlines()
    assert lines[1].startswith("d1") and "2.1 STALE" in lines[1]
    assert "STALE" not in lines[2]
    assert "STALE (nothing for > 2 s): d1" in lines


def test_each_endpoint_says_connecting_connected_or_silent() -> None:
    now = [0.0]
    a, b, c = "tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447", "tcp/10.0.0.3:7447"
    table = SwarmTable(clock=lambda: now[0], endpoints=[a, b, c])
    now[0] = 1.0
    table.set_connected(b, True)
    table.set_connected(c, True)
    table.update("swarm/d2/state", message({}), b)
    table.update("swarm/d3/state", message({}), c)
    now[0] = 6.0
    table.update("swarm/d2/state", message({}), b)
    table.set_connected(c, False)
    links = table.render().split("links:\n")[1].splitlines()
    assert links[0].split() == [a, "connecting", "for", "6.0", "s;", "nothing", "heard"]
    assert f"{b}  connected for 5.0 s; d2: last message 0.0 s ago" in links[1]
    assert (
        f"{c}  DISCONNECTED 0.0 s ago, reconnecting; d3: last message 5.0 s ago SILENT"
        in (links[2])
    )


def test_monitor_names_the_endpoint_never_heard_and_marks_a_drone_that_went_silent() -> None:
    live, dead = free_port(), free_port()
    config = TelemetryConfig(drone_id="d9", listen_endpoints=(f"tcp/127.0.0.1:{live}",))
    out = io.StringIO()
    done = threading.Event()

    def monitor() -> None:
        try:
            endpoints = [f"tcp/127.0.0.1:{live}", f"tcp/127.0.0.1:{dead}"]
            run_monitor(endpoints, interval_s=0.25, duration_s=8.0, out=out, stale_after_s=1.0)
        finally:
            done.set()

    async def publish() -> None:
        async with TelemetryPublisher(config) as publisher:
            publisher.update_health({"state": "active", "reason": ""})
            thread = threading.Thread(target=monitor)
            thread.start()
            # Publish until the monitor has shown the drone, then go silent (a drone that died).
            while not done.is_set() and "\nd9 " not in out.getvalue():
                await publisher.publish_once()
                await asyncio.sleep(0.05)
            assert not done.is_set(), "the monitor never heard the drone in 8 s"
            await asyncio.to_thread(thread.join)

    asyncio.run(publish())
    last = out.getvalue().strip().split("\n\n")[-1]
    assert "STALE (nothing for > 1 s): d9" in last
    assert f"tcp/127.0.0.1:{dead}  connecting for" in last
    assert f"tcp/127.0.0.1:{dead}" in last.split("nothing heard")[0].splitlines()[-1]
    assert f"tcp/127.0.0.1:{live}  connected for" in last and "SILENT" in last
