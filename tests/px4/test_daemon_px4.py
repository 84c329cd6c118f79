"""The unmodified daemon against real PX4 firmware (SITL + SIH), judged by PX4's own state.

Every assertion reads what PX4 reports on its GCS link: HEARTBEAT custom mode (1 Hz: mode-change
times are good to about a second), LOCAL_POSITION_NED (50 Hz), STATUSTEXT. Tolerances: after 3 s
in OFFBOARD the vehicle's horizontal velocity points within 20 deg of the commanded direction and
its speed is within 40 % of the command (PX4 flew 1.27-1.65 m/s for 1.5-2 m/s setpoints here).
"""

from __future__ import annotations

import math
import signal
import time
from collections.abc import Callable
from typing import Any

from sim_harness.hil.px4_gcs import GroundStation, GroundStationError
from sim_harness.hil.px4_logic import MavResult, Px4Mode

COMMANDED_MPS = 1.5  # the constant policy's forward speed (tests/px4/conftest.py)
ENGAGE_GUARD_S = 40.0  # start-up (torch, MAVSDK, health) + pre-stream + heartbeat; ~5-8 s here
HEARTBEAT_SLACK_S = 1.3  # PX4's heartbeat is 1 Hz on the GCS link
# PX4 times the offboard loss from the last setpoint it received, which comes before the kill by
# up to a control period (10 Hz), by more when the daemon was starved on a loaded machine
# (0.9995 s after the kill seen in CI under two busy loops).
LAST_SETPOINT_SLACK_S = 0.2


def heading_ned_rad(gcs: GroundStation) -> float:
    gp = gcs.global_position
    assert gp is not None
    return math.radians(gp.hdg / 100.0)


def engaged(gcs: GroundStation, since_s: float, run: Any = None) -> float:
    """The pilot engages, as the shipped config (`engage = "operator"`) wants: once the daemon
    streams (its log says "ready"), the ground station switches the vehicle to OFFBOARD.
    (PX4 acknowledges the switch even without setpoints, then stays where it is.) Seconds from
    `since_s` until PX4 reports OFFBOARD (fails after ENGAGE_GUARD_S)."""
    if run is not None:
        logged(run, "ready: streaming")
    deadline = since_s + ENGAGE_GUARD_S
    while True:
        gcs.set_mode(Px4Mode.OFFBOARD)
        try:
            gcs.wait_until(
                lambda: gcs.mode is Px4Mode.OFFBOARD, HEARTBEAT_SLACK_S + 1.0, "OFFBOARD"
            )
            return time.monotonic() - since_s
        except GroundStationError:
            assert time.monotonic() < deadline, "PX4 never took the pilot's switch to OFFBOARD"


def logged(run: Any, text: str, timeout_s: float = ENGAGE_GUARD_S) -> None:
    """Wait until a health event of the run's flight log contains `text` (flushed each 1 s)."""
    deadline = time.monotonic() + timeout_s
    while not any(text in e for e in run.health_lines()):
        assert time.monotonic() < deadline, (text, run.health_lines())
        time.sleep(0.3)


def mean_velocity(gcs: GroundStation, seconds: float) -> tuple[float, float]:
    """Mean NED (north, east) velocity (m/s) over the last `seconds` of LOCAL_POSITION_NED."""
    samples = gcs.positions_since(time.monotonic() - seconds)
    # PX4 streams it at about 30-50 Hz; a loaded machine delivers fewer (10 in 0.3 s seen beside
    # two busy loops). Five still make a mean, and fewer means the link itself stalled.
    assert len(samples) >= 5, f"{len(samples)} LOCAL_POSITION_NED in the last {seconds} s"
    return (
        sum(s.vx for s in samples) / len(samples),
        sum(s.vy for s in samples) / len(samples),
    )


def heartbeats_since(gcs: GroundStation, t_s: float) -> list[tuple[float, Any, int]]:
    """(seconds after `t_s`, mode, MAV_STATE) of each heartbeat since: for failure messages."""
    return [(round(m.t_s - t_s, 1), m.mode, m.system_status) for m in gcs.modes_since(t_s)]


def heard(
    gcs: GroundStation, condition: Callable[[], bool], timeout_s: float, what: str, since_s: float
) -> None:
    """Wait for `condition`; on a miss, fail with what PX4 reported since `since_s`."""
    try:
        gcs.wait_until(condition, timeout_s, what)
    except GroundStationError as error:
        seen = (heartbeats_since(gcs, since_s), gcs.texts_since(since_s))
        raise AssertionError((str(error), gcs.height_above_home_m, seen)) from error


def angle_between(a_rad: float, b_rad: float) -> float:
    return abs((a_rad - b_rad + math.pi) % (2 * math.pi) - math.pi)


def assert_flies_forward(gcs: GroundStation, heading_rad: float) -> None:
    commanded = COMMANDED_MPS
    north, east = mean_velocity(gcs, 0.5)
    speed = math.hypot(north, east)
    assert abs(speed - commanded) <= 0.4 * commanded, (north, east)
    # Yaw follows the velocity, so forward turns with any sideways transient: under two busy
    # loops the track was measured 20.1 deg off the starting heading once (a wrong axis is 90+).
    assert math.degrees(angle_between(math.atan2(east, north), heading_rad)) <= 30.0


def test_engages_flies_the_commanded_direction_and_yields_to_the_pilot(
    shipped: Any, daemon_run: Any
) -> None:
    vehicle = shipped
    gcs = vehicle.gcs
    heading = heading_ned_rad(gcs)  # forward in body FLU = this heading (yaw follows velocity)
    start = time.monotonic()
    run = daemon_run(vehicle)
    logged(run, "ready: streaming")  # streaming: only the pilot's switch engages
    time.sleep(1.0)
    assert all(m.mode is Px4Mode.HOLD for m in gcs.modes_since(start))
    engaged(gcs, start, run)
    time.sleep(3.0)
    assert gcs.mode is Px4Mode.OFFBOARD
    assert_flies_forward(gcs, heading)

    # The pilot switches to Hold from the ground station: the daemon stops commanding.
    switched = time.monotonic()
    assert gcs.set_mode(Px4Mode.HOLD) is MavResult.ACCEPTED
    time.sleep(4.0)  # MAVSDK notices at the next heartbeat, re-sends ~2 s more, then stops
    assert all(m.mode is Px4Mode.HOLD for m in gcs.modes_since(switched + 0.5))
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()
    assert gcs.mode is Px4Mode.HOLD
    events = run.health_events()
    assert "active -> pilot" in events, events
    assert events[-1] == "stopped"


def test_sigterm_ends_in_hold_and_exit_0(shipped: Any, daemon_run: Any) -> None:
    vehicle = shipped
    gcs = vehicle.gcs
    run = daemon_run(vehicle)
    engaged(gcs, time.monotonic(), run)
    time.sleep(1.5)
    stopped = time.monotonic()
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()
    gcs.wait_until(lambda: gcs.mode is Px4Mode.HOLD, HEARTBEAT_SLACK_S + 1.0, "HOLD")
    assert not [
        m for m in gcs.modes_since(stopped) if m.mode not in (Px4Mode.OFFBOARD, Px4Mode.HOLD)
    ]
    assert "Failsafe activated" not in "".join(gcs.texts_since(stopped))  # the daemon's own Hold


def test_a_stalled_camera_hovers_then_holds(shipped: Any, daemon_run: Any) -> None:
    vehicle = shipped
    gcs = vehicle.gcs
    run = daemon_run(vehicle, failsafe_after_s=2.0)
    engaged(gcs, time.monotonic(), run)
    time.sleep(2.0)
    assert math.hypot(*mean_velocity(gcs, 0.3)) > 0.8  # flying before the stall
    stalled = time.monotonic()
    run.cameras.stall("front")
    # Hover: the daemon commands zero velocity (still in OFFBOARD); PX4 brakes to a stop.
    gcs.wait_until(lambda: math.hypot(*mean_velocity(gcs, 0.3)) < 0.25, 3.0, "hover")
    assert gcs.mode is Px4Mode.OFFBOARD
    # Then the daemon's failsafe: Hold, failsafe_after_s after the hover began.
    gcs.wait_until(lambda: gcs.mode is Px4Mode.HOLD, 2.0 + 0.3 + HEARTBEAT_SLACK_S + 1.0, "HOLD")
    held = gcs.mode_changes(stalled)[-1].t_s - stalled
    assert 2.0 <= held <= 2.0 + 0.3 + HEARTBEAT_SLACK_S + 0.5
    # Holding: the flight (> 0.8 m/s) comes to rest. PX4's Hold first moves the vehicle back
    # towards its hold point (0.53 m/s in the 0.3 s after the switch once, 0.26-0.53 m/s over
    # the second after, beside other work), then settles there: judged on a whole second's mean
    # speed, with time for the return.
    gcs.wait_until(lambda: math.hypot(*mean_velocity(gcs, 1.0)) < 0.3, 8.0, "Hold at rest")
    assert gcs.mode is Px4Mode.HOLD
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()
    events = run.health_events()
    assert any(e.endswith("-> failsafe") for e in events), events


def sigkill_ends_in_px4_failsafe(vehicle: Any, daemon_run: Any) -> tuple[float, Px4Mode]:
    """Kill the flying daemon; (seconds until PX4 left OFFBOARD, the mode it chose)."""
    gcs = vehicle.gcs
    run = daemon_run(vehicle)
    engaged(gcs, time.monotonic(), run)
    time.sleep(1.0)
    killed = time.monotonic()
    run.signal(signal.SIGKILL)
    run.wait()
    gcs.wait_until(lambda: gcs.mode is not Px4Mode.OFFBOARD, 1.0 + HEARTBEAT_SLACK_S + 1.0, "loss")
    change = gcs.mode_changes(killed)[-1]
    assert change.mode is not None
    assert any("Failsafe activated" in t for t in gcs.texts_since(killed))
    assert len(run.health_events()) > 0  # the crash-cut flight log is readable
    return change.t_s - killed, change.mode


def test_sigkill_with_the_shipped_parameters_ends_in_hold_after_com_of_loss_t(
    shipped: Any, daemon_run: Any
) -> None:
    vehicle = shipped
    after_s, mode = sigkill_ends_in_px4_failsafe(vehicle, daemon_run)
    assert mode is Px4Mode.HOLD  # COM_OBL_RC_ACT 5
    # COM_OF_LOSS_T 1 s (not an earlier timeout), as the 1 Hz heartbeat shows it
    assert 1.0 - LAST_SETPOINT_SLACK_S <= after_s <= 1.0 + HEARTBEAT_SLACK_S

    # systemd restarts the daemon. PX4 still intends OFFBOARD and would resume it on the first
    # setpoint (issue 19 finding 2): the new daemon re-asserts Hold, then streams; the vehicle
    # stays in Hold until the pilot switches to OFFBOARD.
    gcs = vehicle.gcs
    restarted = time.monotonic()
    run = daemon_run(vehicle)
    logged(run, "ready: streaming")
    time.sleep(2.0)
    assert all(m.mode is Px4Mode.HOLD for m in gcs.modes_since(restarted)), gcs.mode_changes(
        restarted
    )
    engaged(gcs, time.monotonic(), run)
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()
    gcs.wait_until(lambda: gcs.mode is Px4Mode.HOLD, HEARTBEAT_SLACK_S + 1.0, "HOLD")


def test_no_engagement_during_a_px4_failsafe(shipped: Any, daemon_run: Any) -> None:
    """A geofence breach (issue 19 finding 3): PX4 holds in a failsafe (its heartbeat says
    CRITICAL); the daemon does not stream, so not even the pilot's switch can engage."""
    vehicle = shipped
    gcs = vehicle.gcs
    held = time.monotonic()
    assert gcs.set_mode(Px4Mode.HOLD) is MavResult.ACCEPTED  # the pilot's mode, nothing pending
    # The pilot's switch ends any failsafe an earlier test left (an offboard loss when the
    # SIGTERMed daemon's last setpoint came late): a plain Hold heartbeat before the breach, so
    # that a CRITICAL one after it is this breach's.
    heard(
        gcs,
        lambda: any(m.mode is Px4Mode.HOLD and not m.failsafe for m in gcs.modes_since(held)),
        2 * HEARTBEAT_SLACK_S + 1.0,
        "a Hold heartbeat without a failsafe",
        held,
    )
    fence = gcs.get_param("GF_MAX_VER_DIST")
    assert fence is not None
    try:
        breached = time.monotonic()
        gcs.set_param("GF_MAX_VER_DIST", 2.0, 9)  # the vehicle hovers about 5 m up: a breach
        # PX4 took about 1 s here (its geofence check, then the next 1 Hz heartbeat); the
        # margin is for a loaded machine. On a miss, say what PX4 did report.
        heard(
            gcs,
            lambda: any(m.failsafe for m in gcs.modes_since(breached)),
            5.0 + 2 * HEARTBEAT_SLACK_S,
            "the breach's failsafe",
            held,
        )
        run = daemon_run(vehicle)
        logged(run, "PX4 is in a failsafe")
        tried = time.monotonic()
        gcs.set_mode(Px4Mode.OFFBOARD)  # PX4 refuses: it has no setpoints to switch to
        time.sleep(HEARTBEAT_SLACK_S + 1.0)
        seen = (heartbeats_since(gcs, breached), gcs.texts_since(breached), run.health_lines())
        assert all(m.mode is not Px4Mode.OFFBOARD for m in gcs.modes_since(tried)), seen
        assert all(m.failsafe for m in gcs.modes_since(tried)), seen  # PX4 still holds
        assert "ready" not in run.health_events(), seen
    finally:
        gcs.set_param("GF_MAX_VER_DIST", fence, 9)
    gcs.set_mode(Px4Mode.HOLD)  # back inside the fence; the pilot's mode change ends the failsafe
    engaged(gcs, time.monotonic(), run)
    run.signal(signal.SIGTERM)
    assert run.wait() == 0, run.output()


def test_sigkill_with_stock_parameters_is_not_hold(stock: Any, daemon_run: Any) -> None:
    """Stock COM_OBL_RC_ACT is 0, Position mode; SITL has no RC, so PX4 falls back to Return."""
    after_s, mode = sigkill_ends_in_px4_failsafe(stock, daemon_run)
    assert mode in (Px4Mode.POSCTL, Px4Mode.RTL)
    assert after_s <= 1.0 + HEARTBEAT_SLACK_S
