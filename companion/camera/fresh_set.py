"""Waiting for a fresh six-frame set: what the daemon's tick follows.

The six cameras run free (each its own phase, on the drone as in the HIL harness), so a tick on a
fixed grid acts on an image up to a period old. `FreshSetWaiter.wait` returns as soon as every
face holds a frame newer than the last image used, or at a deadline (the daemon's rate floor), or
on a stop. It is woken by the camera links themselves (`LatestSlot.on_publish`); frame sources
without a slot (tests, other adapters) are looked at every 5 ms instead.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from companion.camera.rig import Rig
from companion.camera.slot import LatestSlot

POLL_S = 0.005  # for sources that cannot signal a new frame


class FreshSetWaiter:
    """Waits on the rig's sources; use from the event loop the links publish on."""

    def __init__(self, rig: Rig, stop: asyncio.Event, clock: Callable[[], float]) -> None:
        self._rig, self._stop, self._clock = rig, stop, clock
        slots = [getattr(src, "slot", src) for src in rig.sources.values()]
        latest = [slot for slot in slots if isinstance(slot, LatestSlot)]
        self._frames: asyncio.Event | None = None
        if len(latest) == len(slots):
            self._frames = asyncio.Event()
            for slot in latest:
                slot.on_publish = self._frames.set

    async def wait(self, seen: tuple[int | None, ...] | None, deadline_s: float) -> None:
        """Until every face has a frame other than the one it had in `seen` (the rig's
        `latest_seqs()` at the previous tick), a stop, or `deadline_s`.

        Comparing with what the previous tick *saw*, not with the last image it *used*, matters:
        a set that fails the rig's rules (skew, a stale or wrong camera) is not used, and must
        not wake the loop again and again.
        """
        while not self._stop.is_set() and not self._rig.has_new_set(seen):
            remaining_s = deadline_s - self._clock()
            if remaining_s <= 0.0:
                return
            waiters = [self._stop.wait()]
            if self._frames is None:
                remaining_s = min(remaining_s, POLL_S)
            else:
                self._frames.clear()
                if self._rig.has_new_set(seen):  # published between the check and the clear
                    return
                waiters.append(self._frames.wait())
            tasks = [asyncio.ensure_future(w) for w in waiters]
            try:
                await asyncio.wait(tasks, timeout=remaining_s, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for task in tasks:
                    task.cancel()
