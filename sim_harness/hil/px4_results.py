"""The run folder of a HIL flight with real PX4: `results.write_results` plus PX4's side."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from sim_harness.hil.px4_drone import POSE_RATE_HZ
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.results import flight_log_stats, write_results
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN
from sim_harness.sim.rollout import FlightLog

if TYPE_CHECKING:
    from sim_harness.hil.px4_swarm import Px4Swarm
    from sim_harness.hil.swarm import HilRun


def write_px4_results(
    swarm: Px4Swarm, run: HilRun, out_dir: Path, compare: FlightLog | None = None
) -> dict[str, Any]:
    """The run folder as `results.write_results` writes it, with PX4's side: per-drone rows from
    PX4's heartbeats, pose gaps and the frame check in hil.json and report.md."""
    extra = {"autopilot": "px4-sitl", "px4": px4_summary(swarm)}
    doc = write_results(run, out_dir, compare, drones=drone_rows(swarm, run.engage_s), extra=extra)
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


def drone_rows(swarm: Px4Swarm, engage_s: list[float | None]) -> list[dict[str, Any]]:
    """Per drone: engagement, PX4's modes (from its heartbeats), take-off, its flight log."""
    t0 = swarm.flight_t0
    rows = []
    for drone, engaged in zip(swarm.drones, engage_s, strict=True):
        changes = drone.gcs.mode_changes()
        last = changes[-1].mode if changes else None
        rows.append(
            {
                "drone": drone.setup.drone_id,
                "engage_s_after_daemon_start": None if engaged is None else round(engaged, 2),
                "exit_code": drone.exit_code,
                "stopped_by_fault": None,
                "mode_history": [
                    {
                        "t_s": round(m.t_s - t0, 2),
                        "mode": m.mode.name if m.mode else str(m.custom_mode),
                        "reason": "PX4 heartbeat",
                    }
                    for m in changes
                ],
                "final_mode": last.name if last is not None else None,
                "ended_in_offboard": last is Px4Mode.OFFBOARD,
                "frames_sent": None,
                "frames_dropped": None,
                "camera_connections": None,
                "migration_point_global": drone.migration_point_global,
                "takeoff_s": None if drone.takeoff_s is None else round(drone.takeoff_s, 2),
                "px4_instance": drone.px4.spec.index,
                **flight_log_stats(drone.flights_dir),
            }
        )
    return rows


def px4_summary(swarm: Px4Swarm) -> dict[str, Any]:
    return {
        "pose_rate_hz": POSE_RATE_HZ,
        "pose_gap_max_ms": [round(g * 1e3, 1) for g in swarm.pose_gap_max_s],
        "world_steps_late_loop_behind": swarm.world_steps_behind,
        "world_steps_late_pose_stale": swarm.world_steps_pose_stale,
        "estimate_error_max_m": [round(e, 3) for e in swarm.estimate_error_max_m],
        "frame_check_m": [
            None if c is None else {"horizontal": round(c[0], 3), "up": round(c[1], 3)}
            for c in swarm.frame_check_m
        ],
        "world_origin": [
            DEFAULT_ORIGIN.lat_deg,
            DEFAULT_ORIGIN.lon_deg,
            DEFAULT_ORIGIN.alt_amsl_m,
        ],
    }
