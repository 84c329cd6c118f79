"""The cameras of every HIL drone in a process of their own: pybullet rendering + pty cameras.

On a real drone the cameras and the autopilot are separate hardware; here they are separate
processes too, so rendering (the harness's largest cost) runs on the other core instead of
taking the world loop's interpreter lock. The world loop writes every drone's pose into shared
memory at each physics step (`PoseBoard`); this process renders drone i's six faces at its capture
instants from the latest poses and pushes them to that drone's six pty cameras.

Commands (camera faults, stats, stop) arrive over a pipe; the process answers each with a reply.
"""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import sys
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.camera.layout import FACE_NAMES, split
from sim_harness.errors import SimError
from sim_harness.sim.renderers import DEFAULT_RENDERER

FloatArray = NDArray[np.float64]
_POSE = 7  # x, y, z, qw, qx, qy, qz


class PoseBoard:
    """Every drone's latest world pose in shared memory, with a sequence lock.

    Layout (float64): [seq, x0 y0 z0 qw0 qx0 qy0 qz0, x1 ...]; `seq` is odd while a write is in
    progress, so a reader retries instead of mixing two steps.
    """

    def __init__(self, n_agents: int, name: str | None = None) -> None:
        size = 8 * (1 + _POSE * n_agents)
        self._shm = SharedMemory(name=name, create=name is None, size=size)
        self._owner = name is None
        self._array = np.ndarray((1 + _POSE * n_agents,), dtype=np.float64, buffer=self._shm.buf)
        self.n_agents = n_agents
        if self._owner:
            self._array[:] = 0.0

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, pos_world_enu: FloatArray, q_world_body: FloatArray) -> None:
        a = self._array
        a[0] += 1.0
        poses = a[1:].reshape(self.n_agents, _POSE)
        poses[:, :3] = pos_world_enu
        poses[:, 3:] = q_world_body
        a[0] += 1.0

    def read(self) -> tuple[FloatArray, FloatArray]:
        a = self._array
        while True:
            seq = a[0]
            copy = a[1:].copy()
            if seq % 2 == 0 and a[0] == seq:
                poses = copy.reshape(self.n_agents, _POSE)
                return poses[:, :3], poses[:, 3:]

    def close(self) -> None:
        del self._array
        self._shm.close()
        if self._owner:
            self._shm.unlink()


@dataclass(frozen=True)
class CameraSideConfig:
    """What the camera process needs: where each drone's cameras live and when they capture."""

    folders: tuple[Path, ...]
    board_name: str
    phase_s: tuple[float, ...]  # per drone, capture phase within the period
    delay_s: tuple[tuple[float, ...], ...]  # per drone and face, transfer delay after capture
    rate_hz: float = 10.0
    jitter_s: float = 0.002
    late_capture_s: float = 0.02
    seed: int = 0
    nice: int = 0  # the process's niceness, where the OS allows
    renderer: str = DEFAULT_RENDERER


@dataclass
class CaptureStats:
    captures: int = 0
    captures_late: int = 0
    capture_max_late_s: float = 0.0
    render_s: list[float] = field(default_factory=list)
    frames_sent: list[int] = field(default_factory=list)  # per drone
    frames_dropped: list[int] = field(default_factory=list)
    connections: list[list[int]] = field(default_factory=list)  # per drone, per face


def _camera_main(config: CameraSideConfig, conn: Connection) -> None:  # pragma: no cover
    """The child process: own world, renderer and cameras; captures on the wall clock."""
    from sim_harness.hil.camera_emulator import CameraEmulator
    from sim_harness.sim.renderers import make_renderer
    from sim_harness.sim.world import World

    with contextlib.suppress(PermissionError):  # before the camera threads: they inherit it
        os.setpriority(os.PRIO_PROCESS, 0, config.nice)
    sys.setswitchinterval(0.0005)  # captures stay on time beside the pty camera threads
    n = len(config.folders)
    board = PoseBoard(n, config.board_name)
    cameras = [CameraEmulator(f / "dev", source=None).start() for f in config.folders]
    renderer = make_renderer(config.renderer)
    rng = np.random.default_rng(config.seed)
    stats = CaptureStats()
    period = 1.0 / config.rate_hz
    capturing = False
    with World(n) as world:
        pos, q = board.read()
        renderer.render(world, pos, q, [0])  # compile/warm up before any capture is due
        conn.send([c.faces_config() for c in cameras])
        next_capture = np.zeros(n)
        while True:
            now = time.monotonic()
            if capturing:
                due = np.flatnonzero(next_capture <= now)
                if len(due):
                    _capture(config, world, renderer, board, cameras, due, next_capture, stats, rng)
                    next_capture[due] += period
                    for i in due:  # a whole period missed: skip it, counted as late
                        while next_capture[i] <= time.monotonic() - period:
                            next_capture[i] += period
                            stats.captures += 1
                            stats.captures_late += 1
                wait = float(next_capture.min()) - time.monotonic()
            else:
                wait = 0.05
            if conn.poll(max(0.0, wait)):
                command, args = conn.recv()
                if command == "capture":
                    capturing = True
                    next_capture = time.monotonic() + np.asarray(config.phase_s)
                    conn.send(None)
                elif command == "reset_stats":
                    stats = CaptureStats()
                    conn.send(None)
                elif command == "stop":
                    break
                else:
                    conn.send(_camera_command(cameras, command, args, stats))
    for camera in cameras:
        camera.close()
    _fill_camera_stats(cameras, stats)
    conn.send(stats)
    board.close()


def _capture(
    config: CameraSideConfig,
    world: Any,
    renderer: Any,
    board: PoseBoard,
    cameras: list[Any],
    due: NDArray[np.intp],
    next_capture: FloatArray,
    stats: CaptureStats,
    rng: np.random.Generator,
) -> None:
    """Render the drones whose capture instants have come, in one call (a batched renderer
    draws them together), and push each drone's six tiles to its cameras."""
    started = time.monotonic()
    for i in due:
        late = started - float(next_capture[i])
        stats.captures += 1
        stats.captures_late += late > config.late_capture_s
        stats.capture_max_late_s = max(stats.capture_max_late_s, late)
    pos, q = board.read()
    images = renderer.render(world, pos, q, [int(i) for i in due])
    done = time.monotonic()
    stats.render_s.extend([(done - started) / len(due)] * len(due))
    delays = np.asarray(config.delay_s)
    for i, image in zip(due, images, strict=True):
        jitter = rng.uniform(0.0, config.jitter_s, 6)
        cameras[i].push(split(image), done, done + delays[i] + jitter)


def _fill_camera_stats(cameras: list[Any], stats: CaptureStats) -> None:
    stats.frames_sent = [sum(c.stats(f).frames_sent for f in FACE_NAMES) for c in cameras]
    stats.frames_dropped = [sum(c.stats(f).frames_dropped for f in FACE_NAMES) for c in cameras]
    stats.connections = [[c.stats(f).connections for f in FACE_NAMES] for c in cameras]


def _camera_command(cameras: list[Any], command: str, args: tuple[Any, ...], stats: Any) -> Any:
    if command == "stats":
        _fill_camera_stats(cameras, stats)
        return stats
    drone, face = args[0], args[1]
    camera = cameras[drone]
    if command == "stall":
        camera.stall(face)
    elif command == "resume":
        camera.resume(face)
    elif command == "unplug":
        camera.unplug(face)
    elif command == "replug":
        camera.replug(face)
    elif command == "inject":
        return camera.inject(face, args[2])
    elif command == "corrupt":
        camera.corrupt_frames(face, args[2])
    else:
        raise SimError(f"camera side: unknown command {command!r}")
    return None


class CameraSide:
    """Handle on the camera process (start, faults, stats, stop)."""

    def __init__(self, config: CameraSideConfig) -> None:
        ctx = mp.get_context("spawn")  # the parent has threads: never fork it
        self._conn, child = ctx.Pipe()
        self._process = ctx.Process(
            target=_camera_main, args=(config, child), name="hil-cameras", daemon=True
        )
        self._process.start()
        child.close()
        if not self._conn.poll(60.0):
            self._process.kill()
            raise SimError("camera process did not start within 60 s")
        self.faces_config: list[dict[str, dict[str, str]]] = self._conn.recv()
        self.final: CaptureStats | None = None

    @property
    def pid(self) -> int | None:
        return self._process.pid

    def call(self, command: str, *args: Any) -> Any:
        self._conn.send((command, args))
        return self._conn.recv()

    def start_capturing(self) -> None:
        self.call("capture")

    def stop(self) -> CaptureStats:
        if self.final is None:
            try:
                self._conn.send(("stop", ()))
                self.final = self._conn.recv() if self._conn.poll(20.0) else CaptureStats()
            except (BrokenPipeError, EOFError, OSError):
                self.final = CaptureStats()
            self._process.join(10.0)
            if self._process.is_alive():
                self._process.kill()
        return self.final


class RemoteCameras:
    """One drone's cameras as the fault runner sees them (calls into the camera process)."""

    def __init__(self, side: CameraSide, index: int) -> None:
        self._side, self._index = side, index

    def stall(self, face: str) -> None:
        self._side.call("stall", self._index, face)

    def resume(self, face: str) -> None:
        self._side.call("resume", self._index, face)

    def unplug(self, face: str) -> None:
        self._side.call("unplug", self._index, face)

    def replug(self, face: str) -> None:
        self._side.call("replug", self._index, face)

    def inject(self, face: str, data: bytes) -> bool:
        return bool(self._side.call("inject", self._index, face, data))

    def corrupt_frames(self, face: str, count: int) -> None:
        self._side.call("corrupt", self._index, face, count)

    def faces_config(self) -> dict[str, dict[str, str]]:
        return self._side.faces_config[self._index]
