"""What the daemon asks of the autopilot, with the retries and bounds the control loop needs.

`Commander` wraps an `Autopilot`:

- `send()`: one velocity setpoint; errors are counted and logged (rate-limited), never raised
  (an `OffboardLostError` shows up as `offboard_state` LOST on the next tick);
- `engage()` / `failsafe()`: start the OFFBOARD request or the failsafe (Hold/Land) in the
  background, so the loop keeps ticking during their seconds-long exchanges; a refusal is retried
  after `engage_retry_s` / `failsafe_retry_s`;
- `stream()`: "operator" engagement: get READY (in the background, like `engage`), then send
  one setpoint per call for the pilot's switch to OFFBOARD;
- `disengage()`: the operator's `companion disengage`: zero velocity, then Hold;
- `release()`: stop commanding after the pilot took over (no mode change);
- `safe_stop()`: shutdown: wait for a running request, zero velocity, offboard stop (Hold).

Every awaited request is bounded by `timeout_s`. `events` (a callable taking event, level,
detail) receives what belongs in the flight log's health topic.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from companion.autopilot_types import Autopilot, OffboardState
from companion.control import ControlOutput
from companion.errors import AutopilotError, CompanionError, OffboardLostError

log = logging.getLogger(__name__)
EventSink = Callable[[str, str, Any], object]


class Commander:
    """The daemon's side of the autopilot: setpoints, background requests, safe stop."""

    def __init__(
        self,
        autopilot: Autopilot,
        *,
        clock: Callable[[], float],
        events: EventSink,
        timeout_s: float,
        engage_retry_s: float,
        failsafe_retry_s: float = 1.0,
        failsafe_action: str = "hold",
    ) -> None:
        self.autopilot = autopilot
        self._clock = clock
        self._events = events
        self._timeout_s = timeout_s
        self._engage_retry_s = engage_retry_s
        self._failsafe_retry_s = failsafe_retry_s
        self._failsafe_action = failsafe_action
        self._engage_task: asyncio.Task[None] | None = None
        self._next_engage_s = -math.inf
        self._failsafe_task: asyncio.Task[None] | None = None
        self._next_failsafe_s = -math.inf
        self.failsafe_done = False
        self.setpoint_errors = 0

    def rearm(self) -> None:
        """A new engagement may follow (operator/ground): the failsafe may run again."""
        self.failsafe_done = False

    @property
    def offboard_state(self) -> OffboardState:
        return self.autopilot.offboard_state

    @property
    def idle(self) -> bool:
        """No OFFBOARD, stream or failsafe request running."""
        return self._engage_task is None and self._failsafe_task is None

    def may_engage(self, now_s: float) -> bool:
        """No OFFBOARD or failsafe request running and the retry delay is over."""
        return self.idle and now_s >= self._next_engage_s

    async def send(self, command: ControlOutput) -> bool:
        """Send the command's NED velocity and yaw; True if the autopilot took it."""
        try:
            await self.autopilot.set_velocity_ned(command.vel_ned, float(command.yaw_ned_rad))
        except OffboardLostError:
            return False  # the next tick sees LOST and releases
        except AutopilotError as exc:
            self.setpoint_errors += 1
            if self.setpoint_errors == 1 or self.setpoint_errors % 100 == 0:
                log.error("setpoint not sent (%d so far): %s", self.setpoint_errors, exc)
            return False
        return True

    async def stream(self, command: ControlOutput) -> bool:
        """Operator engagement: READY first (in the background), then one setpoint per call."""
        state = self.autopilot.offboard_state
        if state is OffboardState.INACTIVE and self._engage_task is None:
            self._engage_task = asyncio.create_task(self._prepare(), name="prepare-offboard")
        if state is not OffboardState.READY:
            return False
        try:
            await self.autopilot.stream_velocity_ned(command.vel_ned, float(command.yaw_ned_rad))
        except AutopilotError as exc:
            self.setpoint_errors += 1
            if self.setpoint_errors == 1 or self.setpoint_errors % 100 == 0:
                log.error("stream setpoint not sent (%d so far): %s", self.setpoint_errors, exc)
            return False
        return True

    async def _prepare(self) -> None:
        try:
            await self.autopilot.prepare_offboard()
            self._events("ready", "info", "streaming hover setpoints: switch to OFFBOARD to engage")
        except AutopilotError as exc:
            self._next_engage_s = self._clock() + self._engage_retry_s
            log.warning("not ready for OFFBOARD (retry in %g s): %s", self._engage_retry_s, exc)
            self._events("not ready", "warning", str(exc))
        finally:
            self._engage_task = None

    async def disengage(self, hover: ControlOutput) -> bool:
        """Stop commanding at the operator's request: zero velocity, then Hold. True if the
        vehicle was being commanded."""
        if self.autopilot.offboard_state is not OffboardState.ACTIVE:
            return False
        await self.safe_stop(hover)
        return True

    def engage(self, yaw_ned_rad: float | None) -> None:
        """Start requesting OFFBOARD in the background (zero setpoint at `yaw_ned_rad` first)."""
        if self._engage_task is None:
            self._engage_task = asyncio.create_task(self._engage(yaw_ned_rad), name="engage")

    async def _engage(self, yaw_ned_rad: float | None) -> None:
        self._events("engage", "info", "requesting OFFBOARD")
        try:
            await self.autopilot.start_offboard(yaw_ned_rad)
            log.info("engaged: vehicle in OFFBOARD")
            self._events("engaged", "info", "vehicle in OFFBOARD")
        except AutopilotError as exc:
            self._next_engage_s = self._clock() + self._engage_retry_s
            log.warning("engage failed (retry in %g s): %s", self._engage_retry_s, exc)
            self._events("engage failed", "warning", str(exc))
        finally:
            self._engage_task = None

    def failsafe(self) -> None:
        """Start the autopilot failsafe in the background, unless done, running or backing off."""
        busy = self._failsafe_task is not None or self._clock() < self._next_failsafe_s
        # A retry only while still commanding: once the pilot has the vehicle, leave it alone.
        commanding = self.autopilot.offboard_state is OffboardState.ACTIVE
        if not self.failsafe_done and not busy and commanding:
            self._failsafe_task = asyncio.create_task(self._failsafe(), name="failsafe")

    async def _failsafe(self) -> None:
        try:
            await self.autopilot.failsafe()
            self.failsafe_done = True
            self._events("failsafe", "error", f"autopilot switched to {self._failsafe_action}")
        except AutopilotError as exc:
            self._next_failsafe_s = self._clock() + self._failsafe_retry_s
            log.error("failsafe (%s) failed, retrying: %s", self._failsafe_action, exc)
            self._events("failsafe failed", "error", str(exc))
        finally:
            self._failsafe_task = None

    async def release(self) -> None:
        """Stop commanding without a mode change (the pilot or PX4 has the vehicle)."""
        await self.guarded("release", self.autopilot.stop_offboard())

    async def safe_stop(self, hover: ControlOutput) -> None:
        """Shutdown: let a running request end, then, if commanding: `hover`, offboard stop."""
        for task in (self._engage_task, self._failsafe_task):
            if task is not None:
                await asyncio.wait({task}, timeout=self._timeout_s)
        if self.autopilot.offboard_state is not OffboardState.ACTIVE:
            return
        vel, yaw = hover.vel_ned, float(hover.yaw_ned_rad)
        await self.guarded("zero setpoint", self.autopilot.set_velocity_ned(vel, yaw))
        if await self.guarded("offboard stop (Hold)", self.autopilot.stop_offboard()):
            self._events("offboard stopped", "info", "vehicle switched to HOLD")

    async def guarded(self, what: str, work: Awaitable[None] | Coroutine[Any, Any, None]) -> bool:
        """Await an autopilot request bounded by `timeout_s`; log instead of raising."""
        try:
            async with asyncio.timeout(self._timeout_s):
                await work
        except (CompanionError, TimeoutError) as exc:
            log.error("%s failed: %s", what, exc or "timed out")
            return False
        return True
