"""`swarm-sim hil --autopilot px4-sitl` in small: two unmodified daemons, each flying its own real
PX4 (SITL + SIH) in the shared world, for 10 s after the last engaged.

The harness starts its own two PX4 instances (its own loopback-only namespace, apart from the
session's), takes both off to their spawn altitudes as a pilot would, and hands each daemon the
common goal as `migration_point_global`. Judged: both engaged (PX4 reported OFFBOARD), both
moved towards the goal (PX4's own position, placed in the world), both daemons ended with exit
0 and PX4 in Hold. Lateness is reported, not asserted (CI machines are shared). 35-45 s here.

In the default run since 2026-12-02 (it was opt-in after one of three loaded full-suite runs
timed out in the harness's take-off: it ran then beside the session-scoped PX4 pair of
tests/px4, which now stops when that folder is done; here, in tests/sim_harness/hil, it runs
after it). Skipped only where real PX4 is unavailable (no SITL build, no network namespace).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sim_harness.hil.px4_results import write_px4_results
from sim_harness.hil.px4_sitl import unavailable_reason
from sim_harness.hil.px4_swarm import Px4Swarm
from sim_harness.hil.swarm import HilConfig
from sim_harness.learning.shipped import SHIPPED_MODEL_PATH
from sim_harness.sim.scenarios import ScenarioConfig, build_scenario

FLIGHT_S = 10.0
# Each drone's distance to the goal shrinks by at least this much in the 10 s: the in-process
# controller on the same seed closes 4.4 m (the shipped flock is slow: ~0.5 m/s), with real PX4
# 2.8 m was measured here (PX4's smoothed velocity tracking; the first second goes to the flock).
TOWARDS_GOAL_M = 1.5


def test_two_daemons_with_real_px4_engage_and_fly_towards_the_goal(tmp_path: Path) -> None:
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(f"real PX4 not available: {reason}")
    scenario = build_scenario(
        ScenarioConfig(name="common", n_agents=2, seed=1011, duration_s=FLIGHT_S)
    )
    swarm = Px4Swarm(scenario, SHIPPED_MODEL_PATH, tmp_path, HilConfig(engage_timeout_s=40.0))
    run = swarm.run(FLIGHT_S)
    doc = write_px4_results(swarm, run, tmp_path)
    logs = {d.setup.drone_id: d.daemon_log_tail(8) for d in swarm.drones}
    assert run.aborted is None, (run.aborted, logs)
    assert all(e is not None for e in run.engage_s), logs
    goal = scenario.goals[0]
    pos = run.log.pos_world_enu
    closer = np.linalg.norm(pos[0] - goal, axis=1) - np.linalg.norm(pos[-1] - goal, axis=1)
    assert np.all(closer >= TOWARDS_GOAL_M), closer
    for drone in doc["drones"]:
        assert drone["exit_code"] == 0, logs
        assert drone["final_mode"] == "HOLD"
        assert "migration point" in drone["health_events"]
    assert json.loads((tmp_path / "hil.json").read_text())["autopilot"] == "px4-sitl"
    print("lateness:", doc["lateness"], "px4:", doc["px4"])
