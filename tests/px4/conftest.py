"""Real PX4 firmware (SITL + SIH) for the tests in this folder, started once for the folder.

They are stopped when the folder's last test is done (package scope; hence `__init__.py`): two
hovering PX4s left running to the end of the session took CPU from every later test, and the HIL
swarm flights after them starved in CI (physics 6 s behind the wall clock).

Two PX4 instances boot in parallel in one loopback-only network namespace: instance 0 gets the
shipped parameter file loaded over MAVLink (as QGroundControl would), instance 1 stays stock. A
ground station per instance (pymavlink on PX4's GCS port) is the pilot and the eyes: it arms,
takes off, switches modes and reads PX4's own state. The daemon runs as systemd runs it,
`companion run --config FILE`, as a child process inside the namespace (`ip netns exec`), with
six pty cameras playing recorded frames and a constant TorchScript policy.

Skipped, with the reason, where PX4_SITL_TARBALL is unset or network namespaces are not allowed.
"""

from __future__ import annotations

import contextlib
import itertools
import signal
import subprocess
import threading
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.flight_log import TOPIC_HEALTH, LogReader
from companion.param_check import BOARD_ONLY, ParamRow, read_params_file
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.drone import SHIPPED_CONFIG, companion_command, toml_text
from sim_harness.hil.px4_gcs import GroundStation
from sim_harness.hil.px4_params import SHIPPED_PARAMS
from sim_harness.hil.px4_sitl import (
    Px4Instance,
    Px4Sitl,
    RunningPx4,
    tarball_from_env,
    unavailable_reason,
    unpack,
)

SHIPPED, STOCK = 0, 1
TAKEOFF_M = 5.0
POLICY_BODY_FLU = (1.5, 0.0, 0.0)  # the constant policy: forward 1.5 m/s
_ports = itertools.count(17447)


@dataclass
class Vehicle:
    """One real PX4 in the air, its ground station and what loading parameters did."""

    px4: RunningPx4
    gcs: GroundStation
    loaded: dict[str, tuple[float, float, float | None]]  # name -> (file, echoed, read back)
    load_texts: list[str] = field(default_factory=list)  # STATUSTEXT from loading to take-off

    @property
    def url(self) -> str:
        return f"udpin://127.0.0.1:{self.px4.spec.offboard_port}"


def load_params(gcs: GroundStation, rows: list[ParamRow]) -> dict[str, Any]:
    """PARAM_SET every row PX4 has (board-only names are skipped), then read each back."""
    loaded: dict[str, Any] = {}
    for row in rows:
        if row.name in BOARD_ONLY:
            continue
        echoed = gcs.set_param(row.name, row.value, row.param_type)
        loaded[row.name] = (row.value, echoed, gcs.get_param(row.name))
    return loaded


@pytest.fixture(scope="package")
def sitl(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Px4Sitl]:
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(f"real PX4 not available: {reason}")
    tarball = tarball_from_env()
    assert tarball is not None
    root = unpack(tarball, tmp_path_factory.mktemp("px4-build"))
    with Px4Sitl(root, tmp_path_factory.mktemp("px4-work")) as sitl:
        sitl.start(
            [
                Px4Instance(SHIPPED),
                Px4Instance(STOCK, home_lat_deg=47.397742 + 0.0005),  # 55 m north
            ]
        )
        assert sitl.namespace.interfaces() == ["lo"]
        yield sitl


@pytest.fixture(scope="package")
def vehicles(sitl: Px4Sitl) -> Iterator[dict[int, Vehicle]]:
    """Both PX4s ready, instance 0 with the shipped parameters, both hovering at 5 m in HOLD."""
    stations = {
        i: GroundStation(sitl.instances[i].spec.gcs_port, sitl.namespace, i + 1).start()
        for i in (SHIPPED, STOCK)
    }
    try:
        for gcs in stations.values():
            gcs.wait_ready(40.0)
        load_started = time.monotonic()
        loaded = load_params(stations[SHIPPED], read_params_file(SHIPPED_PARAMS))
        errors: list[BaseException] = []

        def take_off(gcs: GroundStation) -> None:
            try:
                gcs.arm_and_take_off(TAKEOFF_M)
            except BaseException as exc:
                errors.append(exc)

        threads = [threading.Thread(target=take_off, args=(g,)) for g in stations.values()]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise errors[0]
        load_texts = stations[SHIPPED].texts_since(load_started)
        yield {
            SHIPPED: Vehicle(sitl.instances[SHIPPED], stations[SHIPPED], loaded, load_texts),
            STOCK: Vehicle(sitl.instances[STOCK], stations[STOCK], {}),
        }
    finally:
        for gcs in stations.values():
            gcs.stop()


@pytest.fixture
def shipped(vehicles: dict[int, Vehicle]) -> Vehicle:
    """PX4 instance 0: the shipped parameter file loaded; in the air."""
    return vehicles[SHIPPED]


@pytest.fixture
def stock(vehicles: dict[int, Vehicle]) -> Vehicle:
    """PX4 instance 1: stock parameters; in the air."""
    return vehicles[STOCK]


@pytest.fixture(scope="session")
def policy_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A TorchScript policy that always answers POLICY_BODY_FLU (body FLU, m/s)."""
    return constant_policy(tmp_path_factory.mktemp("policy") / "constant.pt", POLICY_BODY_FLU)


@pytest.fixture(scope="session")
def make_policy(tmp_path_factory: pytest.TempPathFactory) -> Callable[[tuple[float, ...]], Path]:
    """`make_policy(velocity_body_flu)` -> a constant TorchScript policy file answering it."""

    def make(velocity_body_flu: tuple[float, ...]) -> Path:
        folder = tmp_path_factory.mktemp("policy")
        return constant_policy(folder / "constant.pt", velocity_body_flu)

    return make


def constant_policy(path: Path, velocity_body_flu: tuple[float, ...]) -> Path:
    """Save a TorchScript policy that always answers `velocity_body_flu` (m/s) at `path`."""
    import torch
    from torch import Tensor, nn

    from companion.model_file import base_metadata, save_model, torchscript_calls

    class Constant(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("value", torch.tensor(velocity_body_flu, dtype=torch.float32))

        def forward(self, images: Tensor) -> Tensor:
            return self.value.expand(images.shape[0], 3).clone()

    with torchscript_calls():
        module = torch.jit.script(Constant().eval())
    save_model(module, base_metadata(), path)
    return path


def recording(n: int = 10) -> np.ndarray:
    """Recorded stitched frames (N, 64, 384) uint8, different every frame."""
    frames = np.random.default_rng(7).integers(20, 230, (n, 64, 384), dtype=np.uint8)
    frames[:, :, ::8] = 255
    return frames


class DaemonRun:
    """`companion run --config FILE` in PX4's namespace, wired to one vehicle and pty cameras."""

    def __init__(
        self, sitl: Px4Sitl, vehicle: Vehicle, folder: Path, policy: Path, **daemon: Any
    ) -> None:
        self.sitl, self.vehicle, self.folder = sitl, vehicle, folder
        folder.mkdir(parents=True, exist_ok=True)
        self.cameras = CameraEmulator(folder / "dev", source=recording(), rate_hz=10.0).start()
        doc: dict[str, Any] = tomllib.loads(SHIPPED_CONFIG.read_text())
        doc["drone"] = {"id": "px4test"}
        doc["cameras"]["faces"] = self.cameras.faces_config()
        doc["policy"] = {"model_path": str(policy), "warmup_runs": 1}
        doc["autopilot"].update(url=vehicle.url, discovery_timeout_s=20.0, health_timeout_s=20.0)
        doc["recorder"]["directory"] = str(folder / "flights")
        doc["telemetry"].update(listen_endpoints=[f"tcp/127.0.0.1:{next(_ports)}"])
        doc["daemon"].update({"failsafe_after_s": 2.0, "control_socket": "", **daemon})
        self.config_path = folder / "companion.toml"
        self.config_path.write_text(toml_text(doc))
        self.log_path = folder / "daemon.log"
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> DaemonRun:
        argv = [*companion_command(), "run", "--config", str(self.config_path)]
        with self.log_path.open("wb") as log:
            self.process = subprocess.Popen(
                self.sitl.namespace.command(argv),
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
            )
        return self

    def signal(self, sig: signal.Signals) -> None:
        assert self.process is not None
        self.process.send_signal(sig)

    def wait(self, timeout_s: float = 20.0) -> int:
        assert self.process is not None
        return self.process.wait(timeout_s)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def health_events(self) -> list[str]:
        """The health topic's events of the run's flight log (readable after a kill too)."""
        logs = sorted((self.folder / "flights").glob("*.mcap"))
        return [
            str(m.json().get("event"))
            for log in logs
            for m in LogReader(log).messages()
            if m.topic == TOPIC_HEALTH
        ]

    def health_lines(self) -> list[str]:
        """Each health event as "event: detail" (the detail says why, e.g. why not engaging)."""
        logs = sorted((self.folder / "flights").glob("*.mcap"))
        return [
            f"{m.json().get('event')}: {m.json().get('detail')}"
            for log in logs
            for m in LogReader(log).messages()
            if m.topic == TOPIC_HEALTH
        ]

    def close(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(10.0)
        self.cameras.close()


@pytest.fixture
def daemon_run(sitl: Px4Sitl, tmp_path: Path, policy_file: Path) -> Iterator[Any]:
    """`daemon_run(vehicle, policy=None, **daemon_overrides)` -> a started DaemonRun (stopped
    afterwards); `policy`: a TorchScript file (default: the constant POLICY_BODY_FLU one)."""
    runs: list[DaemonRun] = []

    def make(vehicle: Vehicle, policy: Path | None = None, **daemon: Any) -> DaemonRun:
        folder = tmp_path / f"run{len(runs)}"
        run = DaemonRun(sitl, vehicle, folder, policy or policy_file, **daemon)
        runs.append(run)
        return run.start()

    yield make
    for run in runs:
        run.close()
