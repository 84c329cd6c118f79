"""The run folder of a HIL flight with real PX4: `results.write_results` plus PX4's side."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from sim_harness.hil.results import write_results
from sim_harness.sim.rollout import FlightLog

if TYPE_CHECKING:
    from sim_harness.hil.px4_swarm import Px4Swarm
    from sim_harness.hil.swarm import HilRun


def write_px4_results(
    swarm: Px4Swarm, run: HilRun, out_dir: Path, compare: FlightLog | None = None
) -> dict[str, Any]:
    """The run folder as `results.write_results` writes it, with PX4's side: per-drone rows from
    PX4's heartbeats, pose gaps and the frame check in hil.json and report.md."""
    extra = {"autopilot": "px4-sitl", "px4": swarm.px4_summary()}
    doc = write_results(run, out_dir, compare, drones=swarm.drone_rows(run.engage_s), extra=extra)
    px4 = doc["px4"]
    lines = [
        "",
        "## Real PX4",
        "",
        "Each drone: PX4 SITL (commander, navigator, EKF2, multicopter controllers) flying its own "
        "SIH quadrotor, started at its spawn point's ground position, armed and taken off to the "
        "spawn altitude by the harness's ground station before its daemon started; the daemon "
        "got the goal as `migration_point_global`. A world step counts as late also when a "
        f"drone's newest PX4 pose was older than {1e3 * swarm.config.late_physics_s:.0f} ms + "
        "one pose period.",
        "",
        f"- late world steps: loop behind {px4['world_steps_late_loop_behind']}, a PX4 pose "
        f"stale {px4['world_steps_late_pose_stale']} (a step can be both)",
        f"- longest gap between PX4 poses (ms, per drone): {px4['pose_gap_max_ms']}",
        "- PX4's GLOBAL_POSITION_INT minus SIH's vehicle after take-off (m; the estimate's "
        "error: simulated GPS noise): "
        f"{px4['frame_check_m']}",
        "- PX4's horizontal position estimate (LOCAL_POSITION_NED from the start point) vs "
        f"SIH's vehicle, worst during the flight (m): {px4['estimate_error_max_m']}",
        f"- take-off (s, per drone): {[d['takeoff_s'] for d in doc['drones']]}",
        "",
    ]
    with (out_dir / "report.md").open("a") as report:
        report.write("\n".join(lines))
    return doc
