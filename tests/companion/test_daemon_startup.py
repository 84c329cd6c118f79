"""The daemon's start-up with real parts (pty cameras, the PX4 emulator over MAVSDK, TorchScript):
what it refuses to fly, and how it stops before anything flew: a vehicle on the ground, an
autopilot that never answers, a camera set the rig refuses, a model with the wrong hash."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from companion.autopilot import MavsdkAutopilot
from companion.config import CompanionConfig, config_from_dict
from companion.daemon import Daemon
from companion.errors import ModelError
from companion.flight_log import LogReader
from companion.health import HealthState
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
from sim_harness.hil.px4_logic import Px4Mode

from .daemon_rig import (
    BODY_CMD_FLU,
    DO_SET_MODE,
    GUARD_S,
    daemon_log,
    document,
    free_tcp_port,
    hovering_east,
    until,
)


@pytest.fixture
def px4() -> Iterator[AutopilotEmulator]:
    """PX4 armed and hovering at 5 m in POSCTL, facing east; heartbeats at 20 Hz."""
    with hovering_east() as emulator:
        yield emulator


def test_a_vehicle_on_the_ground_is_never_engaged(
    tmp_path: Path, cameras: CameraEmulator, make_policy_file: Any
) -> None:
    """Healthy pipeline (READY), but disarmed on the ground: no OFFBOARD request, no setpoint."""
    config = EmulatorConfig(free_udp_port(), heartbeat_rate_hz=20.0)
    with AutopilotEmulator(config) as grounded:
        doc = document(
            tmp_path, cameras, grounded, make_policy_file("constant", BODY_CMD_FLU), free_tcp_port()
        )
        daemon = Daemon(config_from_dict(doc), handle_signals=False)

        async def body() -> None:
            run = asyncio.create_task(daemon.run())
            try:
                await until(lambda: daemon.ready, GUARD_S, "READY")
                await asyncio.sleep(1.0)
                assert daemon.health.state is HealthState.STARTING
                assert daemon.health.reason == (
                    "pipeline healthy, not engaged: the vehicle is not armed and in the air"
                )
            finally:
                daemon.request_stop("test over")
                await asyncio.wait_for(run, 15.0)

        asyncio.run(body())
        assert not [c for c in grounded.commands() if c.command == DO_SET_MODE]
        assert not grounded.setpoints() and grounded.mode is Px4Mode.HOLD


def test_a_stop_while_searching_for_the_autopilot_ends_promptly(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    doc = document(tmp_path, cameras, px4, make_policy_file("constant"), free_tcp_port())
    doc["autopilot"].update(url=f"udpin://127.0.0.1:{free_udp_port()}", discovery_timeout_s=3.0)
    config = config_from_dict(doc)
    searching = threading.Event()

    class Searching(MavsdkAutopilot):
        """The real adapter; says when its discovery (a heartbeat that never comes) began."""

        async def connect(self) -> None:
            searching.set()
            await super().connect()

    daemon = Daemon(config, autopilot=Searching(config.autopilot), handle_signals=False)

    async def body() -> float:
        run = asyncio.create_task(daemon.run())
        await until(searching.is_set, GUARD_S, "the autopilot search")  # not a fixed sleep
        await asyncio.sleep(0.2)  # MAVSDK is now waiting for a heartbeat that never comes
        assert not run.done()
        start = time.monotonic()
        daemon.request_stop("test over")
        await asyncio.wait_for(run, GUARD_S)
        return time.monotonic() - start

    took_s = asyncio.run(body())
    # The adapter waits at most close_timeout_s (2.5 s) for MAVSDK; the rest of the shutdown
    # takes ~0.1 s, so 1.4 s of the bound is margin for a loaded machine.
    assert took_s < 4.0
    assert daemon.health.state is HealthState.STOPPING
    events = [m.json()["event"] for m in LogReader(daemon_log(tmp_path)).messages()]
    assert events[-1] == "stopped"


def test_a_set_the_rig_refuses_does_not_spin_the_loop(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    """Found by the HIL swarm: every face streaming but the set refused (here a wrong camera on
    one face; at start-up, skew) must not wake the frame-locked loop again and again, starving
    the links and the autopilot. The loop keeps its rate and the event loop stays responsive."""
    doc = document(tmp_path, cameras, px4, make_policy_file("constant"), free_tcp_port())
    doc["cameras"]["faces"]["up"]["camera_id"] = "ab" * 12  # not the camera on that port
    daemon = Daemon(config_from_dict(doc), handle_signals=False, clock=time.monotonic)

    async def body() -> tuple[int, int, float]:
        run = asyncio.create_task(daemon.run())
        await until(lambda: daemon.ticks > 0, GUARD_S, "the first tick")
        beats = 0
        start, ticks0 = time.monotonic(), daemon.ticks
        while time.monotonic() - start < 1.5:
            await asyncio.sleep(0.01)  # another task on the daemon's loop: must keep running
            beats += 1
        ticks = daemon.ticks - ticks0
        took = time.monotonic() - start
        daemon.request_stop("test over")
        await asyncio.wait_for(run, GUARD_S)
        return ticks, beats, took

    ticks, beats, took_s = asyncio.run(body())
    assert ticks <= 2 * 10 * took_s + 5  # ~10 Hz floor ticks, never a spin (thousands)
    assert ticks >= 0.5 * 10 * took_s  # the floor still ticks (hover/starting decisions)
    assert beats >= 20  # the loop yielded: 1.5 s of 10 ms sleeps is ~150 on a quiet machine
    assert daemon.health.state is HealthState.STOPPING and not px4.setpoints()


def test_a_model_with_the_wrong_hash_is_refused_before_anything_flies(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_policy_file: Any
) -> None:
    doc = document(tmp_path, cameras, px4, make_policy_file("constant"), free_tcp_port())
    doc["policy"]["sha256"] = "0" * 64
    config: CompanionConfig = config_from_dict(doc)
    with pytest.raises(ModelError, match="refused"):
        asyncio.run(Daemon(config, handle_signals=False).run())
    assert not px4.setpoints()
    assert px4.mode is Px4Mode.POSCTL
