"""What the daemon's end-to-end tests share: the east-facing PX4 emulator, the drone's config
document, the constant policy's expected setpoints, a Zenoh monitor and liveness waits.

Times asserted are the issue's bars (hover within 0.5 s), measured between the trigger and the
daemon's own HOVER transition (the daemon's clock is the test's `time.monotonic`), so a loaded
machine that delays the test's polling cannot fail them. Every other wait is a liveness bound
(`GUARD_S`) that returns as soon as its condition holds.
"""

from __future__ import annotations

import asyncio
import json
import math
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
import zenoh

from companion.groundstation import SwarmTable, monitor_zenoh_config
from companion.policy import Policy
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port

from .conftest import drone_document

REPO = Path(__file__).resolve().parents[2]
BODY_CMD_FLU = (1.0, 0.0, 0.25)  # the constant policy: forward 1 m/s, up 0.25 m/s
START_YAW_NED = math.pi / 2  # the vehicle faces east
# Facing east, forward-and-up in FLU is east-and-up: NED (0, 1, -0.25), yaw pi/2 (east).
EXPECTED_NED = (0.0, 1.0, -0.25)
DO_SET_MODE = 176
GUARD_S = 20.0  # liveness bound for "eventually" waits; normally met within a few ticks


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def hovering_east(**emulator: Any) -> AutopilotEmulator:
    """The PX4 emulator armed and hovering at 5 m in POSCTL, facing east, heartbeats at 20 Hz
    (a context manager; `emulator`: more `EmulatorConfig` fields)."""
    config = EmulatorConfig.hovering(
        free_udp_port(), 5.0, heartbeat_rate_hz=20.0, start_yaw_rad=START_YAW_NED, **emulator
    )
    return AutopilotEmulator(config)


def document(
    tmp_path: Path,
    cameras: CameraEmulator,
    px4: AutopilotEmulator,
    model: Path,
    telemetry_port: int,
    **daemon: Any,
) -> dict[str, Any]:
    """The TOML document of a test drone wired to the emulators: telemetry on `telemetry_port`,
    engaging by itself, no control socket, failsafe after 5 s of hover (unless `daemon` says)."""
    return drone_document(
        cameras,
        px4,
        model,
        tmp_path,
        {"listen_endpoints": [f"tcp/127.0.0.1:{telemetry_port}"]},
        {"failsafe_after_s": 5.0, "engage": "auto", "control_socket": "", **daemon},
    )


class ModelHook:
    """Wraps a real policy's model call: "normal", "nan" (NaN outputs) or "hang" (blocks)."""

    def __init__(self, policy: Policy) -> None:
        self.mode = "normal"
        self.release = threading.Event()
        original = policy._run_model

        def run(batch: torch.Tensor) -> torch.Tensor:
            if self.mode == "hang":
                self.release.wait(10.0)
            out = original(batch)
            return torch.full_like(out, math.nan) if self.mode == "nan" else out

        policy._run_model = run  # type: ignore[method-assign]


async def until(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll every 10 ms until `condition` holds (fails after `timeout_s`: a hang guard)."""
    start = time.monotonic()
    while not condition():
        if time.monotonic() - start > timeout_s:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        await asyncio.sleep(0.01)


def last_setpoint(px4: AutopilotEmulator) -> Any:
    return px4.setpoints()[-1]


def quiet(px4: AutopilotEmulator, seconds: float) -> Callable[[], bool]:
    """A condition: no new setpoint reached the emulator for `seconds` (test clock)."""
    last = {"count": -1, "since": time.monotonic()}

    def check() -> bool:
        count = len(px4.setpoints())
        if count != last["count"]:
            last.update(count=count, since=time.monotonic())
        return time.monotonic() - last["since"] >= seconds

    return check


def is_zero(setpoint: Any) -> bool:
    return max(abs(setpoint.vx_mps), abs(setpoint.vy_mps), abs(setpoint.vz_mps)) < 1e-6


def flying_expected(setpoint: Any) -> bool:
    """The constant policy's command in NED, to within what the vehicle's tilt changes.

    The body command is rotated with the attitude at capture time, and the emulated vehicle
    tilts while it accelerates (a few degrees): that moves a 1 m/s forward command by a few
    cm/s horizontally and up to ~0.1 m/s vertically. A frame or sign error moves it by >= 0.5.
    """
    north, east, down = EXPECTED_NED
    return (
        abs(setpoint.vx_mps - north) < 0.06
        and abs(setpoint.vy_mps - east) < 0.06
        and abs(setpoint.vz_mps - down) < 0.12
        and abs(setpoint.yaw_rad - math.pi / 2) < 0.05
    )


class Subscriber:
    """A ground monitor: a real Zenoh session on loopback subscribed to swarm/**."""

    def __init__(self, port: int) -> None:
        self.table = SwarmTable()
        self.messages: list[tuple[str, dict[str, Any]]] = []
        self._lock = threading.Lock()
        self.session = zenoh.open(monitor_zenoh_config([f"tcp/127.0.0.1:{port}"]))
        self.subscriber = self.session.declare_subscriber("swarm/**", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        self.table.update(key, payload)
        with self._lock:
            self.messages.append((key, json.loads(payload)))

    def latest(self, key: str) -> dict[str, Any] | None:
        with self._lock:
            found = [m for k, m in self.messages if k == key]
        return found[-1] if found else None

    def close(self) -> None:
        self.subscriber.undeclare()
        self.session.close()


def daemon_log(tmp_path: Path) -> Path:
    (log,) = sorted((tmp_path / "flights").glob("flight_d1_*.mcap"))
    return log
