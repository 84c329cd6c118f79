"""Who may engage OFFBOARD, and when: the `[daemon] engage` modes and the operator's commands.

- "operator": once healthy the daemon streams hover setpoints; the pilot (RC) or the ground
  station switches the vehicle to OFFBOARD, which engages. After a pilot takeover or a failsafe
  it streams again, and again only the pilot's switch engages.
- "ground": the daemon requests OFFBOARD itself, but only after `companion engage` (the ground
  station runs it over SSH); a takeover, a failsafe or `companion disengage` ends the engagement
  and the next one needs a new `companion engage`.
- "auto": request OFFBOARD as soon as healthy; never again after a takeover (simulation only).
- "never": never command (bench tests).

In every mode nothing engages while the autopilot's heartbeat is missing (the mode is unknown),
during a PX4 failsafe (HEARTBEAT system status CRITICAL/EMERGENCY: a geofence breach, a low
battery...), or, with `engage_requires_airborne`, before the vehicle is armed and in the air. The
one failsafe that does not block is PX4's offboard-loss failsafe waiting to resume OFFBOARD
(`ModeReport.resumes_offboard`): "operator" re-asserts PX4's current mode before streaming (so
the pilot's switch is still needed: `MavsdkAutopilot.prepare_offboard`), and in "ground" an
explicit `companion engage` is the operator asking for exactly that resume.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.autopilot_types import AutopilotTelemetry, OffboardState
from companion.control import ControlOutput
from companion.daemon_commands import Commander
from companion.health import HealthDecision, HealthMonitor, HealthState

COMMANDING = (HealthState.ACTIVE, HealthState.HOVER)


@dataclass(frozen=True)
class EngageGate:
    """This tick: may the daemon request OFFBOARD, may it stream, and if neither, why."""

    engage_allowed: bool
    stream_allowed: bool
    waiting: str


class Engagement:
    """The engage mode's rules and the operator's requests (`companion engage|disengage`)."""

    def __init__(
        self,
        mode: str,
        *,
        requires_airborne: bool,
        heartbeat_timeout_s: float,
        events: Callable[[str, str, Any], object],
    ) -> None:
        self.mode = mode
        self._requires_airborne = requires_airborne
        self._heartbeat_timeout_s = heartbeat_timeout_s
        self._events = events
        self.requested = False  # "ground": `companion engage` arrived and still stands
        self.disengage_requested = False
        self._waiting = ""  # the last "not engaging" reason logged

    @property
    def reengage_allowed(self) -> bool:
        """After a takeover or failsafe an operator may engage again (never the daemon alone)."""
        return self.mode in ("operator", "ground")

    def heartbeat_problem(self, telemetry: AutopilotTelemetry, now_s: float) -> str:
        """Why the autopilot's heartbeat cannot be trusted now ("" when it is fresh)."""
        status = telemetry.status
        if status is None:
            return "no heartbeat from the autopilot yet"
        if now_s - status.t_s > self._heartbeat_timeout_s:
            return (
                f"autopilot heartbeat lost (none for > {self._heartbeat_timeout_s:g} s): "
                "flight mode unknown"
            )
        return ""

    def gate(self, telemetry: AutopilotTelemetry, now_s: float, commander_free: bool) -> EngageGate:
        """The engage and stream permissions for this tick."""
        if self.mode == "never":
            return EngageGate(False, False, 'engage = "never" (dry run)')
        blocked = self._blocked(telemetry, now_s)
        if not blocked and not commander_free:
            blocked = "an OFFBOARD request is running or waiting to retry"
        if blocked:
            return EngageGate(False, False, blocked)
        if self.mode == "auto":
            return EngageGate(True, False, "")
        if self.mode == "ground":
            waiting = "" if self.requested else "waiting for `companion engage` (ground station)"
            return EngageGate(self.requested, False, waiting)
        return EngageGate(False, True, "")

    def _blocked(self, telemetry: AutopilotTelemetry, now_s: float) -> str:
        heartbeat = self.heartbeat_problem(telemetry, now_s)
        if heartbeat:
            return heartbeat
        status, report = telemetry.status, telemetry.mode_report
        assert status is not None
        resumable = report is not None and report.value.resumes_offboard
        if status.value.failsafe and not resumable:
            return (
                f"PX4 is in a failsafe (heartbeat system status {status.value.system_status}, "
                f"mode {status.value.mode.name}): not engaging"
            )
        if self._requires_airborne:
            armed, in_air = telemetry.armed, telemetry.in_air
            if not (armed is not None and armed.value and in_air is not None and in_air.value):
                return "the vehicle is not armed and in the air"
        return ""

    async def before_step(
        self,
        commander: Commander,
        hover: Callable[[], ControlOutput],
        telemetry: AutopilotTelemetry,
        now_s: float,
        health: HealthMonitor,
    ) -> EngageGate:
        """Each tick before the health step: carry out a `companion disengage` (zero velocity
        `hover()`, then Hold), and this tick's gate; a new reason for not engaging is logged."""
        if self.disengage_requested:
            self.disengage_requested = False
            if await commander.disengage(hover()):
                self._events("disengaged", "info", "operator: vehicle switched to HOLD")
        gate = self.gate(telemetry, now_s, commander.may_engage(now_s))
        if gate.waiting != self._waiting and health.state is HealthState.STARTING:
            self._waiting = gate.waiting  # the log says why the drone did not engage
            if gate.waiting and "OFFBOARD request" not in gate.waiting:
                self._events("not engaging", "info", gate.waiting)
        return gate

    def after_step(self, decision: HealthDecision, commander: Commander) -> None:
        """After the health step: an ended engagement needs a new one; a new one may fail safe."""
        if decision.transition is None or decision.state is HealthState.ACTIVE:
            return
        if decision.state in (HealthState.PILOT, HealthState.FAILSAFE):
            self.ended()
        elif decision.state is HealthState.STARTING:
            commander.rearm()

    def ended(self) -> None:
        """The engagement ended (takeover, failsafe, disengage): "ground" needs a new engage."""
        self.requested = False

    def command(
        self, command: str, state: HealthState, reason: str, offboard: OffboardState
    ) -> dict[str, Any]:
        """Answer a control-socket command; sets the requests the daemon acts on next tick."""
        base = {"engage_mode": self.mode, "state": state.value, "offboard": offboard.value}
        if command == "status":
            return {"ok": True, "message": reason or state.value, **base}
        if command == "disengage":
            self.requested = False
            if state in COMMANDING:
                self.disengage_requested = True
                self._events("disengage", "info", "operator: companion disengage")
                return {"ok": True, "message": "disengaging: zero velocity, then Hold", **base}
            return {"ok": True, "message": "not engaged: nothing to do", **base}
        return self._engage(state, base)

    def _engage(self, state: HealthState, base: dict[str, Any]) -> dict[str, Any]:
        refusals = {
            "operator": 'engage = "operator": the pilot or ground station engages by switching '
            "the vehicle to OFFBOARD",
            "auto": 'engage = "auto": the daemon engages by itself',
            "never": 'engage = "never": this daemon never commands',
        }
        if self.mode in refusals:
            return {"ok": False, "message": refusals[self.mode], **base}
        if state in COMMANDING:
            return {"ok": True, "message": "already engaged", **base}
        if state is HealthState.STOPPING:
            return {"ok": False, "message": "the daemon is stopping", **base}
        self.requested = True
        self._events("engage requested", "info", "operator: companion engage")
        return {"ok": True, "message": "engage requested: OFFBOARD once healthy", **base}
