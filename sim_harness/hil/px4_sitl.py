"""Real PX4 firmware (SITL with its built-in quadrotor model, SIH) for tests and tools.

The firmware comes as a tarball of PX4's `px4_sitl_default` build (`bin/` and `etc/`), named by the
environment variable `PX4_SITL_TARBALL` (`SITL_ENV`); `unpack()` extracts it once per folder.
`Px4Sitl` starts one or more instances in one loopback-only network namespace (`netns`), each with
its own instance number N (MAVLink system id N + 1), its own SIH start position (SIH_LOC_LAT0 /
LON0 / H0, through PX4's `PX4_HOME_*` start-up variables) and any start-up parameters (PX4's
`PX4_PARAM_<NAME>` variables, applied after the airframe defaults), and always cleans up: every PX4
by its PID, the namespace, the instances' working folders.

PX4's ports for instance N (etc/init.d-posix/px4-rc.mavlink): the API/offboard link sends from
14580 + N to 14540 + N (MAVSDK `udpin://127.0.0.1:14540+N`: the companion's link); the GCS link
listens on 18570 + N and answers whoever sends to it (`px4_gcs.GroundStation`). Start-up measured
here: first heartbeat ~1.4 s, ready to arm ~5 s.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import tarfile
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

from sim_harness.errors import SimError
from sim_harness.hil import netns
from sim_harness.hil.netns import NetNamespace

SITL_ENV = "PX4_SITL_TARBALL"
MODEL = "sihsim_quadx"
OFFBOARD_PORT_BASE = 14540  # PX4 instance N sends its API link to 14540 + N
GCS_PORT_BASE = 18570  # PX4 instance N's GCS link listens on 18570 + N
MAX_INSTANCES = 10  # from instance 10 on, PX4's start script reuses port 14549
# PX4's server socket for instance N: a file, so shared by every network namespace. Two PX4s with
# the same instance number clash even in different namespaces; pick numbers no live PX4 holds.
SERVER_SOCKET = "/tmp/px4-sock-{index}"


def instance_in_use(index: int) -> bool:
    """Whether a running PX4 (in any namespace) holds instance number `index`."""
    path = SERVER_SOCKET.format(index=index)
    if not os.path.exists(path):
        return False
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(path)
        except OSError:  # a stale file left by a PX4 that is gone
            return False
    return True


def free_instance_indices(count: int) -> list[int]:
    """`count` instance numbers that no running PX4 holds (lowest first)."""
    free = [i for i in range(MAX_INSTANCES) if not instance_in_use(i)]
    if len(free) < count:
        raise Px4SitlError(f"{count} PX4 instances wanted, only {len(free)} numbers free")
    return free[:count]


HOW_TO_GET = (
    "set PX4_SITL_TARBALL to a PX4 SITL build tarball (the project's CI uses "
    "../shared/px4-sitl/px4-sitl-sih-02e73e3b6f.tar.xz; to build one: clone PX4-Autopilot with "
    "submodules, `make px4_sitl_default`, tar bin/ and etc/ of build/px4_sitl_default)"
)


class Px4SitlError(SimError):
    """PX4 SITL is missing, failed to start or did not become ready."""


def tarball_from_env() -> Path | None:
    """The tarball `PX4_SITL_TARBALL` names, or None when unset."""
    value = os.environ.get(SITL_ENV, "").strip()
    return Path(value).expanduser() if value else None


def unavailable_reason() -> str | None:
    """Why real PX4 cannot run here, in words a user can act on (None: it can)."""
    tarball = tarball_from_env()
    if tarball is None:
        return f"{SITL_ENV} is not set: {HOW_TO_GET}"
    if not tarball.is_file():
        return f"{SITL_ENV}={tarball}: no such file; {HOW_TO_GET}"
    reason = netns.unavailable_reason()
    if reason is not None:
        return f"PX4 SITL must run in a loopback-only network namespace, but {reason}"
    return None


def unpack(tarball: Path, folder: Path) -> Path:
    """Extract `tarball` into `folder` (once: a second call finds it) and return the build root,
    the folder holding `bin/px4` and `etc/`."""
    for candidate in (folder, *sorted(p for p in folder.glob("*") if p.is_dir())):
        if (candidate / "bin" / "px4").is_file():
            return candidate
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(tarball) as archive:
        archive.extractall(folder, filter="fully_trusted")  # keeps bin/'s executable links
    for candidate in (folder, *sorted(p for p in folder.glob("*") if p.is_dir())):
        if (candidate / "bin" / "px4").is_file():
            return candidate
    raise Px4SitlError(f"{tarball}: no bin/px4 inside")


@dataclass(frozen=True)
class Px4Instance:
    """One PX4 to start: its instance number, SIH start position and start-up parameters.

    `home_lat_deg` / `home_lon_deg` (deg) / `home_alt_m` (AMSL, m): where SIH places the vehicle,
    which becomes PX4's home and EKF origin. `params`: name -> value, set by PX4's start script
    after the airframe defaults (a stock vehicle: empty).
    """

    index: int = 0
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_alt_m: float = 488.0
    params: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 <= self.index < MAX_INSTANCES:
            raise Px4SitlError(f"instance index {self.index}: must be 0..{MAX_INSTANCES - 1}")

    @property
    def system_id(self) -> int:
        return self.index + 1

    @property
    def offboard_port(self) -> int:
        """Where PX4 sends its API link: the companion listens here (udpin)."""
        return OFFBOARD_PORT_BASE + self.index

    @property
    def gcs_port(self) -> int:
        """PX4's own GCS-link port: a ground station sends here and is answered."""
        return GCS_PORT_BASE + self.index

    def environment(self) -> dict[str, str]:
        """The variables PX4's start scripts read for this instance."""
        env = {
            "PX4_SIM_MODEL": MODEL,
            "PX4_SIMULATOR": "sihsim",
            "PX4_HOME_LAT": f"{self.home_lat_deg:.7f}",
            "PX4_HOME_LON": f"{self.home_lon_deg:.7f}",
            "PX4_HOME_ALT": f"{self.home_alt_m:.2f}",
        }
        for name, value in self.params.items():
            env[f"PX4_PARAM_{name}"] = f"{value:g}" if isinstance(value, float) else str(value)
        return env


@dataclass
class RunningPx4:
    """A started PX4: its spec, process, working folder and console log."""

    spec: Px4Instance
    process: subprocess.Popen[bytes]
    workdir: Path

    @property
    def log_path(self) -> Path:
        return self.workdir / "console.log"

    def console(self) -> str:
        """PX4's console output so far (its INFO/WARN/ERROR lines)."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    @property
    def alive(self) -> bool:
        return self.process.poll() is None


class Px4Sitl:
    """PX4 SITL instances in one loopback-only namespace. Context manager; `stop()` cleans up.

    `root`: the unpacked build (`unpack`). `workdir`: where each instance keeps its files
    (parameters, dataman, logs), removed on stop unless `keep_files`.
    """

    def __init__(
        self,
        root: Path,
        workdir: Path | None = None,
        namespace: NetNamespace | None = None,
        keep_files: bool = False,
    ) -> None:
        self.root = root
        self._own_workdir = workdir is None
        self.workdir = workdir or Path(tempfile.mkdtemp(prefix="px4sitl-"))
        self._own_namespace = namespace is None
        self.namespace = namespace or NetNamespace()
        self.keep_files = keep_files
        self.instances: dict[int, RunningPx4] = {}
        self._namespace_up = not self._own_namespace

    def start(self, specs: Sequence[Px4Instance]) -> list[RunningPx4]:
        """Start every instance at once (they boot in parallel); returns them in order."""
        if not self._namespace_up:
            self.namespace.create()
            self._namespace_up = True
        started = []
        for spec in specs:
            if spec.index in self.instances:
                raise Px4SitlError(f"PX4 instance {spec.index} already started")
            folder = self.workdir / f"px4-{spec.index}"
            folder.mkdir(parents=True, exist_ok=True)
            argv = [str(self.root / "bin" / "px4"), "-d", "-i", str(spec.index), "-w", str(folder)]
            argv.append(str(self.root / "etc"))
            env = {**os.environ, **spec.environment()}
            with (folder / "console.log").open("wb") as log:
                process = subprocess.Popen(
                    self.namespace.command(argv),
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    stdin=subprocess.DEVNULL,
                    cwd=folder,
                    env=env,
                    start_new_session=True,
                )
            running = RunningPx4(spec, process, folder)
            self.instances[spec.index] = running
            started.append(running)
        return started

    def stop_instance(self, index: int, timeout_s: float = 5.0) -> None:
        """SIGTERM (then SIGKILL) one instance's process group, by its PID."""
        running = self.instances.pop(index, None)
        if running is None or running.process.poll() is not None:
            return
        for sig, wait_s in ((signal.SIGTERM, timeout_s), (signal.SIGKILL, 5.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(running.process.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                running.process.wait(wait_s)
                return

    def stop(self) -> None:
        """Every instance, then the namespace, then the files. Idempotent."""
        try:
            for index in list(self.instances):
                self.stop_instance(index)
        finally:
            try:
                if self._own_namespace and self._namespace_up:
                    self._namespace_up = False
                    self.namespace.close()
            finally:
                if self._own_workdir and not self.keep_files:
                    shutil.rmtree(self.workdir, ignore_errors=True)

    def __enter__(self) -> Px4Sitl:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def wait_for_console(running: RunningPx4, text: str, timeout_s: float) -> float:
    """Seconds until `text` appears in the instance's console (raises on timeout or exit)."""
    start = time.monotonic()
    while text not in running.console():
        if not running.alive:
            raise Px4SitlError(f"PX4 {running.spec.index} exited: {running.console()[-2000:]}")
        if time.monotonic() - start > timeout_s:
            raise Px4SitlError(f"PX4 {running.spec.index}: no {text!r} within {timeout_s:g} s")
        time.sleep(0.05)
    return time.monotonic() - start
