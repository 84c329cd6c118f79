"""The HIL swarm with a real PX4 per drone (`swarm-sim hil --autopilot px4-sitl`).

```
PX4 SITL + SIH (one per drone, loopback-only namespace)       daemons (in the namespace)
  flies its own vehicle ◀──────── MAVSDK offboard ────────────── companion run ◀─ 6 ptys
  GCS link ── LOCAL_POSITION_NED, ATTITUDE_QUATERNION ──▶ this process: world loop        ▲
                                  poses ──▶ PoseBoard ──▶ camera process (render) ───────┘
```

Each drone's PX4 flies PX4's own quadrotor model (SIH); nothing here moves the vehicles. The
harness is a ground station per drone (pymavlink on PX4's GCS link, `PoseStation`): it reads the
pose PX4 reports, places that drone in the shared pybullet world (PoseBoard, for the cameras;
contacts are checked in the world) and, as a pilot would, arms each vehicle and takes it off to
its spawn altitude before the daemons start.

One global frame: the world's origin is `DEFAULT_ORIGIN` on the ground; drone i's SIH starts at
its spawn point's ground position (`home_of`), which becomes its PX4's home and EKF origin. Each
drone is placed where SIH's simulated vehicle is (HIL_STATE_QUATERNION, which PX4 streams on the
GCS link: position in WGS-84, converted to the world ENU frame flat-earth from the world origin,
as the daemon converts its goal): the physical vehicle, as the cameras of the others would see it.
PX4's own estimate (LOCAL_POSITION_NED from the start point) is decimetres off it (simulated GPS
noise, `estimate_error_max_m`); it is the fallback where HIL_STATE_QUATERNION does not arrive.
The goal reaches each daemon as an operator gives it in the field: `[control]
migration_point_global` (lat, lon, alt AMSL of the scenario's migration point), which the daemon
converts with the home its PX4 reports.

Timing: the world loop runs on the 100 Hz physics grid, but the physics is PX4's; a world step is
*late* when the loop ran more than `late_physics_s` behind the grid or a drone's newest PX4 pose
was older than `late_physics_s` + one pose period (PX4 or its link starved of CPU). The camera
side counts its own lateness as in the emulator harness (`Lateness`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.frames import ned_to_enu, quat_ned_frd_to_enu_flu
from companion.geo import GlobalPosition, enu_offset_m
from sim_harness.errors import SimError
from sim_harness.hil.camera_side import CameraSide, PoseBoard
from sim_harness.hil.drone import (
    DroneSetup,
    daemon_document,
    launch_daemon,
    toml_text,
)
from sim_harness.hil.lateness import Lateness
from sim_harness.hil.px4_drone import (
    HEARTBEAT_SLACK_S,
    IDENTITY_Q,
    ORIGIN,
    STREAMS_HZ,
    TAKEOFF_TIMEOUT_S,
    Px4Drone,
    shipped_params,
)
from sim_harness.hil.px4_logic import Px4Mode
from sim_harness.hil.px4_pose_station import PoseStation
from sim_harness.hil.px4_sitl import (
    Px4Instance,
    Px4Sitl,
    free_instance_indices,
    tarball_from_env,
    unpack,
)
from sim_harness.hil.px4_world_clock import WorldClock
from sim_harness.hil.swarm import (
    SWITCH_INTERVAL_S,
    HilConfig,
    HilRun,
    _flight_log,
    raise_priority,
)
from sim_harness.hil.world_vehicle import DEFAULT_ORIGIN, home_of
from sim_harness.sim.rollout import has_arrived
from sim_harness.sim.scenarios import Scenario
from sim_harness.sim.world import World

log = logging.getLogger(__name__)
FloatArray = NDArray[np.float64]


class Px4Swarm:
    """Runs one scenario with N daemons and N real PX4s; `run()` returns a `HilRun` (use once).

    `px4_root`: an unpacked PX4 SITL build (default: unpacked from `PX4_SITL_TARBALL` into the
    run folder's `px4/`, removed afterwards).
    """

    def __init__(
        self,
        scenario: Scenario,
        model_path: Path,
        out_dir: Path,
        config: HilConfig | None = None,
        progress: Callable[[str], None] | None = None,
        px4_root: Path | None = None,
    ) -> None:
        self.scenario = scenario
        self.model_path = model_path
        self.out_dir = out_dir
        self.config = config or HilConfig()
        self.progress = progress or (lambda _msg: None)
        self.px4_root = px4_root
        n = scenario.n_agents
        pos = scenario.initial_pos_world_enu
        self.homes = np.column_stack([pos[:, :2], np.zeros(n)])  # SIH starts on the ground
        self.setups = [
            DroneSetup(
                index=i,
                home_world_enu=self.homes[i],
                migration_point_local_enu=None,  # given globally (migration_point_global)
                folder=out_dir / f"drone{i + 1}",
            )
            for i in range(n)
        ]
        self.drones: list[Px4Drone] = []
        self.harness_nice: int | None = None
        self.pose_gap_max_s = [0.0] * n
        self.frame_check_m: list[tuple[float, float] | None] = [None] * n
        self.estimate_error_max_m = [0.0] * n  # PX4's horizontal estimate vs SIH's vehicle
        # Why world steps were late: the loop itself behind, or a PX4 pose stale (flight only).
        self.world_steps_behind = 0
        self.world_steps_pose_stale = 0
        self.flight_t0 = 0.0  # monotonic time of the flight's t = 0

    # -- set-up ----------------------------------------------------------------------------

    def _migration_global(self, i: int) -> tuple[float, float, float] | None:
        point = self.scenario.migration_points[i]
        if np.isnan(point).any():
            return None
        home = home_of(DEFAULT_ORIGIN, point)
        return (home.lat_deg, home.lon_deg, home.alt_amsl_m)

    def _instances(self) -> list[Px4Instance]:
        params = shipped_params()
        specs = []
        numbers = free_instance_indices(len(self.setups))  # another PX4 may run (tests, a CLI)
        for setup, number in zip(self.setups, numbers, strict=True):
            home = home_of(DEFAULT_ORIGIN, setup.home_world_enu)
            specs.append(Px4Instance(number, home.lat_deg, home.lon_deg, home.alt_amsl_m, params))
        return specs

    def _take_off(self) -> None:
        """Every vehicle: ready, armed, taken off to its spawn altitude (in parallel)."""
        errors: list[BaseException] = []

        def one(drone: Px4Drone) -> None:
            altitude = float(self.scenario.initial_pos_world_enu[drone.setup.index, 2])
            try:
                drone.takeoff_s = drone.gcs.arm_and_take_off(altitude, TAKEOFF_TIMEOUT_S)
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=one, args=(d,), daemon=True) for d in self.drones]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise _Abort(f"take-off failed: {errors[0]}")

    def _check_frame(self) -> None:
        """PX4's GLOBAL_POSITION_INT against the world position (SIH's vehicle), per drone (m)."""
        origin = ORIGIN
        pos, _, _ = self._poses(time.monotonic())
        for i, drone in enumerate(self.drones):
            gp = drone.gcs.global_position
            if gp is None:
                continue
            where = GlobalPosition(gp.lat * 1e-7, gp.lon * 1e-7, gp.alt * 1e-3)
            error = enu_offset_m(where, origin) - pos[i]
            self.frame_check_m[i] = (float(np.linalg.norm(error[:2])), float(error[2]))

    # -- poses -----------------------------------------------------------------------------

    def _poses(self, now: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """World ENU positions, velocities (N, 3) and attitudes (N, 4) of every drone: SIH's
        simulated vehicle (HIL_STATE_QUATERNION) where PX4 sends it, else PX4's estimate
        (LOCAL_POSITION_NED from the start point, ATTITUDE_QUATERNION), its height taken above
        home (GLOBAL_POSITION_INT's relative_alt) where PX4 sends that: the local frame's origin
        is where the estimator started, which can sit tenths of a metre off the ground."""
        n = self.scenario.n_agents
        pos = self.scenario.initial_pos_world_enu.copy()
        vel = np.zeros((n, 3))
        q = np.tile(IDENTITY_Q, (n, 1))
        for i, drone in enumerate(self.drones):
            sample, truth = drone.gcs.position(), drone.gcs.truth
            estimate = None
            if sample is not None:
                estimate = self.homes[i] + ned_to_enu(np.array([sample.x, sample.y, sample.z]))
                height = drone.gcs.height_above_home_m
                if height is not None:
                    estimate[2] = self.homes[i][2] + height
                pos[i] = estimate
                vel[i] = ned_to_enu(np.array([sample.vx, sample.vy, sample.vz]))
                attitude = drone.gcs.attitude
                if attitude is not None and np.all(np.isfinite(attitude[1])):
                    q[i] = quat_ned_frd_to_enu_flu(attitude[1])
            if truth is not None:
                pos[i] = enu_offset_m(truth.position, ORIGIN)
                vel[i] = ned_to_enu(truth.vel_ned_mps)
                if np.all(np.isfinite(truth.q_ned_frd)) and np.linalg.norm(truth.q_ned_frd) > 0.5:
                    q[i] = quat_ned_frd_to_enu_flu(truth.q_ned_frd)
                if estimate is not None:
                    error = float(np.linalg.norm(estimate[:2] - pos[i, :2]))
                    self.estimate_error_max_m[i] = max(self.estimate_error_max_m[i], error)
            newest = truth.t_s if truth is not None else None if sample is None else sample.t_s
            if newest is not None:
                self.pose_gap_max_s[i] = max(self.pose_gap_max_s[i], now - newest)
        return pos, vel, q

    def _pose_age_s(self, now: float) -> float:
        ages = []
        for drone in self.drones:
            truth, sample = drone.gcs.truth, drone.gcs.position()
            newest = truth.t_s if truth is not None else None if sample is None else sample.t_s
            ages.append(math.inf if newest is None else now - newest)
        return max(ages, default=0.0)

    def _targets(self) -> FloatArray:
        """The velocity PX4 flies now (POSITION_TARGET_LOCAL_NED), world ENU; NaN when none."""
        out = np.full((self.scenario.n_agents, 3), np.nan)
        for i, drone in enumerate(self.drones):
            with drone.gcs._lock:
                latest = drone.gcs.targets[-1][1] if drone.gcs.targets else None
            if latest is not None:
                out[i] = ned_to_enu(np.array([latest.vx, latest.vy, latest.vz]))
        return out

    # -- the flight ------------------------------------------------------------------------

    def run(self, duration_s: float) -> HilRun:
        cfg = self.config
        n = self.scenario.n_agents
        lateness = Lateness(max_late_fraction=cfg.max_late_fraction)
        rows: dict[str, list[FloatArray]] = {k: [] for k in ("pos", "vel", "q", "sp")}
        contacts: list[tuple[int, int, int]] = []
        engage_s: list[float | None] = [None] * n
        stop_reason, aborted = "time_limit", None
        self.harness_nice = raise_priority(cfg.harness_nice)
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        board = PoseBoard(n)
        board.write(self.scenario.initial_pos_world_enu, np.tile(IDENTITY_Q, (n, 1)))
        side = CameraSide(cfg.camera_side([s.folder for s in self.setups], board.name))
        sitl: Px4Sitl | None = None
        with World(n) as world, contextlib.ExitStack() as stack:
            try:
                sitl = stack.enter_context(Px4Sitl(self._root(stack), self.out_dir / "px4"))
                self.progress(f"starting {n} PX4 SITL instances (SIH)")
                for running, setup in zip(sitl.start(self._instances()), self.setups, strict=True):
                    gcs = PoseStation(running.spec.gcs_port, sitl.namespace, running.spec.system_id)
                    gcs.start()
                    self.drones.append(
                        Px4Drone(
                            setup,
                            running,
                            gcs,
                            side.faces_config[setup.index],
                            self._migration_global(setup.index),
                        )
                    )
                    stack.callback(gcs.stop)
                for drone in self.drones:
                    drone.gcs.wait_ready(TAKEOFF_TIMEOUT_S)
                    for message_id, rate_hz in STREAMS_HZ.items():
                        drone.gcs.stream(message_id, rate_hz)
                self.progress("PX4s ready: arming and taking off to the spawn altitudes")
                self._take_off()
                self._check_frame()
                side.start_capturing()
                self.progress(f"in the air; starting {n} daemons")
                for drone in self.drones:
                    self._start_daemon(drone, sitl)
                daemon_t0 = time.monotonic()
                clock = WorldClock(self, world, board, lateness)
                deadline = daemon_t0 + cfg.engage_timeout_s
                while not self._engaged(engage_s, daemon_t0):
                    if time.monotonic() > deadline:
                        missing = [
                            d.setup.drone_id
                            for d, e in zip(self.drones, engage_s, strict=True)
                            if e is None
                        ]
                        raise _Abort(f"not engaged after {cfg.engage_timeout_s:g} s: {missing}")
                    clock.advance_until(time.monotonic() + 0.05)
                lateness.__init__(max_late_fraction=cfg.max_late_fraction)  # type: ignore[misc]
                self.pose_gap_max_s = [0.0] * n
                self.world_steps_behind = self.world_steps_pose_stale = 0
                side.call("reset_stats")
                flight_start = time.monotonic()
                self.progress(f"all engaged (last after {max(e or 0 for e in engage_s):.1f} s)")
                steps = math.ceil(duration_s * cfg.rates.control_hz - 1e-9)
                for step in range(steps + 1):
                    touching = clock.advance_until(flight_start + step * cfg.rates.control_dt_s)
                    contacts.extend((step, i, j) for i, j in touching)
                    pos, vel, q = clock.last
                    rows["pos"].append(pos)
                    rows["vel"].append(vel)
                    rows["q"].append(q)
                    rows["sp"].append(self._targets())
                    if has_arrived(self.scenario, pos):
                        stop_reason = "arrived"
                        break
                    if step % max(1, int(cfg.rates.control_hz * 5)) == 0 and step:
                        self.progress(f"t = {step * cfg.rates.control_dt_s:.0f} s")
                self.flight_t0 = flight_start
            except (_Abort, SimError, OSError) as exc:
                aborted = str(exc)
                log.error("hil px4: %s", aborted)
            finally:
                self._stop_daemons()
                cameras = side.stop()
                board.close()
        lateness.add_cameras(cameras)
        flight = _flight_log(self.scenario, cfg.rates, rows, contacts, stop_reason)
        return HilRun(
            log=flight,
            drones=[],
            cameras=cameras,
            lateness=lateness,
            engage_s=engage_s,
            flight_t0_px4=[0.0] * n,
            harness_nice=self.harness_nice,
            renderer=cfg.renderer,
            faults=None,
            aborted=aborted,
        )

    def _root(self, stack: contextlib.ExitStack) -> Path:
        if self.px4_root is not None:
            return self.px4_root
        tarball = tarball_from_env()
        if tarball is None:
            raise _Abort("PX4_SITL_TARBALL is not set")
        folder = Path(tempfile.mkdtemp(prefix="px4-build-"))
        stack.callback(shutil.rmtree, folder, True)
        return unpack(tarball, folder)

    def _start_daemon(self, drone: Px4Drone, sitl: Px4Sitl) -> None:
        doc = daemon_document(
            drone.setup,
            drone.faces,
            self.model_path,
            f"udpin://127.0.0.1:{drone.px4.spec.offboard_port}",
            drone.telemetry_endpoint,
            drone.flights_dir,
            self.config.daemon_overrides,
            migration_point_global=drone.migration_point_global,
        )
        drone.config_path.write_text(toml_text(doc))
        log_path = drone.setup.folder / "daemon.log"
        drone.process = launch_daemon(drone.config_path, log_path, sitl.namespace.command)

    def _engaged(self, engage_s: list[float | None], daemon_t0: float) -> bool:
        for i, drone in enumerate(self.drones):
            if engage_s[i] is None:
                seen = [
                    m.t_s for m in drone.gcs.mode_changes(daemon_t0) if m.mode is Px4Mode.OFFBOARD
                ]
                if seen:
                    engage_s[i] = seen[0] - daemon_t0
            if not drone.alive:
                raise _Abort(
                    f"{drone.setup.drone_id}'s daemon exited before the flight: "
                    f"{drone.daemon_log_tail(3)}"
                )
        return all(e is not None for e in engage_s)

    def _stop_daemons(self, timeout_s: float = 10.0) -> None:
        """SIGTERM every daemon at once (each ends in PX4 Hold), wait, SIGKILL what is left."""
        for drone in self.drones:
            if drone.alive and drone.process is not None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(drone.process.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for drone in self.drones:
            if drone.process is None:
                continue
            try:
                drone.exit_code = drone.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                drone.process.kill()
                drone.exit_code = drone.process.wait(5.0)
        # PX4's heartbeat (1 Hz) shows the daemons' Hold within a second: wait for it, so the
        # final modes reported are PX4's, not the last heartbeat before the switch.
        deadline = time.monotonic() + HEARTBEAT_SLACK_S
        while time.monotonic() < deadline and any(
            d.gcs.mode is Px4Mode.OFFBOARD for d in self.drones
        ):
            time.sleep(0.05)


class _Abort(Exception):
    """The flight cannot start or go on."""
