"""Shared fixtures for companion tests: tiny real TorchScript policies saved with `save_model`.

Every policy takes the stitched images, uint8 (B, 64, 384), and returns a body-FLU velocity
(B, 3) like a trained one; they differ in what they compute:

- "constant": always `value`;
- "brightness": (mean/255, -mean/255, 0): proves the image really reaches the model;
- "nan": NaN everywhere;
- "wide": (B, 4), a wrong output shape;
- "raise": raises inside TorchScript when pixel (0, 0, 0) is 255, else returns zeros;
- "spin": busy-loops pixel(0, 0, 0) * `SPIN_ITERS_PER_UNIT` times (about 7 us each, the GIL
  released), then returns (0.5, 0, 0): a slow model.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

SPIN_ITERS_PER_UNIT = 20_000


def build_module(kind: str, value: Sequence[float] = (1.0, 0.0, 0.0)) -> Any:
    """A scripted test policy (torch imported here: the other companion tests do not pay for it)."""
    import torch
    from torch import Tensor, nn

    from companion.model_file import torchscript_calls

    class Constant(nn.Module):
        def __init__(self, value: Sequence[float]) -> None:
            super().__init__()
            self.register_buffer("value", torch.tensor(list(value), dtype=torch.float32))

        def forward(self, images: Tensor) -> Tensor:
            return self.value.expand(images.shape[0], 3).clone()

    class Brightness(nn.Module):
        def forward(self, images: Tensor) -> Tensor:
            mean = images.to(torch.float32).mean(dim=(1, 2)) / 255.0
            return torch.stack([mean, -mean, torch.zeros_like(mean)], dim=1)

    class NaN(nn.Module):
        def forward(self, images: Tensor) -> Tensor:
            return torch.full((images.shape[0], 3), float("nan"))

    class Wide(nn.Module):
        def forward(self, images: Tensor) -> Tensor:
            return torch.zeros(images.shape[0], 4)

    class Raise(nn.Module):
        def forward(self, images: Tensor) -> Tensor:
            if int(images[0, 0, 0]) == 255:
                raise RuntimeError("synthetic model failure")
            return torch.zeros(images.shape[0], 3)

    class Spin(nn.Module):
        def __init__(self, iters_per_unit: int) -> None:
            super().__init__()
            self.iters_per_unit = iters_per_unit

        def forward(self, images: Tensor) -> Tensor:
            n = int(images[0, 0, 0]) * self.iters_per_unit
            acc = torch.zeros(images.shape[0], 3)
            for _ in range(n):
                acc = acc + 0.0
            return acc + torch.tensor([0.5, 0.0, 0.0])

    modules: dict[str, Callable[[], nn.Module]] = {
        "constant": lambda: Constant(value),
        "brightness": Brightness,
        "nan": NaN,
        "wide": Wide,
        "raise": Raise,
        "spin": lambda: Spin(SPIN_ITERS_PER_UNIT),
    }
    with torchscript_calls():
        return torch.jit.script(modules[kind]().eval())


PolicyFactory = Callable[..., Path]


@pytest.fixture
def make_policy_file(tmp_path: Path) -> PolicyFactory:
    """`make_policy_file(kind, value=(1, 0, 0), name=kind) -> Path` of a saved NAME.pt.

    The sidecar NAME.json (hash + metadata) is written next to it by `save_model`.
    """

    def make(kind: str, value: Sequence[float] = (1.0, 0.0, 0.0), name: str | None = None) -> Path:
        from companion.model_file import base_metadata, save_model

        path = tmp_path / f"{name or kind}.pt"
        metadata = base_metadata()
        metadata["test_kind"] = kind
        save_model(build_module(kind, value), metadata, path)
        return path

    return make


def textured_frames(n: int = 10) -> Any:
    """Recorded stitched frames (n, 64, 384) uint8: textured, different every frame, with
    vertical bars like horizon and drone edges."""
    import numpy as np

    frames = np.random.default_rng(7).integers(20, 230, (n, 64, 384), dtype=np.uint8)
    frames[:, :, ::8] = 255
    return frames


@pytest.fixture
def cameras(tmp_path: Path) -> Iterator[Any]:
    """Six pty cameras playing `textured_frames` at 10 Hz."""
    from sim_harness.hil.camera_emulator import CameraEmulator

    with CameraEmulator(tmp_path / "dev", source=textured_frames(), rate_hz=10.0) as emulator:
        yield emulator


@pytest.fixture
def px4() -> Iterator[Any]:
    """The PX4 emulator, armed and hovering at 5 m in POSCTL; heartbeats at 20 Hz."""
    from sim_harness.hil.autopilot_emulator import AutopilotEmulator
    from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port

    config = EmulatorConfig.hovering(free_udp_port(), 5.0, heartbeat_rate_hz=20.0)
    with AutopilotEmulator(config) as emulator:
        yield emulator


def drone_document(
    cameras: Any,
    px4: Any,
    model: Path,
    folder: Path,
    telemetry: dict[str, Any],
    daemon: dict[str, Any],
) -> dict[str, Any]:
    """The config document of a test drone wired to pty cameras and the PX4 emulator (flight
    logs under `folder`), with these `[telemetry]` and `[daemon]` sections."""
    return {
        "drone": {"id": "d1"},
        "cameras": {"faces": cameras.faces_config()},
        "policy": {"model_path": str(model)},
        "autopilot": {
            "url": f"udpin://127.0.0.1:{px4.config.client_port}",
            "discovery_timeout_s": 5.0,
            "health_timeout_s": 5.0,
            "offboard_prestream_s": 0.05,
        },
        "recorder": {"directory": str(folder / "flights")},
        "telemetry": telemetry,
        "daemon": daemon,
    }


def drone_daemon(*document_args: Any) -> Any:
    """A `Daemon` for `drone_document(*document_args)`, on the test's clock, no signal handlers."""
    import time

    from companion.config import config_from_dict
    from companion.daemon import Daemon

    config = config_from_dict(drone_document(*document_args))
    return Daemon(config, handle_signals=False, clock=time.monotonic)


@pytest.fixture
def make_drone_daemon() -> Callable[..., Any]:
    """`drone_daemon` for test modules (which cannot import this file)."""
    return drone_daemon


class EngageRig:
    """One drone's hardware around a daemon under test: six pty cameras playing textured frames
    and the pymavlink PX4 emulator, hovering at 5 m in POSCTL with 1 Hz heartbeats like PX4."""

    def __init__(self, folder: Path, model: Path, px4: dict[str, Any]) -> None:
        from sim_harness.hil.autopilot_emulator import AutopilotEmulator
        from sim_harness.hil.camera_emulator import CameraEmulator
        from sim_harness.hil.emulator_config import EmulatorConfig, free_udp_port
        from sim_harness.hil.px4_logic import Px4LogicConfig

        self.folder, self.model = folder, model
        self.cameras = CameraEmulator(folder / "dev", source=textured_frames(), rate_hz=10.0)
        self.cameras.start()
        config = EmulatorConfig.hovering(
            free_udp_port(), 5.0, heartbeat_rate_hz=1.0, px4=Px4LogicConfig(**px4)
        )
        self.px4 = AutopilotEmulator(config).start()

    def daemon(self, control_socket: str, **daemon: Any) -> Any:
        """A `Daemon` wired to this rig (telemetry off; the test's clock)."""
        daemon_section = {"failsafe_after_s": 5.0, "control_socket": control_socket, **daemon}
        return drone_daemon(
            self.cameras, self.px4, self.model, self.folder, {"enabled": False}, daemon_section
        )

    def close(self) -> None:
        self.px4.stop()
        self.cameras.close()


@pytest.fixture
def engage_rig(
    tmp_path: Path, make_policy_file: PolicyFactory
) -> Iterator[Callable[..., EngageRig]]:
    """`engage_rig(**px4_logic) -> EngageRig` flying the constant policy (forward 1 m/s)."""
    rigs: list[EngageRig] = []

    def make(**px4: Any) -> EngageRig:
        model = make_policy_file("constant", (1.0, 0.0, 0.0))
        rigs.append(EngageRig(tmp_path / f"rig{len(rigs)}", model, px4))
        return rigs[-1]

    yield make
    for rig in rigs:
        rig.close()


@pytest.fixture
def control_socket_path() -> Iterator[str]:
    """A control socket path short enough for a unix socket (pytest's tmp_path may not be)."""
    import shutil
    import tempfile

    folder = tempfile.mkdtemp(prefix="ctl", dir="/tmp")
    yield f"{folder}/control.sock"
    shutil.rmtree(folder, ignore_errors=True)
