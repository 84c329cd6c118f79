"""The control loop's two schedules with the real daemon (pty cameras, PX4 emulator, MAVSDK)."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from companion.health import HealthState
from sim_harness.hil.px4_logic import Px4Mode

GUARD_S = 20.0


async def until_state(daemon: Any, state: HealthState) -> None:
    start = time.monotonic()
    while daemon.health.state is not state:
        assert time.monotonic() - start < GUARD_S, f"never {state}"
        await asyncio.sleep(0.01)


def test_the_fixed_rate_loop_flies_on_its_grid(engage_rig: Any) -> None:
    """`tick_on_frames = false`: ticks on t0 + k * period; each overrun skips whole periods, so
    ticks plus skipped ticks count the periods elapsed, whatever the machine's load."""
    rig = engage_rig()
    daemon = rig.daemon("", engage="auto", tick_on_frames=False)

    async def body() -> tuple[int, float]:
        run = asyncio.create_task(daemon.run())
        try:
            await until_state(daemon, HealthState.ACTIVE)
            assert rig.px4.mode is Px4Mode.OFFBOARD
            first = daemon.ticks + daemon.skipped_ticks
            started = time.monotonic()
            await asyncio.sleep(2.0)
            return daemon.ticks + daemon.skipped_ticks - first, time.monotonic() - started
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    periods, elapsed_s = asyncio.run(body())
    assert abs(periods - elapsed_s * 10.0) <= 4.0, (periods, elapsed_s)  # a tick in progress
