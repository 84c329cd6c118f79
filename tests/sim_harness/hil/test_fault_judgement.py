"""How fault outcomes are judged from the PX4 emulator's records (pure logic, recorded inputs).

The HIL swarm tests fly the real thing; these pin the judgement itself, including the starved
machine that CI is: every daemon's setpoints stop for a second at a time, PX4's offboard-loss
failsafe puts vehicles in Hold before a fault fires, and a response time then says nothing about
the daemon.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from companion.flight_log import TOPIC_SETPOINT
from companion.recorder import FlightRecorder, RecorderConfig
from sim_harness.hil.faults import FaultRunner, load_plan
from sim_harness.hil.plans import PLANS_DIR
from sim_harness.hil.px4_logic import ModeChange, Px4Mode
from sim_harness.hil.px4_messages import SetpointRecord

OFF, HOLD = Px4Mode.OFFBOARD, Px4Mode.HOLD
LOST = "offboard setpoints lost"


def _setpoints(times: np.ndarray, speed: float) -> list[SetpointRecord]:
    return [SetpointRecord(float(t), 1, 0, speed, 0.0, 0.0, 0.0, 0.0) for t in times]


@dataclass
class _Px4:
    """The emulator's records, as `FaultRunner` reads them (all on one clock, origin 0)."""

    sent: list[SetpointRecord]
    modes: list[ModeChange]
    clock_origin_s: float = 0.0
    config: Any = field(
        default_factory=lambda: SimpleNamespace(px4=SimpleNamespace(offboard_loss_timeout_s=1.0))
    )

    def setpoints(self) -> list[SetpointRecord]:
        return self.sent

    def mode_changes(self) -> list[ModeChange]:
        return self.modes


@dataclass
class _Drone:
    px4: _Px4
    flights_dir: Path
    exit_code: int | None = 0
    killed_by: str | None = None

    def config_document(self) -> dict[str, Any]:
        return {"daemon": {"failsafe_after_s": 3.0, "rate_hz": 10.0, "shutdown_timeout_s": 5.0}}


def _ticking(start_s: float, end_s: float, speed: float = 1.0) -> list[SetpointRecord]:
    return _setpoints(np.arange(start_s, end_s, 0.1), speed)


def _stalled(start_s: float, end_s: float) -> list[SetpointRecord]:
    """A starved daemon: a setpoint every 1.2 s."""
    return _setpoints(np.arange(start_s, end_s, 1.2), 1.0)


def _log(folder: Path) -> Path:
    folder.mkdir(parents=True)
    with FlightRecorder(RecorderConfig(directory=folder), drone_id="d") as recorder:
        recorder.record(TOPIC_SETPOINT, {"vel_ned": [1.0, 0.0, 0.0], "yaw_ned_rad": 0.0})
    return folder


def _judge(
    tmp_path: Path, drone1: _Drone, drone2: _Drone, rest: list[SetpointRecord]
) -> dict[str, Any]:
    """unplug_and_kill.toml's outcomes: drone1 unplugged at 6 s for 5 s, drone2 killed at 9 s."""
    plan = load_plan(PLANS_DIR / "unplug_and_kill.toml", 4)
    others = [_Drone(_Px4(rest, [ModeChange(0.0, HOLD, OFF, "DO_SET_MODE")]), tmp_path)] * 2
    runner = FaultRunner(plan, [drone1, drone2, *others])  # type: ignore[list-item]
    runner.fired = {plan.events[0]: 6.0, plan.events[1]: 9.0}
    return {o.event.kind: o for o in runner.outcomes()}


def _unplugged(hover_s: float, hold_s: float, ticks: list[SetpointRecord]) -> _Drone:
    sent = [s for s in ticks if s.t_s < hover_s] + _ticking(hover_s, hold_s, 0.0)
    modes = [
        ModeChange(0.0, HOLD, OFF, "DO_SET_MODE"),
        ModeChange(hold_s, OFF, HOLD, "DO_SET_MODE"),
    ]
    return _Drone(_Px4(sent, modes), Path("."))


def _killed(tmp_path: Path, modes: list[ModeChange]) -> _Drone:
    return _Drone(_Px4(_ticking(0.0, 9.0), modes), _log(tmp_path / "d2"), -9, "sigkill")


def test_a_timely_swarm_is_judged_on_its_time_bounds(tmp_path: Path) -> None:
    killed = _killed(
        tmp_path, [ModeChange(0, HOLD, OFF, "DO_SET_MODE"), ModeChange(10, OFF, HOLD, LOST)]
    )
    on_time = _judge(tmp_path, _unplugged(6.3, 9.3, _ticking(0, 30)), killed, _ticking(0, 30))
    assert on_time["camera_unplug"].passed and on_time["camera_unplug"].observed["timing"] == "met"
    kill = on_time["daemon_sigkill"]
    assert kill.passed and kill.observed["mode_at_fire"] == "OFFBOARD"
    assert kill.observed["hold_after_s"] == pytest.approx(1.0)
    # Hovering 1.5 s late while the rest of the swarm ticked on time: the daemon's own fault.
    late = _judge(tmp_path, _unplugged(7.5, 10.5, _stalled(0, 30)), killed, _ticking(0, 30))
    assert not late["camera_unplug"].passed
    assert late["camera_unplug"].observed["timing"] == "missed"


def test_a_starved_swarm_is_judged_on_its_end_state(tmp_path: Path) -> None:
    # PX4 had put drone2 in Hold at 8.9 s (its daemon starved): the kill finds it there.
    before = [ModeChange(0, HOLD, OFF, "DO_SET_MODE"), ModeChange(8.9, OFF, HOLD, LOST)]
    doc = _judge(
        tmp_path, _unplugged(7.5, 10.5, _stalled(0, 30)), _killed(tmp_path, before), _stalled(0, 30)
    )
    unplug, kill = doc["camera_unplug"], doc["daemon_sigkill"]
    assert unplug.passed and unplug.observed["timing"].startswith("not judged")
    assert kill.passed and kill.observed["mode_at_fire"] == "HOLD"
    assert kill.observed["hold_after_s"] == pytest.approx(-0.1)
    # Whatever the machine: a vehicle that is not in Hold at the end, or goes back to OFFBOARD
    # after its Hold, fails.
    back = [*before, ModeChange(9.5, HOLD, OFF, "offboard setpoints regained")]
    doc = _judge(
        tmp_path / "b", _unplugged(7.5, 10.5, _stalled(0, 30)), _killed(tmp_path / "b", back), []
    )
    assert not doc["daemon_sigkill"].passed
    drone1 = _unplugged(7.5, 10.5, _stalled(0, 30))
    drone1.px4.modes.append(ModeChange(12.0, HOLD, OFF, "DO_SET_MODE"))
    assert not _judge(tmp_path / "c", drone1, _killed(tmp_path / "c", before), [])[
        "camera_unplug"
    ].passed
