"""One dataset run: spawn, constant cone velocities flown through the vehicle model, samples.

Each control step (0.1 s) records, for every agent, the stitched 64x384 image and the teacher's
Reynolds command (separation + cohesion, no migration) in world ENU and in the agent's body frame
FLU, with the attitude at the moment the image is taken.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX
from companion.flocking import FlockingParams, pairwise_offsets, reynolds_from_offsets
from companion.frames import quat_to_rotmat, world_to_body
from sim_harness.dataset.spec import TERMINATIONS, DatasetSpec, run_rng, sample_in_cone
from sim_harness.sim.render import Renderer
from sim_harness.sim.scenarios import spawn_positions
from sim_harness.sim.vehicle import VehicleModel, VehicleParams
from sim_harness.sim.world import World

FloatArray = NDArray[np.float64]


@dataclass
class RunTiming:
    """Seconds spent per stage while simulating one run."""

    render_s: float = 0.0
    physics_s: float = 0.0
    teacher_s: float = 0.0


@dataclass
class RunData:
    """All samples of one run; every array's first axis is the sample (step-major, then agent)."""

    split: str
    run_index: int
    termination: str
    migration_point_world_enu: FloatArray  # (3,)
    images: NDArray[np.uint8]  # (n, 64, 384)
    arrays: dict[str, NDArray[np.generic]]  # per-sample metadata and targets
    timing: RunTiming = field(default_factory=RunTiming)

    @property
    def n_samples(self) -> int:
        return int(self.images.shape[0])


def termination(
    spec: DatasetSpec, pos: FloatArray, mig: FloatArray, t_s: float, arrival: bool = True
) -> str | None:
    """Why the run ends in this state, or None (rules in `spec`'s docstring order); `arrival`
    False leaves the arrival rule out (an aggregation round that flies on through the arrival)."""
    if arrival and np.min(np.linalg.norm(pos - mig, axis=1)) < spec.arrival_radius_m:
        return "arrival"
    d = np.linalg.norm(pairwise_offsets(pos), axis=-1)
    iu = np.triu_indices(len(pos), k=1)
    if d[iu].min() < spec.collision_m:
        return "collision"
    if d[iu].max() > spec.dispersion_m:
        return "dispersion"
    if pos[:, 2].min() < spec.min_altitude_m:
        return "ground"
    if t_s >= spec.max_run_s - 1e-9:
        return "time_limit"
    return None


def initial_conditions(
    spec: DatasetSpec, split: str, run_index: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(spawn positions (N, 3), velocity commands (N, 3), migration point (3,)), world ENU."""
    rng = run_rng(spec, split, run_index)
    center = np.asarray(spec.spawn_center_m, dtype=np.float64)
    pos = spawn_positions(
        rng, spec.n_agents, spec.spawn_center_m, spec.spawn_side_m, spec.spawn_min_separation_m
    )
    azimuth = rng.uniform(0.0, 2.0 * np.pi)
    axis = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    mig = center + spec.migration_distance_m * axis
    vel = sample_in_cone(
        rng, spec.n_agents, axis, math.radians(spec.cone_half_angle_deg), spec.cone_length_mps
    )
    return pos, vel, mig


def teacher_targets(
    pos_world_enu: FloatArray, q_world_body: FloatArray, params: FlockingParams
) -> dict[str, FloatArray]:
    """The teacher's Reynolds command of every agent, world ENU and body FLU, from true positions.

    Returns "rey_world", "rey_body" (N, 3) m/s, "n_neighbours" (N,) and "nearest_m" (N,).
    """
    n = len(pos_world_enu)
    offsets = pairwise_offsets(pos_world_enu)
    sep, coh, count = reynolds_from_offsets(offsets, ~np.eye(n, dtype=bool), params)
    rey_world = sep + coh
    dist = np.linalg.norm(offsets, axis=-1)
    np.fill_diagonal(dist, np.inf)
    return {
        "rey_world": rey_world,
        "rey_body": world_to_body(rey_world, quat_to_rotmat(q_world_body)),
        "n_neighbours": count.astype(np.float64),
        "nearest_m": dist.min(axis=1),
    }


def sample_arrays(
    rows: dict[str, list[FloatArray]], n_steps: int, n: int, vel_command: FloatArray
) -> dict[str, NDArray[np.generic]]:
    """A run's stored per-sample arrays from per-step rows (one (n, ...) array per step).

    `rows` keys: "rey_body", "rey_world", "pos", "vel", "q", "t", "n_nb", "nearest";
    `vel_command` is the velocity command of every sample, (n_steps * n, 3) world ENU.
    """
    flat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in rows.items()}

    def per_sample(name: str, width: int) -> FloatArray:
        return flat[name].reshape(n_steps * n, width) if width > 1 else flat[name]

    return {
        "targets": per_sample("rey_body", 3).astype(np.float32),
        "rey_world_enu": per_sample("rey_world", 3).astype(np.float32),
        "pos_world_enu": per_sample("pos", 3).astype(np.float32),
        "vel_world_enu": per_sample("vel", 3).astype(np.float32),
        "q_world_body": per_sample("q", 4).astype(np.float32),
        "time_s": per_sample("t", 1).astype(np.float32),
        "n_neighbours": per_sample("n_nb", 1).astype(np.int16),
        "nearest_m": per_sample("nearest", 1).astype(np.float32),
        "agent": np.tile(np.arange(n, dtype=np.int16), n_steps),
        "vel_command_world_enu": np.asarray(vel_command, dtype=np.float32).reshape(-1, 3),
    }


def simulate_run(
    spec: DatasetSpec,
    split: str,
    run_index: int,
    world: World,
    renderer: Renderer,
    initial: tuple[FloatArray, FloatArray, FloatArray] | None = None,
) -> RunData:
    """Fly one run and collect its samples; `world` must hold `spec.n_agents` drones.

    `initial` replaces the run's random (positions, velocity commands, migration point), for tests.
    """
    if world.n_agents != spec.n_agents:
        raise ValueError(f"world has {world.n_agents} drones, the dataset {spec.n_agents}")
    pos0, vel_cmd, mig = initial or initial_conditions(spec, split, run_index)
    rates = spec.rates
    yaw0 = np.arctan2(vel_cmd[:, 1], vel_cmd[:, 0])
    vehicle = VehicleModel(VehicleParams(), pos0, yaw0)
    state = vehicle.state
    n = spec.n_agents
    max_steps = math.ceil(spec.max_run_s * rates.control_hz - 1e-9) + 1
    timing = RunTiming()
    images: list[NDArray[np.uint8]] = []
    rows: dict[str, list[FloatArray]] = {
        k: [] for k in ("pos", "vel", "q", "rey_world", "rey_body", "n_nb", "nearest", "t")
    }
    reason = "time_limit"
    for step in range(max_steps):
        t_s = step * rates.control_dt_s
        pos = state.pos_world_enu
        ended = termination(spec, pos, mig, t_s)
        if ended is not None:
            reason = ended
            break
        q = vehicle.q_world_body
        started = time.perf_counter()
        images.append(renderer.render(world, pos, q))
        mid = time.perf_counter()
        teacher = teacher_targets(pos, q, spec.flocking)
        rows["pos"].append(pos.copy())
        rows["vel"].append(state.vel_world_enu.copy())
        rows["q"].append(q.copy())
        rows["rey_world"].append(teacher["rey_world"])
        rows["rey_body"].append(teacher["rey_body"])
        rows["n_nb"].append(teacher["n_neighbours"])
        rows["nearest"].append(teacher["nearest_m"])
        rows["t"].append(np.full(n, t_s))
        done = time.perf_counter()
        for _ in range(rates.substeps):
            vehicle.step(vel_cmd, rates.physics_dt_s)
        timing.render_s += mid - started
        timing.teacher_s += done - mid
        timing.physics_s += time.perf_counter() - done
    assert reason in TERMINATIONS
    n_steps = len(images)
    arrays = sample_arrays(rows, n_steps, n, np.tile(vel_cmd, (n_steps, 1)))
    stacked = (
        np.concatenate(images)
        if images
        else np.zeros((0, IMAGE_HEIGHT_PX, IMAGE_WIDTH_PX), dtype=np.uint8)
    )
    return RunData(split, run_index, reason, mig, stacked, arrays, timing)
