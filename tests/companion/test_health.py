"""The health state machine, driven by hand with explicit times (no clock, no I/O)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.autopilot_types import OffboardState
from companion.errors import ConfigError
from companion.health import (
    Action,
    HealthConfig,
    HealthInputs,
    HealthMonitor,
    HealthState,
)

ACTIVE, LOST, INACTIVE = OffboardState.ACTIVE, OffboardState.LOST, OffboardState.INACTIVE
CONFIG = HealthConfig(stale_after_s=0.3, failsafe_after_s=3.0)


def fresh(now_s: float, offboard: OffboardState = ACTIVE, **kwargs: object) -> HealthInputs:
    """A valid output computed from an image received 50 ms ago."""
    return HealthInputs(now_s, now_s - 0.05, True, offboard=offboard, **kwargs)  # type: ignore[arg-type]


def flying(start_s: float = 0.0) -> HealthMonitor:
    """A monitor that has engaged and is ACTIVE at `start_s`."""
    monitor = HealthMonitor(CONFIG, start_s=start_s)
    assert monitor.step(fresh(start_s)).state is HealthState.ACTIVE
    return monitor


def test_starting_waits_for_a_healthy_pipeline_then_engages_only_when_allowed() -> None:
    monitor = HealthMonitor(CONFIG)
    waiting = monitor.step(HealthInputs(0.0, None, False, "no fresh rig image: front: missing"))
    assert (waiting.state, waiting.action) == (HealthState.STARTING, Action.WAIT)
    assert waiting.reason == "no fresh rig image: front: missing" and not waiting.healthy

    not_allowed = monitor.step(fresh(1.0, INACTIVE, engage_allowed=False))
    assert (not_allowed.action, not_allowed.healthy) == (Action.WAIT, True)
    assert not_allowed.reason == "pipeline healthy, not engaged"

    engage = monitor.step(fresh(1.1, INACTIVE, engage_allowed=True))
    assert (engage.state, engage.action) == (HealthState.STARTING, Action.ENGAGE)
    # A stale pipeline never engages, whatever the daemon allows.
    stale = HealthInputs(2.0, 1.5, True, offboard=INACTIVE, engage_allowed=True)
    assert monitor.step(stale).action is Action.WAIT


def test_engaged_with_a_fresh_pipeline_flies() -> None:
    monitor = HealthMonitor(CONFIG, start_s=0.0)
    decision = monitor.step(fresh(1.0))
    assert (decision.state, decision.action, decision.reason) == (
        HealthState.ACTIVE,
        Action.FLY,
        "",
    )
    assert decision.transition is not None
    assert decision.transition.source is HealthState.STARTING and decision.transition.t_s == 1.0
    assert monitor.step(fresh(1.1)).transition is None  # staying is not a transition


def test_engaged_while_stale_hovers_at_once() -> None:
    monitor = HealthMonitor(CONFIG)
    decision = monitor.step(HealthInputs(1.0, 0.5, True, offboard=ACTIVE))
    assert (decision.state, decision.action) == (HealthState.HOVER, Action.HOVER)


def test_stale_output_hovers_after_the_limit_not_before() -> None:
    monitor = flying()
    at_limit = monitor.step(HealthInputs(1.5, 1.25, True, offboard=ACTIVE))
    assert at_limit.state is HealthState.ACTIVE  # 250 ms old: fresh
    past = monitor.step(
        HealthInputs(1.5625, 1.25, True, "no fresh rig image: left: stale", offboard=ACTIVE)
    )
    assert (past.state, past.action) == (HealthState.HOVER, Action.HOVER)
    assert past.reason == "no fresh rig image: left: stale"
    assert monitor.hover_since_s == 1.5625  # 312.5 ms old: stale


def test_stale_reason_without_a_problem_names_the_age() -> None:
    monitor = flying()
    decision = monitor.step(HealthInputs(2.0, 1.5, True, offboard=ACTIVE))
    assert decision.reason == "output image 0.500 s old > 0.300 s"


def test_invalid_output_hovers_immediately_even_if_the_last_valid_one_is_fresh() -> None:
    monitor = flying()
    nan = HealthInputs(0.1, 0.05, False, "policy output refused: non-finite output", ACTIVE)
    decision = monitor.step(nan)
    assert (decision.state, decision.action) == (HealthState.HOVER, Action.HOVER)
    assert "non-finite" in decision.reason


def test_hover_recovers_when_fresh_again_and_the_hover_clock_restarts() -> None:
    monitor = flying()
    monitor.step(HealthInputs(1.0, 0.5, True, offboard=ACTIVE))  # hover from t = 1
    back = monitor.step(fresh(3.5))  # 2.5 s of hover: under the 3 s failsafe delay
    assert (back.state, back.action) == (HealthState.ACTIVE, Action.FLY)
    monitor.step(HealthInputs(4.0, 3.0, True, offboard=ACTIVE))  # a new hover from t = 4
    still = monitor.step(HealthInputs(6.9, 3.0, True, offboard=ACTIVE))
    assert still.state is HealthState.HOVER  # 2.9 s of this hover, not 5.4 s of both


def test_long_hover_escalates_to_failsafe_once_and_never_comes_back() -> None:
    monitor = flying()
    monitor.step(HealthInputs(1.0, 0.5, True, offboard=ACTIVE))
    assert monitor.step(HealthInputs(4.0, 0.5, True, offboard=ACTIVE)).state is HealthState.HOVER
    failsafe = monitor.step(HealthInputs(4.01, 0.5, True, offboard=ACTIVE))
    assert (failsafe.state, failsafe.action) == (HealthState.FAILSAFE, Action.FAILSAFE)
    assert "hovered 3.01 s > 3 s" in failsafe.reason
    # After the failsafe the autopilot holds; fresh images do not take the vehicle back.
    for now_s in (4.1, 5.0, 9.0):
        later = monitor.step(fresh(now_s, INACTIVE, engage_allowed=True))
        assert (later.state, later.action) == (HealthState.FAILSAFE, Action.WAIT)


@pytest.mark.parametrize("start", [HealthState.ACTIVE, HealthState.HOVER])
def test_pilot_taking_over_releases_once_and_is_never_fought(start: HealthState) -> None:
    monitor = flying()
    if start is HealthState.HOVER:
        monitor.step(HealthInputs(1.0, 0.5, True, offboard=ACTIVE))
    assert monitor.state is start
    release = monitor.step(fresh(2.0, LOST))
    assert (release.state, release.action) == (HealthState.PILOT, Action.RELEASE)
    assert "left OFFBOARD" in release.reason
    for offboard in (LOST, INACTIVE, ACTIVE):
        later = monitor.step(fresh(3.0, offboard, engage_allowed=True))
        assert (later.state, later.action) == (HealthState.PILOT, Action.WAIT)


def test_stop_request_stops_once_from_any_state() -> None:
    monitor = flying()
    stop = monitor.step(HealthInputs(1.0, None, False, stop_requested=True))
    assert (stop.state, stop.action) == (HealthState.STOPPING, Action.STOP)
    again = monitor.step(HealthInputs(1.1, None, False, stop_requested=True))
    assert (again.state, again.action) == (HealthState.STOPPING, Action.WAIT)
    assert monitor.step(fresh(1.2)).state is HealthState.STOPPING


def test_history_keeps_the_latest_transitions() -> None:
    monitor = HealthMonitor(CONFIG, history_size=4)
    now = 0.0
    for _ in range(10):
        now += 0.1
        monitor.step(fresh(now))
        now += 0.1
        monitor.step(HealthInputs(now, now - 1.0, True, offboard=ACTIVE))
    assert len(monitor.history) == 4
    assert monitor.history[-1].target is HealthState.HOVER


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"stale_after_s": 0.0}, r"daemon\.stale_hover_after_s: 0 is outside"),
        ({"failsafe_after_s": -1.0}, r"daemon\.failsafe_after_s"),
        ({"stale_after_s": float("nan")}, r"daemon\.stale_hover_after_s: must be finite"),
    ],
)
def test_config_errors_name_the_field(fields: dict[str, float], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        HealthConfig(**fields)


_inputs = st.tuples(
    st.floats(0.0, 0.5),  # time step
    st.one_of(st.none(), st.floats(0.0, 1.0)),  # output age
    st.booleans(),  # output ok
    st.sampled_from(list(OffboardState)),
    st.booleans(),  # engage allowed
)


@settings(max_examples=200, deadline=None)
@given(st.lists(_inputs, min_size=1, max_size=60))
def test_invariants_over_random_ticks(ticks: list[tuple]) -> None:
    """Fly only when healthy and commanding; engage only while starting; final states stay."""
    monitor = HealthMonitor(CONFIG)
    now = 0.0
    seen_final: HealthState | None = None
    for dt, age, ok, offboard, allowed in ticks:
        now += dt
        output_time = None if age is None else now - age
        decision = monitor.step(HealthInputs(now, output_time, ok, "", offboard, allowed))
        if decision.action is Action.FLY:
            assert decision.healthy and offboard is ACTIVE
        if decision.action is Action.HOVER:
            assert offboard is ACTIVE
        if decision.action is Action.ENGAGE:
            assert decision.state is HealthState.STARTING and allowed and decision.healthy
        if seen_final is not None:
            assert decision.state is seen_final and decision.action is Action.WAIT
        if decision.state.final:
            seen_final = decision.state


# --- boundaries: exactly at each limit and one float step either side ------------------------
# Binary-exact values (0.25, 2.0, 100.0, 99.75): `now - then` is computed without rounding, so
# "exactly at the limit" is exact, and math.nextafter is the smallest step either side.
EXACT = HealthConfig(stale_after_s=0.25, failsafe_after_s=2.0)
AT_LIMIT_S = 100.0 - EXACT.stale_after_s  # an image received exactly stale_after_s before 100 s


@pytest.mark.parametrize(
    ("output_time_s", "fresh"),
    [
        (math.nextafter(AT_LIMIT_S, math.inf), True),  # one step younger than the limit
        (AT_LIMIT_S, True),  # exactly stale_after_s old: the limit is inclusive
        (math.nextafter(AT_LIMIT_S, -math.inf), False),  # one step older: stale
    ],
)
def test_freshness_limit_is_inclusive_to_the_last_step(output_time_s: float, fresh: bool) -> None:
    assert EXACT.stale_after_s == (100.0 - AT_LIMIT_S)  # the arithmetic really is exact
    monitor = HealthMonitor(EXACT, start_s=99.0)
    monitor.step(HealthInputs(99.5, 99.45, True, offboard=ACTIVE))
    assert monitor.state is HealthState.ACTIVE
    decision = monitor.step(HealthInputs(100.0, output_time_s, True, offboard=ACTIVE))
    assert decision.healthy is fresh
    expected = (HealthState.ACTIVE, Action.FLY) if fresh else (HealthState.HOVER, Action.HOVER)
    assert (decision.state, decision.action) == expected


@pytest.mark.parametrize(
    ("now_s", "state"),
    [
        (math.nextafter(3.0, -math.inf), HealthState.HOVER),  # one step short of 2 s of hover
        (3.0, HealthState.HOVER),  # exactly failsafe_after_s: not yet (the rule is "longer")
        (math.nextafter(3.0, math.inf), HealthState.FAILSAFE),  # one step longer
    ],
)
def test_failsafe_comes_one_step_after_failsafe_after_s(now_s: float, state: HealthState) -> None:
    monitor = HealthMonitor(EXACT, start_s=0.0)
    monitor.step(HealthInputs(0.5, 0.45, True, offboard=ACTIVE))  # ACTIVE
    monitor.step(HealthInputs(1.0, 0.5, True, offboard=ACTIVE))  # stale: hover from t = 1
    assert monitor.hover_since_s == 1.0 and EXACT.failsafe_after_s == (3.0 - 1.0)
    assert monitor.step(HealthInputs(now_s, 0.5, True, offboard=ACTIVE)).state is state
