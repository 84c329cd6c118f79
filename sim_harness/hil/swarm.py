"""The HIL swarm: one pybullet world, N unmodified daemons, all on the wall clock.

```
this process: world loop           PX4 emulator threads (MAVLink/UDP)      daemons (processes)
  physics 100 Hz ◀── latest command ── WorldVehicle ◀─ PX4 emulator ◀─ MAVSDK ─ companion run
  poses ──▶ PoseBoard (shared memory)                                            ▲ 6 ptys
camera process: render drone i at its capture instants ─▶ six pty cameras ──────┘
```

The daemons run in real time, so the world must too: physics steps are due on a fixed grid and
a step taken more than `late_physics_s` behind it is *late*; a capture rendered more than
`late_capture_s` after its instant is *late*; a frame replaced before it was sent is *dropped*.
`Lateness.valid` says whether the run stayed inside the stated thresholds; an invalid run is
reported as such, never as a result.

Two processes, like the drone's two kinds of hardware: this one (physics and the PX4 emulators)
and the camera process (`camera_side`: rendering and the pty cameras), which reads the poses
from shared memory. Cameras: each drone's six cameras capture together at 10 Hz with a
per-drone phase (drones are switched on at different times); each camera's frame then leaves
after its own fixed transfer delay plus jitter (free-running OpenMV boards: exposure, readout
and USB polling differ), so the daemon sees the six tiles arrive spread over up to
`camera_delay_s[1]`, stamped with the capture time on each camera's own clock and numbered by
each camera's own sequence counter.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim_harness.hil.camera_side import (
    CameraSide,
    CameraSideConfig,
    CaptureStats,
    PoseBoard,
    RemoteCameras,
)
from sim_harness.hil.drone import DroneSetup, HilDrone
from sim_harness.hil.faults import FaultPlan, FaultRunner
from sim_harness.hil.lateness import GridClock, Lateness
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN, WorldVehicle, home_of, states_ned
from sim_harness.sim import metrics
from sim_harness.sim.renderers import DEFAULT_RENDERER
from sim_harness.sim.rollout import FlightLog, has_arrived
from sim_harness.sim.scenarios import Scenario
from sim_harness.sim.vehicle import VehicleModel, VehicleParams
from sim_harness.sim.world import SimRates, World

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]
# The world loop shares the interpreter lock with the PX4 emulator threads: a short switch
# interval (default 5 ms) keeps its 10 ms physics grid on time.
SWITCH_INTERVAL_S = 0.0005


@dataclass(frozen=True)
class HilConfig:
    """How the harness runs a flight (the scenario and model come separately).

    `engage_timeout_s`: how long every daemon gets to start, connect and engage OFFBOARD.
    `camera_delay_s`: range of the per-camera transfer delay after capture (s).
    Lateness thresholds: at most `max_late_fraction` of captures (and of physics steps) late.
    """

    rates: SimRates = field(default_factory=SimRates)
    camera_rate_hz: float = 10.0
    camera_delay_s: tuple[float, float] = (0.004, 0.030)
    camera_jitter_s: float = 0.002
    engage_timeout_s: float = 90.0
    late_capture_s: float = 0.02
    late_physics_s: float = 0.02
    max_late_fraction: float = 0.01
    daemon_overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    seed: int = 0  # camera phases and delays
    # The harness stands in for hardware that, on a drone, never competes with the daemon for
    # CPU (cameras, autopilot): it runs above the daemons' Nice=-5 where the OS allows (root).
    harness_nice: int = -10
    renderer: str = DEFAULT_RENDERER  # sim_harness.sim.renderers: what draws the camera images

    def camera_side(self, folders: Sequence[Path], board_name: str) -> CameraSideConfig:
        """The camera process's configuration for drones whose files live in `folders`: each
        drone's capture phase (spread over the period) and each camera's transfer delay, drawn
        from `seed`."""
        n = len(folders)
        rng = np.random.default_rng(self.seed)
        period = 1.0 / self.camera_rate_hz
        phase_s = (np.arange(n) + rng.uniform(0, 1, n)) * period / n
        delay_s = rng.uniform(*self.camera_delay_s, (n, 6))
        return CameraSideConfig(
            folders=tuple(folders),
            board_name=board_name,
            phase_s=tuple(float(p) for p in phase_s),
            delay_s=tuple(tuple(float(d) for d in row) for row in delay_s),
            rate_hz=self.camera_rate_hz,
            jitter_s=self.camera_jitter_s,
            late_capture_s=self.late_capture_s,
            seed=self.seed,
            nice=self.harness_nice,
            renderer=self.renderer,
        )


@dataclass
class HilRun:
    """What a HIL flight produced: the flight log, the drones (for their logs) and timing."""

    log: FlightLog
    drones: list[HilDrone]
    cameras: CaptureStats
    lateness: Lateness
    engage_s: list[float | None]  # per drone: seconds from daemon start to OFFBOARD
    flight_t0_px4: list[float]  # per drone: its PX4 emulator's clock at the flight's t = 0
    harness_nice: int | None
    renderer: str
    faults: FaultRunner | None
    aborted: str | None = None  # why the flight could not start


class HilSwarm:
    """Runs one scenario with N daemons; `run()` returns a `HilRun` (use it once)."""

    def __init__(
        self,
        scenario: Scenario,
        model_path: Path,
        out_dir: Path,
        config: HilConfig | None = None,
        faults: FaultPlan | None = None,
        vehicle_params: VehicleParams | None = None,
        progress: Callable[[str], None] | None = None,
        on_phase: Callable[[str, HilSwarm], None] | None = None,
    ) -> None:
        """`on_phase(name, self)` is called at "flight_start" and "flight_end" (daemons still
        running), e.g. for a benchmark to sample the processes' CPU time."""
        self.scenario = scenario
        self.on_phase = on_phase or (lambda _name, _swarm: None)
        self.camera_pid: int | None = None
        self.config = config or HilConfig()
        self.model_path = model_path
        self.progress = progress or (lambda _msg: None)
        self.plan = faults
        n = scenario.n_agents
        self.vehicle = VehicleModel(
            vehicle_params or VehicleParams(),
            scenario.initial_pos_world_enu,
            scenario.initial_yaw_rad,
        )
        pos = scenario.initial_pos_world_enu
        self.homes = np.column_stack([pos[:, :2], np.zeros(n)])
        self.setups = [
            DroneSetup(
                index=i,
                home_world_enu=self.homes[i],
                migration_point_local_enu=(
                    None
                    if np.isnan(scenario.migration_points[i]).any()
                    else scenario.migration_points[i] - self.homes[i]
                ),
                folder=out_dir / f"drone{i + 1}",
            )
            for i in range(n)
        ]
        self.drones: list[HilDrone] = []
        self.harness_nice: int | None = None

    def _states(self) -> list[Any]:
        s = self.vehicle.state
        return states_ned(s.pos_world_enu, s.vel_world_enu, self.vehicle.q_world_body, self.homes)

    def _start(self) -> tuple[PoseBoard, CameraSide]:
        """The pose board and the camera process first (before any thread), then the drones."""
        cfg = self.config
        board = PoseBoard(self.scenario.n_agents)
        board.write(self.vehicle.state.pos_world_enu, self.vehicle.q_world_body)
        side = CameraSide(cfg.camera_side([setup.folder for setup in self.setups], board.name))
        self.camera_pid = side.pid
        for setup, state in zip(self.setups, self._states(), strict=True):
            drone = HilDrone(
                setup,
                WorldVehicle(setup.home_world_enu, state),
                RemoteCameras(side, setup.index),
                home_of(DEFAULT_ORIGIN, setup.home_world_enu),
                self.model_path,
                cfg.daemon_overrides,
            )
            self.drones.append(drone)
        return board, side

    # -- the loop ------------------------------------------------------------------------

    def run(self, duration_s: float) -> HilRun:
        cfg = self.config
        n = self.scenario.n_agents
        lateness = Lateness(max_late_fraction=cfg.max_late_fraction)
        rows: dict[str, list[FloatArray]] = {k: [] for k in ("pos", "vel", "q", "sp")}
        contacts: list[tuple[int, int, int]] = []
        engage_s: list[float | None] = [None] * n
        stop_reason = "time_limit"
        aborted = None
        faults = None
        flight_t0 = [0.0] * n
        self.harness_nice = raise_priority(cfg.harness_nice)  # before any thread starts
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        board, side = self._start()
        with World(n) as world:
            try:
                side.start_capturing()
                for drone in self.drones:
                    drone.start_autopilot()
                for drone in self.drones:
                    drone.start_daemon()
                daemon_t0 = [d.px4.now_s() for d in self.drones]
                clock = _Clock(self, world, board, lateness)
                self.progress(f"started {n} daemons; waiting for OFFBOARD")
                deadline = time.monotonic() + cfg.engage_timeout_s
                while not self._engaged(engage_s, daemon_t0):
                    if time.monotonic() > deadline:
                        missing = [
                            d.setup.drone_id
                            for d, e in zip(self.drones, engage_s, strict=True)
                            if e is None
                        ]
                        raise _Abort(f"not engaged after {cfg.engage_timeout_s:g} s: {missing}")
                    clock.advance_until(time.monotonic() + 0.05)
                clock.reset_counters()
                side.call("reset_stats")
                flight_start = time.monotonic()
                flight_t0 = [d.px4.now_s() for d in self.drones]
                faults = FaultRunner(self.plan, self.drones) if self.plan is not None else None
                self.on_phase("flight_start", self)
                self.progress(f"all engaged (last after {max(e or 0 for e in engage_s):.1f} s)")
                steps = math.ceil(duration_s * cfg.rates.control_hz - 1e-9)
                for step in range(steps + 1):
                    due = flight_start + step * cfg.rates.control_dt_s
                    touching = clock.advance_until(due)
                    contacts.extend((step, i, j) for i, j in touching)
                    s = self.vehicle.state
                    rows["pos"].append(s.pos_world_enu.copy())
                    rows["vel"].append(s.vel_world_enu.copy())
                    rows["q"].append(self.vehicle.q_world_body.copy())
                    rows["sp"].append(clock.setpoints.copy())
                    if faults is not None:
                        faults.poll(time.monotonic() - flight_start)
                    if has_arrived(self.scenario, s.pos_world_enu):
                        stop_reason = "arrived"
                        break
                    if step % max(1, int(cfg.rates.control_hz * 5)) == 0 and step:
                        self.progress(f"t = {step * cfg.rates.control_dt_s:.0f} s")
                if faults is not None:
                    faults.finish(time.monotonic() - flight_start)
                self.on_phase("flight_end", self)
            except _Abort as exc:
                aborted = str(exc)
                log.error("hil: %s", aborted)
            finally:
                stop_all(self.drones)
                cameras = side.stop()
                board.close()
        lateness.add_cameras(cameras)
        flight = _flight_log(self.scenario, cfg.rates, rows, contacts, stop_reason)
        return HilRun(
            log=flight,
            drones=self.drones,
            cameras=cameras,
            lateness=lateness,
            engage_s=engage_s,
            flight_t0_px4=flight_t0,
            harness_nice=self.harness_nice,
            renderer=cfg.renderer,
            faults=faults,
            aborted=aborted,
        )

    def _engaged(self, engage_s: list[float | None], daemon_t0: list[float]) -> bool:
        """Note each drone's first OFFBOARD; True once all are; abort if a daemon died."""
        for i, drone in enumerate(self.drones):
            if engage_s[i] is None:
                first = next(
                    (m.t_s for m in drone.px4.mode_changes() if m.new is Px4Mode.OFFBOARD), None
                )
                if first is not None:
                    engage_s[i] = first - daemon_t0[i]
            if not drone.alive:
                raise _Abort(
                    f"{drone.setup.drone_id}'s daemon exited before the flight: "
                    f"{drone.daemon_log_tail(3)}"
                )
        return all(e is not None for e in engage_s)


def raise_priority(nice: int) -> int:
    """Set this thread's niceness (threads started later inherit it); the niceness it has."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except PermissionError:
        log.warning("hil: cannot raise the harness's priority (not root): lateness may grow")
    return os.getpriority(os.PRIO_PROCESS, 0)


def stop_all(drones: list[HilDrone], timeout_s: float = 10.0) -> None:
    """SIGTERM every daemon at once (none is left hovering on frozen cameras while another
    shuts down), wait for all, then close the emulators."""
    for drone in drones:
        drone.signal_daemon(signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    for drone in drones:
        drone.wait_daemon(max(0.1, deadline - time.monotonic()))
    for drone in drones:
        drone.stop()


class _Abort(Exception):
    """The flight cannot start or go on (a daemon died before engaging, a timeout)."""


class _Clock(GridClock):
    """Advances physics to the wall clock, counting lateness; poses go to the pose board."""

    def __init__(self, swarm: HilSwarm, world: World, board: PoseBoard, lateness: Lateness) -> None:
        self.swarm, self.world, self.board, self.lateness = swarm, world, board, lateness
        self.dt_s = swarm.config.rates.physics_dt_s
        self.next_step = time.monotonic()
        self.setpoints = np.zeros((swarm.scenario.n_agents, 3))

    def reset_counters(self) -> None:
        keep = self.lateness.max_late_fraction
        self.lateness.__init__(max_late_fraction=keep)  # type: ignore[misc]

    def _run_due(self, now: float) -> set[tuple[int, int]]:
        sw, lat = self.swarm, self.lateness
        touching: set[tuple[int, int]] = set()
        while self.next_step <= now:
            behind = now - self.next_step
            lat.physics_steps += 1
            lat.physics_late += behind > sw.config.late_physics_s
            lat.physics_max_behind_s = max(lat.physics_max_behind_s, behind)
            self.setpoints = np.stack([d.vehicle.velocity_setpoint_enu() for d in sw.drones])
            yaw_sp = np.array([d.vehicle.yaw_setpoint_enu() for d in sw.drones])
            sw.vehicle.step(self.setpoints, self.dt_s, yaw_sp)
            s = sw.vehicle.state
            q = sw.vehicle.q_world_body
            self.board.write(s.pos_world_enu, q)
            if self.world.may_touch(s.pos_world_enu):
                touching.update(self.world.contacts(s.pos_world_enu, q))
            for drone, state in zip(sw.drones, sw._states(), strict=True):
                drone.vehicle.publish(state)
            self.next_step += self.dt_s
        return touching


def _flight_log(
    scenario: Scenario,
    rates: SimRates,
    rows: dict[str, list[FloatArray]],
    contacts: list[tuple[int, int, int]],
    stop_reason: str,
) -> FlightLog:
    n = scenario.n_agents
    if not rows["pos"]:  # aborted before the flight: the spawn state only
        rows = {
            "pos": [scenario.initial_pos_world_enu.copy()],
            "vel": [np.zeros((n, 3))],
            "q": [np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))],
            "sp": [np.zeros((n, 3))],
        }
    pos, vel = np.stack(rows["pos"]), np.stack(rows["vel"])
    sp = np.stack(rows["sp"])
    sp[-1] = np.nan
    d_min, d_max = metrics.distance_extremes(pos)
    return FlightLog(
        scenario=scenario,
        controller="hil",
        rates=rates,
        time_s=np.arange(pos.shape[0]) * rates.control_dt_s,
        pos_world_enu=pos,
        vel_world_enu=vel,
        q_world_body=np.stack(rows["q"]),
        setpoint_world_enu=sp,
        d_min_m=d_min,
        d_max_m=d_max,
        order=metrics.order_parameter(vel),
        contacts=contacts,
        stop_reason=stop_reason,
    )
