"""Fly a scenario with a controller until the flock arrives or the time limit; log every step.

The loop, per control step (10 Hz by default): observe (and, for a controller that declares the
`"cameras"` sense, render every agent's six views at this instant: the capture time) -> controller
-> `substeps` physics steps of the vehicle model (contacts checked at every physics step) ->
metrics. The log holds one row per control tick, from t = 0 to the final state: positions,
velocities, attitudes, the setpoint issued at that tick (NaN on the final row: nothing is issued
after the run ends) and the per-step metrics.
`stage_time_s` adds up the wall time of each stage over the flight: `render`, `control` (the
controller's `command`, inference included), `physics`, plus what a controller reports itself
through `stage_time_s()` (the CNN controller: `inference`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim_harness.errors import ControllerError
from sim_harness.sim import metrics
from sim_harness.sim.controllers import (
    SENSE_CAMERAS,
    SENSE_NEIGHBOURS,
    Controller,
    Observation,
    OwnState,
    sense_neighbours,
)
from sim_harness.sim.progress import progress_bar
from sim_harness.sim.render import PyBulletRenderer, Renderer
from sim_harness.sim.scenarios import Scenario
from sim_harness.sim.vehicle import VehicleModel, VehicleParams
from sim_harness.sim.world import SimRates, World

FloatArray = NDArray[np.float64]


@dataclass
class FlightLog:
    """Per-step record of one flight; T rows (control ticks), N agents."""

    scenario: Scenario
    controller: str
    rates: SimRates
    time_s: FloatArray  # (T,)
    pos_world_enu: FloatArray  # (T, N, 3)
    vel_world_enu: FloatArray  # (T, N, 3)
    q_world_body: FloatArray  # (T, N, 4) wxyz
    setpoint_world_enu: FloatArray  # (T, N, 3); last row NaN
    d_min_m: FloatArray  # (T,)
    d_max_m: FloatArray  # (T,)
    order: FloatArray  # (T,)
    contacts: list[tuple[int, int, int]] = field(default_factory=list)  # (step, i, j)
    stop_reason: str = "time_limit"
    wall_time_s: float = 0.0
    stage_time_s: dict[str, float] = field(default_factory=dict)  # stage -> summed wall time

    @property
    def n_steps(self) -> int:
        return int(self.time_s.shape[0])


def _observe(
    state_pos: FloatArray,
    state_vel: FloatArray,
    state_q: FloatArray,
    t: float,
    scenario: Scenario,
    controller: Controller,
    images: NDArray[np.uint8] | None = None,
) -> Observation:
    own = OwnState(
        t, state_pos.copy(), state_vel.copy(), state_q.copy(), scenario.migration_points.copy()
    )
    neighbours = None
    if SENSE_NEIGHBOURS in controller.senses:
        neighbours = sense_neighbours(own.pos_world_enu, scenario.config.flocking.r_max_m)
    return Observation(own=own, neighbours=neighbours, images=images)


def _controller_stage_times(controller: Controller) -> dict[str, float]:
    """What the controller timed itself (`stage_time_s()`, optional), as float seconds."""
    report = getattr(controller, "stage_time_s", None)
    if not callable(report):
        return {}
    return {str(k): float(v) for k, v in report().items()}


def has_arrived(scenario: Scenario, pos_world_enu: FloatArray) -> bool:
    """True when each arrival goal's group centroid is within the arrival radius."""
    if not scenario.has_goal:
        return False
    dist = metrics.group_centroid_distances(pos_world_enu, scenario.groups, scenario.goals)
    return bool(np.all(dist[scenario.arrival_goals] <= scenario.config.arrival_radius_m))


def fly(
    scenario: Scenario,
    controller: Controller,
    rates: SimRates | None = None,
    vehicle_params: VehicleParams | None = None,
    progress: bool = False,
    renderer: Renderer | None = None,
    stop_when: Callable[[FloatArray, float], str | None] | None = None,
    progress_label: str | None = None,
    progress_lines: bool | None = None,
    stop_at_arrival: bool = True,
) -> FlightLog:
    """Run one flight; returns its log (use `summarize` for the paper's numbers).

    `progress` shows a bar named `progress_label` (default: scenario / controller); plain lines
    instead when stderr is not a terminal or `progress_lines` (see `sim_harness.sim.progress`).

    `stop_when(positions, t_s)`, checked after every control step, ends the flight early when it
    returns a reason (which becomes the log's `stop_reason`); arrival ends it too, unless
    `stop_at_arrival` is False (then only `stop_when` and the time limit do).

    A controller that declares the `"cameras"` sense gets every agent's 64x384 image each control
    step, rendered with `renderer` (default: a `PyBulletRenderer`); no other controller pays for it.
    """
    rates = rates or SimRates()
    cameras = SENSE_CAMERAS in controller.senses
    if cameras and renderer is None:
        renderer = PyBulletRenderer()
    stage = {"render": 0.0, "control": 0.0, "physics": 0.0}
    n = scenario.n_agents
    vehicle = VehicleModel(
        vehicle_params or VehicleParams(), scenario.initial_pos_world_enu, scenario.initial_yaw_rad
    )
    max_steps = math.ceil(scenario.config.time_limit_s * rates.control_hz - 1e-9)
    rows: dict[str, list[FloatArray]] = {k: [] for k in ("pos", "vel", "q", "sp")}
    contacts: list[tuple[int, int, int]] = []
    controller.reset(n)
    stop_reason = "time_limit"
    started = time.perf_counter()
    with (
        World(n) as world,
        progress_bar(
            total=max_steps,
            desc=progress_label or f"{scenario.config.name} / {controller.name}",
            enabled=progress,
            lines=progress_lines,
            unit="step",
            leave=False,
        ) as bar,
    ):
        s = vehicle.state

        def record(setpoint: FloatArray) -> None:
            rows["pos"].append(s.pos_world_enu.copy())
            rows["vel"].append(s.vel_world_enu.copy())
            rows["q"].append(vehicle.q_world_body.copy())
            rows["sp"].append(setpoint)

        for step in range(max_steps):
            images = None
            if cameras and renderer is not None:
                t0 = time.perf_counter()
                images = renderer.render(world, s.pos_world_enu, vehicle.q_world_body)
                stage["render"] += time.perf_counter() - t0
            obs = _observe(
                s.pos_world_enu,
                s.vel_world_enu,
                vehicle.q_world_body,
                step * rates.control_dt_s,
                scenario,
                controller,
                images,
            )
            t0 = time.perf_counter()
            setpoint = np.asarray(controller.command(obs), dtype=np.float64)
            stage["control"] += time.perf_counter() - t0
            if setpoint.shape != (n, 3):
                raise ControllerError(
                    f"controller {controller.name!r} returned setpoints of shape "
                    f"{setpoint.shape}; expected ({n}, 3)"
                )
            if not np.all(np.isfinite(setpoint)):
                raise ControllerError(
                    f"controller {controller.name!r} returned non-finite setpoints at "
                    f"t = {obs.own.time_s:.1f} s"
                )
            record(setpoint)
            touching: set[tuple[int, int]] = set()
            t0 = time.perf_counter()
            for _ in range(rates.substeps):
                vehicle.step(setpoint, rates.physics_dt_s)
                if world.may_touch(s.pos_world_enu):
                    touching.update(world.contacts(s.pos_world_enu, vehicle.q_world_body))
            contacts.extend((step + 1, i, j) for i, j in sorted(touching))
            world.set_poses(s.pos_world_enu, vehicle.q_world_body)
            stage["physics"] += time.perf_counter() - t0
            bar.update()
            if stop_at_arrival and has_arrived(scenario, s.pos_world_enu):
                stop_reason = "arrived"
                break
            if stop_when is not None:
                reason = stop_when(s.pos_world_enu, (step + 1) * rates.control_dt_s)
                if reason is not None:
                    stop_reason = reason
                    break
        bar.set_postfix_str(stop_reason, refresh=False)  # the closing line says why it ended
        record(np.full((n, 3), np.nan))  # final state: nothing is issued after the run
    wall = time.perf_counter() - started
    pos = np.stack(rows["pos"])
    vel = np.stack(rows["vel"])
    d_min, d_max = metrics.distance_extremes(pos)
    return FlightLog(
        scenario=scenario,
        controller=controller.name,
        rates=rates,
        time_s=np.arange(pos.shape[0]) * rates.control_dt_s,
        pos_world_enu=pos,
        vel_world_enu=vel,
        q_world_body=np.stack(rows["q"]),
        setpoint_world_enu=np.stack(rows["sp"]),
        d_min_m=d_min,
        d_max_m=d_max,
        order=metrics.order_parameter(vel),
        contacts=contacts,
        stop_reason=stop_reason,
        wall_time_s=wall,
        stage_time_s={**stage, **_controller_stage_times(controller)},
    )


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def summarize(
    log: FlightLog, collision_threshold_m: float = metrics.COLLISION_THRESHOLD_M
) -> dict[str, Any]:
    """The run's numbers as a JSON-ready dict; deterministic (no wall-clock values)."""
    cfg = log.scenario.config
    dist = metrics.pair_distances(log.pos_world_enu)  # (T, P)
    i_idx, j_idx = np.triu_indices(log.scenario.n_agents, k=1)
    close = dist < collision_threshold_m
    close_steps = np.flatnonzero(close.any(axis=1)) if dist.shape[1] else np.array([], int)
    close_pairs = sorted({(int(i_idx[p]), int(j_idx[p])) for p in np.flatnonzero(close.any(0))})
    arrived = log.stop_reason == "arrived"
    speeds = np.linalg.norm(log.vel_world_enu, axis=-1)
    with np.errstate(all="ignore"):
        d_min_all = float(np.nanmin(log.d_min_m)) if cfg.n_agents > 1 else math.nan
        d_max_all = float(np.nanmax(log.d_max_m)) if cfg.n_agents > 1 else math.nan
        order_mean = float(np.nanmean(log.order)) if cfg.n_agents > 1 else math.nan
    return {
        "scenario": cfg.name,
        "controller": log.controller,
        "n_agents": cfg.n_agents,
        "seed": cfg.seed,
        "v_max_mps": cfg.flocking.v_max_mps,
        "r_max_m": cfg.flocking.r_max_m,
        "time_limit_s": cfg.time_limit_s,
        "physics_hz": log.rates.physics_hz,
        "control_hz": log.rates.control_hz,
        "steps": log.n_steps - 1,
        "duration_s": round(float(log.time_s[-1]), 6),
        "stop_reason": log.stop_reason,
        "arrived": arrived,
        "arrival_time_s": round(float(log.time_s[-1]), 6) if arrived else None,
        "d_min_m": _finite_or_none(d_min_all),
        "d_max_m": _finite_or_none(d_max_all),
        "collision_threshold_m": collision_threshold_m,
        "collision_free": len(close_steps) == 0,
        "steps_below_threshold": len(close_steps),
        "first_below_threshold_s": (
            float(log.time_s[close_steps[0]]) if len(close_steps) else None
        ),
        "pairs_below_threshold": [list(p) for p in close_pairs],
        "physical_contacts": len(log.contacts),
        "contact_pairs": [list(p) for p in sorted({(i, j) for _, i, j in log.contacts})],
        "flock_split": bool(np.nanmax(log.d_max_m) >= cfg.flocking.r_max_m)
        if cfg.n_agents > 1
        else False,
        "order_mean": _finite_or_none(order_mean),
        "order_final": _finite_or_none(float(log.order[-1])),
        "mean_speed_mps": float(speeds.mean()),
        # towards the goal whose arrival ends the run (the majority's, with opposing goals)
        "centroid_progress_m": (
            metrics.centroid_progress(
                log.pos_world_enu, log.scenario.goals[log.scenario.arrival_goals[0]]
            )
            if log.scenario.has_goal
            else None
        ),
    }


def save_flight(log: FlightLog, out_dir: Path) -> dict[str, Path]:
    """Write `steps.npz` (per-step arrays), `summary.json` and `timing.json` into `out_dir`."""
    out_dir.mkdir(parents=True, exist_ok=True)
    sc = log.scenario
    paths = {
        "steps": out_dir / "steps.npz",
        "summary": out_dir / "summary.json",
        "timing": out_dir / "timing.json",
    }
    np.savez_compressed(
        paths["steps"],
        time_s=log.time_s,
        pos_world_enu=log.pos_world_enu,
        vel_world_enu=log.vel_world_enu,
        q_world_body_wxyz=log.q_world_body,
        setpoint_world_enu=log.setpoint_world_enu,
        d_min_m=log.d_min_m,
        d_max_m=log.d_max_m,
        order=log.order,
        contacts_step_i_j=np.asarray(log.contacts, dtype=np.int64).reshape(-1, 3),
        migration_points=sc.migration_points,
        groups=sc.groups,
        goals=sc.goals,
    )
    paths["summary"].write_text(json.dumps(summarize(log), indent=2) + "\n")
    simulated = float(log.time_s[-1])
    timing = {
        "wall_time_s": log.wall_time_s,
        "simulated_s": simulated,
        "real_time_factor": simulated / log.wall_time_s if log.wall_time_s > 0 else None,
        "stage_time_s": log.stage_time_s,
    }
    paths["timing"].write_text(json.dumps(timing, indent=2) + "\n")
    return paths
