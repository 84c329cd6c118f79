"""Fault plans for the HIL swarm: timed events per drone, each with the outcome it must have.

A plan is a TOML file of `[[event]]` tables (times from the flight's start, drones numbered from
1 like their ids `drone1`, `drone2`, ...):

    [[event]]
    at_s = 8.0
    drone = 2
    kind = "camera_unplug"      # see KINDS
    face = "front"              # camera faults
    duration_s = 5.0            # camera_stall, camera_unplug, link_pause

What each kind does and the outcome checked afterwards from the PX4 emulator's own records
(setpoints, mode changes; emulator clock) and the daemon's exit:

| kind           | does                                  | expected outcome                     |
|----------------|---------------------------------------|--------------------------------------|
| camera_stall   | the camera's script hangs             | hover within 0.5 s, then flies again |
| camera_unplug  | cable out, then back in               | the same; Hold if it outlasts        |
|                |                                       | `failsafe_after_s` (final by design) |
| camera_garbage | 4 kB of random bytes on the link      | dropped and counted: keeps flying    |
| camera_corrupt | the next 5 frames fail their CRC      | keeps flying                         |
| link_pause     | the MAVLink link drops (duration_s)   | PX4's offboard-loss failsafe (Hold); |
|                |                                       | PX4 itself resumes OFFBOARD when the |
|                |                                       | re-sent setpoints get through again  |
| pilot_mode     | the pilot switches to Position mode   | setpoints stop; no OFFBOARD again    |
| daemon_sigterm | systemd stops the service             | Hold, exit 0, complete flight log    |
| daemon_sigkill | the daemon dies                       | PX4's failsafe (Hold) after          |
|                |                                       | COM_OF_LOSS_T, a readable flight log |

A daemon's response times are its loop's. When the machine is too busy to run the daemons (the
unfaulted daemons' setpoints, like the faulted one's, stopped for over three ticks around the
fault), a camera fault's time bounds are reported "not judged" and only its end state (Hold) is.
A stopped or killed daemon is judged on the mode in force, so a vehicle that PX4 had already put in
Hold (its daemon starved of CPU) passes by staying there.
"""

from __future__ import annotations

import itertools
import math
import signal
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from companion.camera.layout import FACE_NAMES
from companion.errors import ConfigError
from companion.flight_log import summarize_log
from sim_harness.hil.px4_logic import ModeChange, Px4Mode

if TYPE_CHECKING:
    from sim_harness.hil.drone import HilDrone

KINDS = (
    "camera_stall",
    "camera_unplug",
    "camera_garbage",
    "camera_corrupt",
    "link_pause",
    "pilot_mode",
    "daemon_sigterm",
    "daemon_sigkill",
)
CAMERA_KINDS = KINDS[:4]
TIMED_KINDS = ("camera_stall", "camera_unplug", "link_pause")
HOVER_WITHIN_S = 0.5  # the operator guide's promise for stale cameras
STALL_PERIODS = 3.0  # no setpoint for this many ticks: the daemon did not run (_judge_timing)
SETTLE_S = 4.0  # the flight goes on at least this long after the last event ends


@dataclass(frozen=True)
class FaultEvent:
    at_s: float
    drone: int  # 1-based
    kind: str
    face: str = "front"
    duration_s: float = 0.0

    @property
    def label(self) -> str:
        where = f" {self.face}" if self.kind in CAMERA_KINDS else ""
        span = f" for {self.duration_s:g} s" if self.kind in TIMED_KINDS else ""
        return f"t={self.at_s:g} s drone{self.drone}: {self.kind}{where}{span}"


@dataclass(frozen=True)
class FaultPlan:
    events: tuple[FaultEvent, ...]
    source: str = ""

    @property
    def end_s(self) -> float:
        """When the last event is over, plus time to see its outcome."""
        return max((e.at_s + e.duration_s for e in self.events), default=0.0) + SETTLE_S


def _field(entry: dict[str, Any], index: int, name: str, kind: type, default: Any = None) -> Any:
    value = entry.get(name, default)
    if value is None:
        raise ConfigError(f"faults.event[{index}].{name}: required")
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or isinstance(value, bool):
        raise ConfigError(f"faults.event[{index}].{name}: expected {kind.__name__}, got {value!r}")
    return value


def parse_plan(data: dict[str, Any], n_drones: int, source: str = "") -> FaultPlan:
    """A validated plan; errors name the event and field."""
    entries = data.get("event", [])
    if not isinstance(entries, list) or not entries:
        raise ConfigError("faults.event: a plan needs at least one [[event]] table")
    events = []
    for k, entry in enumerate(entries):
        unknown = set(entry) - {"at_s", "drone", "kind", "face", "duration_s"}
        if unknown:
            raise ConfigError(f"faults.event[{k}]: unknown field(s) {sorted(unknown)}")
        kind = _field(entry, k, "kind", str)
        if kind not in KINDS:
            raise ConfigError(f"faults.event[{k}].kind: {kind!r} is not one of {', '.join(KINDS)}")
        at_s = _field(entry, k, "at_s", float)
        drone = _field(entry, k, "drone", int)
        face = _field(entry, k, "face", str, "front")
        duration = _field(entry, k, "duration_s", float, 0.0)
        if not 0.0 <= at_s < 3600.0:
            raise ConfigError(f"faults.event[{k}].at_s: {at_s} is outside [0, 3600)")
        if not 1 <= drone <= n_drones:
            raise ConfigError(f"faults.event[{k}].drone: {drone} is outside [1, {n_drones}]")
        if face not in FACE_NAMES:
            raise ConfigError(f"faults.event[{k}].face: {face!r} is not one of {FACE_NAMES}")
        if kind in TIMED_KINDS and not 0.0 < duration <= 600.0:
            raise ConfigError(f"faults.event[{k}].duration_s: {duration} is outside (0, 600]")
        events.append(FaultEvent(at_s, drone, kind, face, duration))
    stops = [e.drone for e in events if e.kind.startswith("daemon_")]
    if len(stops) != len(set(stops)):
        raise ConfigError("faults.event: a drone's daemon can be stopped only once")
    return FaultPlan(tuple(sorted(events, key=lambda e: e.at_s)), source)


def load_plan(path: Path, n_drones: int) -> FaultPlan:
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"faults: cannot read {path}: {exc}") from exc
    return parse_plan(data, n_drones, str(path))


@dataclass
class FaultOutcome:
    """One event's expected outcome and what was observed."""

    event: FaultEvent
    expected: str
    passed: bool
    observed: dict[str, Any] = field(default_factory=dict)

    def line(self) -> str:
        verdict = "PASS" if self.passed else "FAIL"
        seen = ", ".join(f"{k} {_fmt(v)}" for k, v in self.observed.items())
        return f"{verdict} {self.event.label}: expected {self.expected}; observed {seen}"


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


class FaultRunner:
    """Fires a plan's events on the flight clock and checks their outcomes afterwards."""

    def __init__(self, plan: FaultPlan, drones: Sequence[HilDrone]) -> None:
        self.plan = plan
        self.drones = list(drones)
        self._pending = list(plan.events)
        self._ends: list[tuple[float, FaultEvent]] = []
        self.fired: dict[FaultEvent, float] = {}  # event -> emulator clock time when fired
        self.exit_s: dict[int, float] = {}  # drone -> emulator time its daemon was seen gone
        self._rng = np.random.default_rng(0)

    def poll(self, t_s: float) -> None:
        """Fire what is due at flight time `t_s`; end timed events; note daemon exits."""
        while self._pending and self._pending[0].at_s <= t_s:
            self._fire(self._pending.pop(0))
        for end in [e for e in self._ends if e[0] <= t_s]:
            self._ends.remove(end)
            self._end(end[1])
        for event in self.fired:
            drone = self.drones[event.drone - 1]
            gone = event.kind.startswith("daemon_") and not drone.alive
            if gone and event.drone not in self.exit_s:
                self.exit_s[event.drone] = drone.px4.now_s()

    def finish(self, t_s: float) -> None:
        """End whatever is still going (the flight stopped first)."""
        for _, event in self._ends:
            self._end(event)
        self._ends.clear()
        self.poll(t_s)

    def _fire(self, event: FaultEvent) -> None:
        drone = self.drones[event.drone - 1]
        self.fired[event] = drone.px4.now_s()
        cams, face = drone.cameras, event.face
        if event.kind == "camera_stall":
            cams.stall(face)
        elif event.kind == "camera_unplug":
            cams.unplug(face)
        elif event.kind == "camera_garbage":
            cams.inject(face, self._rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
        elif event.kind == "camera_corrupt":
            cams.corrupt_frames(face, 5)
        elif event.kind == "link_pause":
            drone.px4.set_link_alive(False)
        elif event.kind == "pilot_mode":
            drone.px4.pilot_switch_mode(Px4Mode.POSCTL)
        elif event.kind == "daemon_sigterm":
            drone.killed_by = "sigterm"
            drone.signal_daemon(signal.SIGTERM)
        elif event.kind == "daemon_sigkill":
            drone.killed_by = "sigkill"
            drone.signal_daemon(signal.SIGKILL)
        if event.kind in TIMED_KINDS:
            self._ends.append((event.at_s + event.duration_s, event))

    def _end(self, event: FaultEvent) -> None:
        drone = self.drones[event.drone - 1]
        if event.kind == "camera_stall":
            drone.cameras.resume(event.face)
        elif event.kind == "camera_unplug":
            drone.cameras.replug(event.face)
        elif event.kind == "link_pause":
            drone.px4.set_link_alive(True)

    # -- outcomes (after the drones stopped) ---------------------------------------------

    def outcomes(self) -> list[FaultOutcome]:
        return [self._outcome(e, t) for e, t in self.fired.items()]

    def _outcome(self, event: FaultEvent, fired_s: float) -> FaultOutcome:
        drone = self.drones[event.drone - 1]
        daemon = drone.config_document()["daemon"]
        failsafe_after_s = float(daemon["failsafe_after_s"])
        loss_s = drone.px4.config.px4.offboard_loss_timeout_s
        setpoints = [s for s in drone.px4.setpoints() if s.t_s >= fired_s]
        history = drone.px4.mode_changes()
        modes = [m for m in history if m.t_s >= fired_s]
        back_in_offboard = any(m.new is Px4Mode.OFFBOARD for m in modes)
        obs: dict[str, Any] = {}
        kind = event.kind
        if kind in ("camera_stall", "camera_unplug"):
            hover = next((s.t_s for s in setpoints if _speed(s) < 1e-3), math.inf)
            obs["hover_after_s"] = hover - fired_s
            recovered_s = fired_s + event.duration_s
            if event.duration_s < failsafe_after_s:
                expected = f"hover within {HOVER_WITHIN_S} s, then flies again"
                flying = next(
                    (s.t_s for s in setpoints if s.t_s > recovered_s and _speed(s) > 1e-3), math.inf
                )
                obs["flies_again_after_recovery_s"] = flying - recovered_s
                left = [m for m in modes if m.old is Px4Mode.OFFBOARD]
                obs["mode_changes"] = [m.new.name for m in modes]
                ok = hover - fired_s <= HOVER_WITHIN_S and math.isfinite(flying) and not left
            else:
                expected = (
                    f"hover within {HOVER_WITHIN_S} s, Hold after {failsafe_after_s:g} s, "
                    "in Hold to the end"
                )
                hold = next((m.t_s for m in modes if m.new is Px4Mode.HOLD), math.inf)
                obs["hold_after_hover_s"] = hold - hover
                # Judged only when the daemons got CPU: hover and Hold in time, no OFFBOARD again
                # (on a starved machine PX4's offboard-loss failsafe may take the vehicle out of
                # OFFBOARD and back first). Always: the vehicle ends in Hold.
                on_time = (
                    hover - fired_s <= HOVER_WITHIN_S
                    and hold - hover <= failsafe_after_s + 1.0
                    and not back_in_offboard
                )
                window_end = min(hold, fired_s + HOVER_WITHIN_S + failsafe_after_s + 1.0)
                tick_s = 1.0 / float(daemon["rate_hz"])
                judged = self._judge_timing(drone, fired_s, window_end, tick_s, on_time, obs)
                ok = bool(history) and history[-1].new is Px4Mode.HOLD and (on_time or not judged)
        elif kind in ("camera_garbage", "camera_corrupt"):
            expected = "keeps flying, in OFFBOARD, daemon alive"
            obs["mode_changes"] = [m.new.name for m in modes]
            ok = not modes and (drone.exit_code is None or drone.killed_by is not None)
            ok = ok and any(_speed(s) > 1e-3 for s in setpoints if s.t_s > fired_s + 1.0)
        elif kind == "link_pause":
            # Real PX4 keeps OFFBOARD as the intended mode through this failsafe and resumes
            # it, with no request, once MAVSDK's re-sent setpoints arrive again (issue 19).
            expected = f"Hold within {loss_s:g} s + 0.5 s (PX4 may resume OFFBOARD after)"
            hold = next((m.t_s for m in modes if m.new is Px4Mode.HOLD), math.inf)
            obs["hold_after_s"] = hold - fired_s
            obs["back_in_offboard"] = back_in_offboard
            ok = hold - fired_s <= loss_s + 0.5
        elif kind == "pilot_mode":
            expected = "setpoints stop within 2 s; OFFBOARD never taken back"
            last = max((s.t_s for s in setpoints), default=fired_s)
            obs["setpoints_for_s"] = last - fired_s
            obs["back_in_offboard"] = back_in_offboard
            ok = last - fired_s <= 2.0 and not back_in_offboard
        else:
            ok, expected = self._daemon_outcome(event, drone, fired_s, history, daemon, loss_s, obs)
        return FaultOutcome(event, expected, bool(ok), obs)

    def _judge_timing(
        self,
        drone: HilDrone,
        fired_s: float,
        end_s: float,
        tick_s: float,
        on_time: bool,
        obs: dict[str, Any],
    ) -> bool:
        """Whether the outcome's time bounds are judged, with the reason in `obs["timing"]`.

        A daemon's response times are its loop's: a daemon that got no CPU sends nothing, and a
        starved machine (measured in CI: every daemon's setpoints stopped for over 1 s at a
        time) says nothing about the daemon's logic. The bounds are judged unless the faulted
        daemon's setpoints stopped for longer than `STALL_PERIODS` ticks in [fired - 1 s, end]
        *and* so did the unfaulted daemons' (their median): a stall only the faulted drone had
        is the fault's doing and is judged.
        """
        bound_s = STALL_PERIODS * tick_s
        start_s = fired_s - 1.0
        own = _longest_gap([s.t_s for s in drone.px4.setpoints()], start_s, end_s)
        swarm = self._swarm_gap_s(drone, start_s, end_s)
        obs["daemon_gap_s"], obs["swarm_gap_s"] = own, swarm
        judged = own <= bound_s or swarm is None or swarm <= bound_s
        if not judged:
            obs["timing"] = f"not judged: every daemon stalled > {bound_s:g} s (machine late)"
        else:
            obs["timing"] = "met" if on_time else "missed"
        return judged

    def _swarm_gap_s(self, drone: HilDrone, start_s: float, end_s: float) -> float | None:
        """The unfaulted daemons' median longest setpoint gap in [start, end] of `drone`'s clock."""
        faulted = {e.drone for e in self.plan.events}
        gaps = []
        for number, other in enumerate(self.drones, start=1):
            if number in faulted:
                continue
            shift = drone.px4.clock_origin_s - other.px4.clock_origin_s
            times = [s.t_s for s in other.px4.setpoints()]
            gaps.append(_longest_gap(times, start_s + shift, end_s + shift))
        return float(np.median(gaps)) if gaps else None

    def _daemon_outcome(
        self,
        event: FaultEvent,
        drone: HilDrone,
        fired_s: float,
        history: list[ModeChange],
        daemon: dict[str, Any],
        loss_s: float,
        obs: dict[str, Any],
    ) -> tuple[bool, str]:
        # Judged on the mode in force, not on a transition after the signal: on a starved
        # machine the vehicle may already be in Hold (PX4's offboard-loss failsafe while the
        # daemon got no CPU) when the signal comes, and then Hold must simply last.
        at_fire = _in_force(history, fired_s)
        obs["mode_at_fire"] = None if at_fire is None else at_fire.new.name
        if event.kind == "daemon_sigterm":
            limit_s = float(daemon["shutdown_timeout_s"])
            expected = f"Hold within {limit_s:g} s, exit 0, complete flight log"
        else:
            limit_s = loss_s + 1.0
            expected = f"PX4 offboard-loss failsafe (Hold) within {loss_s:g} s + 1 s, readable log"
        hold = _in_force(history, fired_s + limit_s)
        if hold is not None and hold.new is not Px4Mode.HOLD:
            hold = None
        obs["hold_after_s"] = math.inf if hold is None else hold.t_s - fired_s
        obs["hold_reason"] = None if hold is None else hold.reason
        logs = sorted(drone.flights_dir.glob("*.mcap"))
        summaries = [summarize_log(p) for p in logs]
        obs["log_readable"] = bool(summaries) and all(s["message_count"] > 0 for s in summaries)
        obs["exit_code"] = drone.exit_code
        stays = hold is not None and not any(
            m.new is Px4Mode.OFFBOARD for m in history if m.t_s > hold.t_s
        )
        if event.kind == "daemon_sigterm":
            obs["log_complete"] = bool(summaries) and all(s["complete"] for s in summaries)
            ok = stays and drone.exit_code == 0 and obs["log_complete"]
        else:
            # From OFFBOARD, the Hold must be PX4's own failsafe for the setpoints that stopped.
            by_px4 = (
                at_fire is None
                or at_fire.new is not Px4Mode.OFFBOARD
                or (hold is not None and "lost" in hold.reason)
            )
            ok = stays and by_px4 and obs["log_readable"]
        return bool(ok), expected


def _in_force(history: Sequence[ModeChange], t_s: float) -> ModeChange | None:
    """The mode change in force at `t_s` (the last one at or before it), or None."""
    return next((m for m in reversed(history) if m.t_s <= t_s), None)


def _longest_gap(times: Sequence[float], start_s: float, end_s: float) -> float:
    """The longest stretch of [start, end] without a time in `times` (sorted)."""
    edges = [start_s, *(t for t in times if start_s < t < end_s), end_s]
    return max(b - a for a, b in itertools.pairwise(edges))


def _speed(s: Any) -> float:
    return math.sqrt(s.vx_mps**2 + s.vy_mps**2 + s.vz_mps**2)
