"""What a HIL flight is judged by: the simulated flight's summary plus, per drone, what its
daemon did (from its MCAP log and its PX4 emulator's records), and the harness's lateness.

Writes into the run folder: `summary.json`, `steps.npz`, `timing.json` and figures as `swarm-sim
fly` does, `hil.json` (drones, lateness, faults, comparison) and `report.md`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from companion.flight_log import TOPIC_FRAME, TOPIC_HEALTH, TOPIC_SETPOINT, LogReader
from sim_harness.hil.camera_side import CaptureStats
from sim_harness.hil.drone import HilDrone, unit_nice
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.swarm import HilRun
from sim_harness.sim.plots import save_comparison_figure, save_flight_figures
from sim_harness.sim.rollout import FlightLog, save_flight, summarize

COMPARED = (
    "arrived",
    "arrival_time_s",
    "d_min_m",
    "d_max_m",
    "order_mean",
    "mean_speed_mps",
    "steps_below_threshold",
    "physical_contacts",
)


def _percentiles_ms(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50_ms": None, "p99_ms": None}
    array = np.asarray(values) * 1e3
    return {
        "p50_ms": round(float(np.percentile(array, 50)), 2),
        "p99_ms": round(float(np.percentile(array, 99)), 2),
    }


def flight_log_stats(folder: Path) -> dict[str, Any]:
    """Tick latency, image age, hover and failsafe episodes from a daemon's MCAP files."""
    tick, age, actions = [], [], []
    frames, events, readable = 0, [], True
    for path in sorted(folder.glob("*.mcap")):
        try:
            for message in LogReader(path).messages():
                if message.topic == TOPIC_SETPOINT:
                    data = message.json()
                    actions.append(str(data["action"]))
                    if data.get("tick_latency_s") is not None:
                        tick.append(float(data["tick_latency_s"]))
                    if data.get("image_age_s") is not None:
                        age.append(float(data["image_age_s"]))
                elif message.topic == TOPIC_FRAME:
                    frames += 1
                elif message.topic == TOPIC_HEALTH:
                    events.append(message.json().get("event", "?"))
        except Exception:  # an unreadable log is itself the finding
            readable = False
    hover_episodes = sum(
        1 for a, b in zip(["", *actions], actions, strict=False) if b == "hover" and a != "hover"
    )
    return {
        "log_files": len(list(folder.glob("*.mcap"))),
        "log_readable": readable,
        "tick_latency": _percentiles_ms(tick),
        "image_age": _percentiles_ms(age),
        "stitched_images": frames,
        "hover_ticks": actions.count("hover"),
        "hover_episodes": hover_episodes,
        "failsafe": any("failsafe" in e for e in events),
        "health_events": events,
    }


def drone_summary(
    drone: HilDrone, engage_s: float | None, flight_t0_px4: float, cameras: CaptureStats
) -> dict[str, Any]:
    """One drone's row: engagement, modes (flight time, s), frames, and its flight log."""
    px4 = drone.px4
    i = drone.setup.index
    return {
        "drone": drone.setup.drone_id,
        "engage_s_after_daemon_start": None if engage_s is None else round(engage_s, 2),
        "exit_code": drone.exit_code,
        "stopped_by_fault": drone.killed_by,
        "mode_history": [
            {"t_s": round(m.t_s - flight_t0_px4, 2), "mode": m.new.name, "reason": m.reason}
            for m in px4.mode_changes()
        ],
        "final_mode": px4.mode.name,
        "ended_in_offboard": px4.mode is Px4Mode.OFFBOARD,
        "frames_sent": cameras.frames_sent[i] if cameras.frames_sent else None,
        "frames_dropped": cameras.frames_dropped[i] if cameras.frames_dropped else None,
        "camera_connections": cameras.connections[i] if cameras.connections else None,
        "migration_point_local_enu": (
            None
            if drone.setup.migration_point_local_enu is None
            else [round(float(c), 3) for c in drone.setup.migration_point_local_enu]
        ),
        **flight_log_stats(drone.flights_dir),
    }


def write_results(
    run: HilRun,
    out_dir: Path,
    compare: FlightLog | None = None,
    drones: list[dict[str, Any]] | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the run folder; returns the `hil.json` document. `drones`: the per-drone rows when
    they come from elsewhere than `run.drones` (real PX4: `px4_swarm`); `extra`: more keys
    (`autopilot` names what flew the vehicles, "emulator" by default)."""
    save_flight(run.log, out_dir)
    save_flight_figures(run.log, out_dir)
    summary = summarize(run.log)
    if drones is None:
        drones = [
            drone_summary(d, e, t0, run.cameras)
            for d, e, t0 in zip(run.drones, run.engage_s, run.flight_t0_px4, strict=True)
        ]
    doc: dict[str, Any] = {
        "autopilot": "emulator",
        **(extra or {}),
        "valid": run.aborted is None and run.lateness.valid,
        "aborted": run.aborted,
        "summary": summary,
        "lateness": run.lateness.summary(),
        "priorities": {"harness_nice": run.harness_nice, "daemon_nice": unit_nice()},
        "renderer": run.renderer,
        "drones": drones,
    }
    if run.faults is not None:
        outcomes = run.faults.outcomes()
        doc["faults"] = {
            "plan": run.faults.plan.source,
            "passed": all(o.passed for o in outcomes),
            "outcomes": [
                {
                    "event": o.event.label,
                    "expected": o.expected,
                    "passed": o.passed,
                    "observed": _jsonable(o.observed),
                }
                for o in outcomes
            ],
        }
    if compare is not None:
        ref = summarize(compare)
        doc["compare"] = {"in_process": {k: ref[k] for k in COMPARED}}
        save_flight(compare, out_dir / "in_process")
        title = f"{summary['scenario']}, N = {summary['n_agents']}"
        save_comparison_figure(
            {title: {"in-process CNN": [compare], "HIL daemons": [run.log]}},
            out_dir / "compare.png",
        )
        save_overlay(run.log, compare, out_dir / "overlay.png")
        doc["compare"]["differences"] = differences(doc, run)
    (out_dir / "hil.json").write_text(json.dumps(_jsonable(doc), indent=2) + "\n")
    (out_dir / "report.md").write_text(report_text(doc))
    return doc


def save_overlay(hil: FlightLog, ref: FlightLog, path: Path) -> Path:
    """Both flights' trajectories in one top view: HIL solid, in-process dashed, per drone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5), dpi=90)
    colours = plt.get_cmap("tab10")
    for i in range(hil.scenario.n_agents):
        ax.plot(*hil.pos_world_enu[:, i, :2].T, "-", color=colours(i % 10), lw=1.4)
        ax.plot(*ref.pos_world_enu[:, i, :2].T, "--", color=colours(i % 10), lw=1.0)
    for goal in hil.scenario.goals:
        ax.annotate(f"goal ({goal[0]:+.0f}, {goal[1]:+.0f}) m", xy=(0.99, 0.02),
                    xycoords="axes fraction", ha="right", color="0.4")  # fmt: skip
    ax.plot([], [], "k-", label="HIL daemons")
    ax.plot([], [], "k--", label="in-process CNN")
    ax.set(xlabel="east (m)", ylabel="north (m)", aspect="equal", title="top view, same seed")
    ax.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def differences(doc: dict[str, Any], run: HilRun) -> list[str]:
    """What differs between the two flights by construction, with this run's sizes."""
    engaged = [e for e in run.engage_s if e is not None]
    ages = [d["image_age"]["p50_ms"] for d in doc["drones"] if d["image_age"]["p50_ms"]]
    hovers = sum(d["hover_episodes"] for d in doc["drones"])
    s, ref = doc["summary"], doc["compare"]["in_process"]
    out = [
        f"start: the HIL flight's t = 0 is when the last daemon engaged; the first had engaged "
        f"{max(engaged) - min(engaged):.1f} s earlier and was already flying"
        if engaged
        else "start: no daemon engaged",
        f"latency: each daemon acts on an image {np.median(ages) if ages else float('nan'):.0f} "
        "ms old at the median (transfer and stitching; the in-process controller sees images "
        "rendered at the control instant), and its setpoint reaches the vehicle through MAVSDK "
        "and the emulator's 50 Hz loop",
        f"hover episodes: {hovers} in all (stale or incomplete images; in-process: none by "
        "construction)",
        f"lateness: {'inside' if doc['lateness']['valid'] else 'OUTSIDE'} the thresholds",
    ]
    if s["d_min_m"] is not None and ref["d_min_m"] is not None:
        out.append(
            f"closest pair {s['d_min_m']:.2f} m vs {ref['d_min_m']:.2f} m; single flights are "
            "chaotic (a 1e-6 m/s change of the outputs moved a seed's closest pair by 0.2 m): "
            "compare over seeds (benchmarks/hil_vs_inprocess.py)"
        )
    return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2f}"
    return str(value)


def report_text(doc: dict[str, Any]) -> str:
    s, lat = doc["summary"], doc["lateness"]
    verdict = "VALID" if doc["valid"] else "INVALID (not a result)"
    lines = [
        f"# HIL flight: {s['scenario']}, N = {s['n_agents']}, seed {s['seed']}: {verdict}",
        "",
    ]
    if doc["aborted"]:
        lines += [f"The flight did not run: {doc['aborted']}", ""]
    lines += [
        "Every drone is the unmodified `companion run --config FILE` daemon, fed by six pty "
        "cameras rendered from the shared world and flying through "
        + (
            "its own real PX4 (SITL, flying PX4's own quadrotor model SIH; the world places each "
            "drone where its PX4 reports it)."
            if doc.get("autopilot") == "px4-sitl"
            else "its own PX4 emulator."
        ),
        "",
        "## Harness lateness",
        "",
        f"- physics steps late (> 20 ms behind the wall clock): {lat['physics_late']} of "
        f"{lat['physics_steps']} "
        f"({100 * lat['physics_late_fraction']:.2f} %), worst {lat['physics_max_behind_ms']} ms",
        f"- captures late: {lat['captures_late']} of {lat['captures']} "
        f"({100 * lat['captures_late_fraction']:.2f} %), worst {lat['capture_max_late_ms']} ms; "
        f"render p50 {lat['render_ms_p50']} ms, p99 {lat['render_ms_p99']} ms per drone",
        f"- camera frames dropped: {lat['frames_dropped']} of "
        f"{lat['frames_sent'] + lat['frames_dropped']}",
        f"- threshold: {100 * lat['threshold_fraction']:.1f} % for each; this run is "
        f"{'inside' if lat['valid'] else 'OUTSIDE'} it.",
        f"- priorities: harness nice {doc['priorities']['harness_nice']}, daemons nice "
        f"{doc['priorities']['daemon_nice']} (the unit's `Nice=`); renderer {doc['renderer']}",
        "",
        "## Flight",
        "",
        "| metric | HIL daemons |" + (" in-process CNN |" if "compare" in doc else ""),
        "|---|---|" + ("---|" if "compare" in doc else ""),
    ]
    for key in COMPARED:
        row = f"| {key} | {_cell(s[key])} |"
        if "compare" in doc:
            row += f" {_cell(doc['compare']['in_process'][key])} |"
        lines.append(row)
    lines += [
        "",
        "## Drones",
        "",
        "| drone | engaged after (s) | tick p50/p99 (ms) | image age p50/p99 (ms) | frames sent "
        "/ dropped | hover episodes | failsafe | final mode | exit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for d in doc["drones"]:
        tick, age = d["tick_latency"], d["image_age"]
        lines.append(
            f"| {d['drone']} | {_cell(d['engage_s_after_daemon_start'])} | "
            f"{_cell(tick['p50_ms'])} / {_cell(tick['p99_ms'])} | "
            f"{_cell(age['p50_ms'])} / {_cell(age['p99_ms'])} | "
            f"{d['frames_sent']} / {d['frames_dropped']} | {d['hover_episodes']} | "
            f"{'yes' if d['failsafe'] else 'no'} | {d['final_mode']} | {_cell(d['exit_code'])} |"
        )
    if "faults" in doc:
        lines += ["", "## Fault plan", ""]
        for o in doc["faults"]["outcomes"]:
            seen = ", ".join(f"{k} {_cell(v)}" for k, v in o["observed"].items())
            lines.append(
                f"- **{'PASS' if o['passed'] else 'FAIL'}** {o['event']}: expected "
                f"{o['expected']}; observed {seen}"
            )
    if "compare" in doc:
        lines += ["", "## HIL against the in-process CNN: what differs", ""]
        lines += [f"- {line}" for line in doc["compare"].get("differences", [])]
    figures = ["flight.png"] + (["compare.png", "overlay.png"] if "compare" in doc else [])
    lines += ["", *[f"![{f}]({f})" for f in figures], ""]
    return "\n".join(lines)
