"""When the daemon's control loop ticks (`[daemon] tick_on_frames`).

- `frame_locked`: a tick as soon as all six cameras delivered a new frame, so each decision acts
  on the newest image, and at the latest one period after the previous tick (`rate_hz` is the
  floor: the setpoint stream never pauses longer than a period).
- `fixed_rate`: ticks on the grid `t0 + k * period`; an overrun skips the missed deadlines
  (reported to `on_skip`) and stays on the grid, never drifting.

A tick is `tick(now_s, late_s)`: its start time and how late it is against its deadline.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Awaitable, Callable

from companion.camera.fresh_set import FreshSetWaiter
from companion.camera.rig import Rig

Tick = Callable[[float, float], Awaitable[None]]


async def frame_locked(
    tick: Tick, rig: Rig, stop: asyncio.Event, clock: Callable[[], float], period_s: float
) -> None:
    """Tick on each fresh six-frame set, with one period as the floor, until `stop`."""
    waiter = FreshSetWaiter(rig, stop, clock)
    deadline_s = clock()
    while not stop.is_set():
        now_s = clock()
        seen = rig.latest_seqs()
        await tick(now_s, max(0.0, now_s - deadline_s))
        deadline_s = now_s + period_s  # the floor: never a period without a tick
        await asyncio.sleep(0)  # the links and the autopilot run between ticks, always
        await waiter.wait(seen, deadline_s)


async def fixed_rate(
    tick: Tick,
    stop: asyncio.Event,
    clock: Callable[[], float],
    period_s: float,
    on_skip: Callable[[int], None],
) -> None:
    """Tick on the grid `t0 + k * period` (late ticks skipped, never drifting) until `stop`."""
    next_s = clock()
    while not stop.is_set():
        now_s = clock()
        await tick(now_s, now_s - next_s)
        next_s += period_s
        behind_s = clock() - next_s
        if behind_s >= 0.0:  # overran: skip the missed deadlines, stay on the grid
            missed = math.floor(behind_s / period_s) + 1
            next_s += missed * period_s
            on_skip(missed)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), max(0.0, next_s - clock()))
