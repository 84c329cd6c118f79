"""What the running daemon tells the operator: camera link health, battery and GPS, and telemetry
that cannot open at start-up. Real parts: six pty cameras, the pymavlink PX4 emulator through
MAVSDK on loopback UDP, a TorchScript policy, Zenoh on loopback, the MCAP log read back.

Waits are liveness bounds (`GUARD_S`) that return as soon as their condition holds.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from companion import cli
from companion.camera.layout import FACE_NAMES
from companion.camera.protocol import MAGIC
from companion.flight_log import TOPIC_CAMERAS, TOPIC_HEALTH, LogReader, summarize_log
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator

from .daemon_rig import daemon_log, free_tcp_port

GUARD_S = 30.0


def garbage(blocks: int) -> bytes:
    """`blocks` fake message starts (MAGIC + 40 bytes without 0xA5): exactly one bad header each."""
    body = np.random.default_rng(5).integers(0, 256, (blocks, 40), dtype=np.uint8)
    body[body == 0xA5] = 0
    return b"".join(MAGIC + row.tobytes() for row in body)


class Monitor:
    """A ground monitor: a real Zenoh session on loopback, keeping the latest message per key."""

    def __init__(self, port: int) -> None:
        self._lock = threading.Lock()
        self._latest: dict[str, dict[str, Any]] = {}
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps("peer"))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        self.session = zenoh.open(conf)
        self.subscriber = self.session.declare_subscriber("swarm/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self._latest[str(sample.key_expr)] = json.loads(sample.payload.to_bytes())

    def data(self, kind: str) -> dict[str, Any] | None:
        with self._lock:
            message = self._latest.get(f"swarm/d1/{kind}")
        return None if message is None else message["data"]

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


async def until(condition: Callable[[], bool], what: str) -> None:
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > GUARD_S:
            pytest.fail(f"timed out after {GUARD_S} s waiting for {what}")
        await asyncio.sleep(0.02)


def test_camera_errors_battery_and_gps_reach_the_ground_and_the_log(
    tmp_path: Path,
    cameras: CameraEmulator,
    px4: AutopilotEmulator,
    make_policy_file: Any,
    make_drone_daemon: Any,
) -> None:
    port = free_tcp_port()
    listen = {"listen_endpoints": [f"tcp/127.0.0.1:{port}"]}
    model = make_policy_file("constant")
    daemon = make_drone_daemon(cameras, px4, model, tmp_path, listen, {"failsafe_after_s": 5.0})
    monitor = Monitor(port)
    junk = garbage(12)

    def camera(face: str) -> dict[str, Any]:
        health = monitor.data("health") or {}
        return dict(health.get("cameras", {}).get(face, {}))

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            # Every face streams at ~10 Hz, measured by the daemon over the last 2 s.
            await until(lambda: all(camera(f).get("fps", 0) >= 5.0 for f in FACE_NAMES), "fps")
            assert all(camera(f)["fps"] <= 11.0 for f in FACE_NAMES)
            clean = camera("left")
            assert clean["bad_headers"] == 0 and clean["last_error"] == ""
            # A flaky cable: garbage on the left camera, damaged frames on the right one.
            assert cameras.inject("left", junk)
            cameras.corrupt_frames("right", 3)
            await until(lambda: "bad header" in camera("left").get("last_error", ""), "left")
            await until(lambda: camera("right").get("bad_payloads", 0) >= 3, "right payloads")
            left = camera("left")
            assert left["bad_headers"] == 12
            assert left["dropped_bytes"] >= len(junk)
            assert set(left) >= {"fps", "bad_headers", "bad_payloads", "dropped_bytes",
                                 "seq_gaps", "last_error"}  # fmt: skip
            assert "bad payload" in camera("right")["last_error"]
            # Battery and GPS fix, from PX4's SYS_STATUS and GPS_RAW_INT through MAVSDK.
            await until(lambda: (monitor.data("state") or {}).get("gps", {}).get("satellites")
                        is not None, "gps in the state")  # fmt: skip
            state = monitor.data("state") or {}
            assert state["battery"] == {"remaining_pct": 80.0, "voltage_v": 16.2}
            assert state["gps"] == {"fix_type": "fix_3d", "satellites": 12}
            # The flight log has written the final counters before the daemon stops.
            await asyncio.sleep(0.6)  # one more camera report (every 0.5 s) after the counts
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    try:
        asyncio.run(body())
    finally:
        monitor.close()

    log = daemon_log(tmp_path)
    records = [m.json() for m in LogReader(log).messages() if m.topic == TOPIC_CAMERAS]
    assert records and records[-1]["left"]["bad_headers"] == 12
    assert records[-1]["right"]["bad_payloads"] >= 3
    assert len(records) < 200  # on change (checked every 0.5 s) or every 5 s: bounded
    summary = summarize_log(log)
    assert summary["cameras"]["left"]["bad_headers"] == 12
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main(["log", "summary", str(log)]) == 0
    text = out.getvalue()
    assert "cameras (final counters):" in text
    left_line = next(line for line in text.splitlines() if line.strip().startswith("left "))
    assert "bad headers 12" in left_line and "last error: bad header x" in left_line


def test_telemetry_that_cannot_listen_does_not_ground_the_drone(
    tmp_path: Path,
    cameras: CameraEmulator,
    px4: AutopilotEmulator,
    make_policy_file: Any,
    make_drone_daemon: Any,
) -> None:
    port = free_tcp_port()
    holder = socket.socket()  # another program holds the telemetry port at start-up
    holder.bind(("127.0.0.1", port))
    holder.listen()
    telemetry = {
        "listen_endpoints": [f"tcp/127.0.0.1:{port}"],
        "retry_min_s": 0.2,
        "retry_max_s": 0.5,
    }
    model = make_policy_file("constant")
    daemon = make_drone_daemon(cameras, px4, model, tmp_path, telemetry, {"failsafe_after_s": 5.0})

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        monitor: Monitor | None = None
        try:
            await until(lambda: daemon.ticks >= 30, "the control loop to tick")
            assert not run.done() and not daemon.outputs.telemetry.is_open
            await until(lambda: daemon.outputs.recorder.stats().written > 0, "the flight log")
            holder.close()  # the port is free now (as when the Wi-Fi comes up)
            monitor = Monitor(port)
            await until(lambda: monitor is not None and monitor.data("health") is not None,
                        "telemetry once the port is free")  # fmt: skip
            assert not run.done()
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)
            if monitor is not None:
                monitor.close()

    try:
        asyncio.run(body())
    finally:
        holder.close()
    events = [
        m.json() for m in LogReader(daemon_log(tmp_path)).messages() if m.topic == TOPIC_HEALTH
    ]
    names = [event["event"] for event in events]
    assert names.count("telemetry unavailable") == 1
    assert names.count("telemetry up") == 1
    assert names.index("telemetry unavailable") < names.index("telemetry up")
    unavailable = events[names.index("telemetry unavailable")]
    assert unavailable["level"] == "warning" and "Address already in use" in str(
        unavailable["detail"]
    )
