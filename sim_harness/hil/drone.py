"""One emulated drone of the HIL swarm: six pty cameras, a PX4 emulator on the shared world's
vehicle, and the unmodified `companion run --config FILE` daemon, started as systemd starts it.

The daemon's configuration is the shipped example (`systemd/companion.toml`, what an operator
copies to the drone) with only what differs per drone replaced: its id, the camera devices and
ids, the model, the autopilot link, the log folder, the telemetry endpoint and the migration
point. The migration point is given in the drone's own local frame (ENU from its EKF origin,
which PX4 sets on the ground where the drone was switched on): the operator computes it per drone
from the goal and that drone's take-off point, exactly as done here.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_side import RemoteCameras
from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
from sim_harness.hil.px4_messages import Home
from sim_harness.hil.px4_params import logic_config
from sim_harness.hil.world_vehicle import WorldVehicle
from sim_harness.learning.shipped import PROJECT_ROOT

SHIPPED_CONFIG = PROJECT_ROOT / "systemd" / "companion.toml"
SHIPPED_UNIT = PROJECT_ROOT / "systemd" / "vision-swarm-companion.service"
LOOPBACK_TCP = "tcp/127.0.0.1"


def toml_text(doc: dict[str, Any], prefix: str = "") -> str:
    """A TOML document of tables, strings, numbers, booleans and lists (what configs hold)."""
    scalars, tables = [], []
    for key, value in doc.items():
        if isinstance(value, dict):
            tables.append((key, value))
        else:
            scalars.append(f"{key} = {json.dumps(value)}")
    text = (f"[{prefix}]\n" if prefix and scalars else "") + "".join(s + "\n" for s in scalars)
    for key, value in tables:
        text += "\n" + toml_text(value, f"{prefix}.{key}" if prefix else key)
    return text


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def unit_nice(unit: Path = SHIPPED_UNIT) -> int:
    """The service's `Nice=` (0 when it sets none): the daemons run at the unit's priority."""
    for line in unit.read_text().splitlines():
        key, _, value = line.partition("=")
        if key.strip() == "Nice":
            return int(value)
    return 0


def companion_command() -> list[str]:
    """`companion` as installed next to this interpreter (the unit's ExecStart), else `-m`."""
    exe = shutil.which("companion", path=str(Path(sys.executable).parent))
    return [exe] if exe else [sys.executable, "-m", "companion.cli"]


def daemon_document(
    setup: DroneSetup,
    faces: dict[str, dict[str, str]],
    model_path: Path,
    url: str,
    telemetry_endpoint: str,
    flights_dir: Path,
    overrides: dict[str, dict[str, Any]],
    migration_point_global: tuple[float, float, float] | None = None,
) -> dict[str, Any]:
    """The shipped example config with one drone's wiring: id, cameras, model, autopilot URL,
    log folder, telemetry endpoint and the migration point (`migration_point_global`, as an
    operator gives it in the field, else the setup's local ENU point); `overrides` last."""
    doc: dict[str, Any] = tomllib.loads(SHIPPED_CONFIG.read_text())
    doc["drone"] = {"id": setup.drone_id}
    doc["cameras"]["faces"] = faces
    doc["policy"] = {**doc["policy"], "model_path": str(model_path.resolve())}
    doc["policy"].pop("sha256", None)
    control = doc.setdefault("control", {})
    if migration_point_global is not None:
        control["migration_point_global"] = [round(float(c), 8) for c in migration_point_global]
    elif setup.migration_point_local_enu is not None:
        control["migration_point_enu"] = [
            round(float(c), 6) for c in setup.migration_point_local_enu
        ]
    doc["autopilot"] = {
        **doc["autopilot"],
        "url": url,
        "discovery_timeout_s": 60.0,  # nine daemons start at once on two cores
        "health_timeout_s": 60.0,
    }
    doc["recorder"] = {**doc["recorder"], "directory": str(flights_dir)}
    doc["telemetry"] = {
        **doc["telemetry"],
        "listen_endpoints": [telemetry_endpoint],
        "connect_endpoints": [],
        "multicast_scouting": False,
    }
    # No operator in the loop; one control socket per drone would outgrow a unix socket path.
    doc["daemon"] = {**doc["daemon"], "engage": "auto", "control_socket": ""}
    for section, values in overrides.items():
        doc.setdefault(section, {}).update(values)
    return doc


def launch_daemon(
    config_path: Path, log_path: Path, wrap: Callable[[list[str]], list[str]] | None = None
) -> subprocess.Popen[bytes]:
    """`companion run --config FILE` at the unit's `Nice=`, in its own process group, output to
    `log_path`; `wrap` turns the command into another (e.g. run inside a network namespace)."""
    env = {k: v for k, v in os.environ.items() if k != "NOTIFY_SOCKET"}
    # `nice -n` is relative to this (possibly raised) harness thread: the unit's Nice= it is.
    nice = ["nice", "-n", str(unit_nice() - os.getpriority(os.PRIO_PROCESS, 0))]
    argv = [*companion_command(), "run", "--config", str(config_path)]
    with log_path.open("wb") as log:
        return subprocess.Popen(
            [*nice, *(wrap(argv) if wrap is not None else argv)],
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
            env=env,
        )


@dataclass(frozen=True)
class DroneSetup:
    """Per-drone facts the harness chooses: index, home and where its files go."""

    index: int
    home_world_enu: NDArray[np.float64]
    migration_point_local_enu: NDArray[np.float64] | None
    folder: Path

    @property
    def drone_id(self) -> str:
        return f"drone{self.index + 1}"

    @property
    def system_id(self) -> int:
        return self.index + 1


class HilDrone:
    """Autopilot emulator and daemon of one drone (its cameras live in the camera process)."""

    def __init__(
        self,
        setup: DroneSetup,
        vehicle: WorldVehicle,
        cameras: RemoteCameras,
        home: Home,
        model_path: Path,
        daemon_overrides: dict[str, dict[str, Any]] | None = None,
    ) -> None:
        self.setup = setup
        self.vehicle = vehicle
        setup.folder.mkdir(parents=True, exist_ok=True)
        self.cameras = cameras
        altitude_m = float(vehicle.state().altitude_m)
        self.px4 = AutopilotEmulator(
            EmulatorConfig.hovering(
                free_udp_port(),
                altitude_m,
                system_id=setup.system_id,
                home=home,
                start_yaw_rad=float(vehicle.state().yaw_ned_rad),
                px4=logic_config(),  # the offboard-loss rule of the shipped parameter file
            ),
            backend=vehicle,
        )
        self.model_path = model_path
        self.overrides = daemon_overrides or {}
        self.telemetry_endpoint = f"{LOOPBACK_TCP}:{free_tcp_port()}"
        self.config_path = setup.folder / "companion.toml"
        self.flights_dir = setup.folder / "flights"
        self.process: subprocess.Popen[bytes] | None = None
        self.exit_code: int | None = None
        self.killed_by: str | None = None  # "sigterm" | "sigkill" when a fault plan stopped it

    def config_document(self) -> dict[str, Any]:
        """The shipped example config with this drone's wiring."""
        return daemon_document(
            self.setup,
            self.cameras.faces_config(),
            self.model_path,
            f"udpin://127.0.0.1:{self.px4.config.client_port}",
            self.telemetry_endpoint,
            self.flights_dir,
            self.overrides,
        )

    def start_autopilot(self) -> None:
        self.px4.start()

    def start_daemon(self) -> None:
        """`companion run --config FILE` in its own process group, output to daemon.log."""
        self.config_path.write_text(toml_text(self.config_document()))
        self.process = launch_daemon(self.config_path, self.setup.folder / "daemon.log")

    @property
    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def signal_daemon(self, sig: signal.Signals) -> None:
        """Send `sig` to the daemon's process group (as systemd's KillMode=mixed does first)."""
        if self.process is None or self.process.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, sig)

    def wait_daemon(self, timeout_s: float) -> int | None:
        """The exit code once the daemon ended within `timeout_s`, else None."""
        if self.process is None:
            return None
        try:
            self.exit_code = self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        return self.exit_code

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM, wait, SIGKILL what is left; then the autopilot emulator. Idempotent."""
        if self.alive:
            self.signal_daemon(signal.SIGTERM)
            if self.wait_daemon(timeout_s) is None:
                self.signal_daemon(signal.SIGKILL)
                self.wait_daemon(5.0)
        elif self.process is not None:
            self.exit_code = self.process.poll()
        self.px4.stop()

    def daemon_log_tail(self, lines: int = 5) -> str:
        path = self.setup.folder / "daemon.log"
        if not path.exists():
            return ""
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
