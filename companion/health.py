"""The daemon's health state machine: pure logic, one `step()` per control tick, time passed in.

States and what the daemon commands in each:

| state     | meaning                                              | command                    |
|-----------|------------------------------------------------------|----------------------------|
| STARTING  | not commanding yet; waits for a healthy pipeline     | none (ENGAGE or STREAM)    |
| ACTIVE    | commanding, pipeline fresh and valid                 | the control law's velocity |
| HOVER     | commanding, pipeline stale or output invalid         | zero velocity, yaw held    |
| FAILSAFE  | hovered longer than `failsafe_after_s`               | Hold/Land once, then none  |
| PILOT     | the vehicle left OFFBOARD (pilot or PX4 failsafe)    | none: never fight the pilot|
| STOPPING  | SIGTERM/SIGINT                                       | zero velocity, then Hold   |

The pipeline is *healthy* when the latest output is valid (`output_ok`: policy output finite and
bounded, control inputs valid) and fresh: the image it was computed from (its oldest tile's receive
time, `output_time_s`) is at most `stale_after_s` old. Anything else is a hover: no fresh rig
image, no fresh inference (a stalled model), NaN output. A hover lasting longer than
`failsafe_after_s` escalates to FAILSAFE. STOPPING is final. FAILSAFE and PILOT are final unless
`reengage_allowed` ("operator" and "ground" engagement: an operator engages again, the daemon
never does on its own): then, once the vehicle is out of OFFBOARD, back to STARTING.

Engagement from STARTING, once healthy: ENGAGE (the daemon requests OFFBOARD: "auto", or "ground"
after `companion engage`) or STREAM (stream hover setpoints so that the pilot or the ground
station can switch to OFFBOARD: "operator"); `waiting` says why neither is allowed yet.

`step()` returns the state and one `Action`; the daemon carries the action out. Times are seconds
of the daemon's monotonic clock, passed in with every input (no clock is read here).
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass

from companion.autopilot_types import OffboardState
from companion.validation import require_positive


class HealthState(enum.Enum):
    STARTING = "starting"
    ACTIVE = "active"
    HOVER = "hover"
    FAILSAFE = "failsafe"
    PILOT = "pilot"
    STOPPING = "stopping"

    @property
    def final(self) -> bool:
        """True for states the machine never leaves."""
        return self in (HealthState.FAILSAFE, HealthState.PILOT, HealthState.STOPPING)


class Action(enum.Enum):
    WAIT = "wait"  # send nothing
    ENGAGE = "engage"  # request OFFBOARD (initial zero setpoint first)
    STREAM = "stream"  # stream hover setpoints; the pilot's switch to OFFBOARD engages
    FLY = "fly"  # send the control law's setpoint
    HOVER = "hover"  # send zero velocity, yaw held
    FAILSAFE = "failsafe"  # switch to the autopilot's failsafe (Hold/Land), once
    RELEASE = "release"  # stop commanding without a mode change (the pilot has control), once
    STOP = "stop"  # shutdown: zero velocity then offboard stop (Hold), once


@dataclass(frozen=True)
class HealthConfig:
    """Freshness limit and failsafe delay, in seconds."""

    stale_after_s: float = 0.3
    failsafe_after_s: float = 3.0

    def __post_init__(self) -> None:
        require_positive("daemon.stale_hover_after_s", self.stale_after_s)
        require_positive("daemon.failsafe_after_s", self.failsafe_after_s)


@dataclass(frozen=True)
class HealthInputs:
    """What the daemon observed this tick.

    `output_time_s`: receive time of the oldest tile of the image behind the latest *valid*
    output (None: none yet). `output_ok`: the latest output (this tick's) is valid;
    `problem`: why the pipeline is not producing, for the reason text ("" if nothing to say).
    `offboard`: the autopilot adapter's view. `engage_allowed`: the daemon may request OFFBOARD
    now (config, armed, no request in flight, retry delay over); `stream_allowed`: it may stream
    setpoints for the pilot's switch; `waiting`: why neither (for the reason text).
    `reengage_allowed`: FAILSAFE and PILOT return to STARTING once out of OFFBOARD.
    """

    now_s: float
    output_time_s: float | None
    output_ok: bool
    problem: str = ""
    offboard: OffboardState = OffboardState.INACTIVE
    engage_allowed: bool = False
    stop_requested: bool = False
    stream_allowed: bool = False
    waiting: str = ""
    reengage_allowed: bool = False


@dataclass(frozen=True)
class Transition:
    """One state change: when, from, to and why."""

    t_s: float
    source: HealthState
    target: HealthState
    reason: str


@dataclass(frozen=True)
class HealthDecision:
    """The state after this tick, what to do, and why."""

    state: HealthState
    action: Action
    reason: str  # why the state is what it is ("" when ACTIVE)
    healthy: bool  # the pipeline is fresh and valid
    transition: Transition | None  # the change made by this tick, if any


class HealthMonitor:
    """The state machine. `step(inputs)` once per tick; `state`, `since_s` and `history` to read."""

    def __init__(self, config: HealthConfig, start_s: float = 0.0, history_size: int = 256) -> None:
        self.config = config
        self._state = HealthState.STARTING
        self._since_s = start_s
        self._reason = "waiting for a healthy pipeline"
        self._hover_since_s: float | None = None
        self.history: deque[Transition] = deque(maxlen=history_size)  # latest transitions

    @property
    def state(self) -> HealthState:
        return self._state

    @property
    def since_s(self) -> float:
        """When the current state was entered."""
        return self._since_s

    @property
    def reason(self) -> str:
        return self._reason

    @property
    def hover_since_s(self) -> float | None:
        """When the current hover began (None unless HOVER)."""
        return self._hover_since_s

    def healthy(self, inputs: HealthInputs) -> bool:
        """Fresh and valid: the latest output is ok and its image is young enough."""
        if not inputs.output_ok or inputs.output_time_s is None:
            return False
        return inputs.now_s - inputs.output_time_s <= self.config.stale_after_s

    def _why_not(self, inputs: HealthInputs) -> str:
        if inputs.problem:
            return inputs.problem
        if inputs.output_time_s is None:
            return "no valid output yet"
        age_s = inputs.now_s - inputs.output_time_s
        return f"output image {age_s:.3f} s old > {self.config.stale_after_s:.3f} s"

    def step(self, inputs: HealthInputs) -> HealthDecision:
        """Advance by one tick and say what to do."""
        healthy = self.healthy(inputs)
        state = self._state
        now = inputs.now_s
        if inputs.stop_requested:
            if state is HealthState.STOPPING:
                return self._stay(Action.WAIT, healthy)
            return self._go(now, HealthState.STOPPING, Action.STOP, "stop requested", healthy)
        ended = state in (HealthState.FAILSAFE, HealthState.PILOT)
        if ended and inputs.reengage_allowed and inputs.offboard is not OffboardState.ACTIVE:
            why = "waiting for an operator to engage again"
            return self._go(now, HealthState.STARTING, Action.WAIT, why, healthy)
        if state.final:
            return self._stay(Action.WAIT, healthy)
        commanding = state in (HealthState.ACTIVE, HealthState.HOVER)
        if commanding and inputs.offboard is not OffboardState.ACTIVE:
            why = (
                "the vehicle left OFFBOARD (pilot or PX4 failsafe): not commanding"
                if inputs.offboard is OffboardState.LOST
                else "offboard no longer active: not commanding"
            )
            return self._go(now, HealthState.PILOT, Action.RELEASE, why, healthy)
        if state is HealthState.STARTING:
            if inputs.offboard is OffboardState.ACTIVE:
                return self._fly_or_hover(inputs, healthy)
            if healthy and inputs.engage_allowed:
                return self._stay(Action.ENGAGE, healthy, "engaging: requesting OFFBOARD")
            if healthy and inputs.stream_allowed:
                why = "ready: streaming hover setpoints; the pilot's switch to OFFBOARD engages"
                return self._stay(Action.STREAM, healthy, why)
            if not healthy:
                reason = self._why_not(inputs)
            else:
                waiting = f": {inputs.waiting}" if inputs.waiting else ""
                reason = f"pipeline healthy, not engaged{waiting}"
            return self._stay(Action.WAIT, healthy, reason)
        if state is HealthState.HOVER and not healthy:
            assert self._hover_since_s is not None
            hovered_s = now - self._hover_since_s
            if hovered_s > self.config.failsafe_after_s:
                why = f"hovered {hovered_s:.2f} s > {self.config.failsafe_after_s:g} s: failsafe"
                return self._go(now, HealthState.FAILSAFE, Action.FAILSAFE, why, healthy)
        return self._fly_or_hover(inputs, healthy)

    def _fly_or_hover(self, inputs: HealthInputs, healthy: bool) -> HealthDecision:
        if healthy:
            return self._go(inputs.now_s, HealthState.ACTIVE, Action.FLY, "", healthy)
        return self._go(
            inputs.now_s, HealthState.HOVER, Action.HOVER, self._why_not(inputs), healthy
        )

    def _stay(self, action: Action, healthy: bool, reason: str | None = None) -> HealthDecision:
        if reason is not None:
            self._reason = reason
        return HealthDecision(self._state, action, self._reason, healthy, None)

    def _go(
        self, now_s: float, target: HealthState, action: Action, reason: str, healthy: bool
    ) -> HealthDecision:
        self._reason = reason
        if target is self._state:
            return HealthDecision(target, action, reason, healthy, None)
        transition = Transition(now_s, self._state, target, reason)
        self.history.append(transition)
        self._state = target
        self._since_s = now_s
        self._hover_since_s = now_s if target is HealthState.HOVER else None
        return HealthDecision(target, action, reason, healthy, transition)
