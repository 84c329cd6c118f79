"""How `companion run` ends, run as a child process against the emulators, as systemd runs it.

The cameras are six ptys playing recorded frames, the autopilot the pymavlink PX4 emulator over
loopback UDP (MAVSDK in between), the policy a real TorchScript file; the log is read back.

- A model that hangs in native code (a TorchScript loop that never ends, the GIL released) while
  flying: SIGTERM still sends Hold, closes a readable log and exits 0, not killed by an abort.
- A model refused at load (warm-up error, wrong reference output): exit 2, one line on stderr
  naming the reason, and the flight log's events say why the daemon stopped.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from companion.flight_log import summarize_log
from companion.model_file import base_metadata, save_model, sidecar_path, torchscript_calls
from sim_harness.hil.autopilot_emulator import AutopilotEmulator
from sim_harness.hil.camera_emulator import CameraEmulator
from sim_harness.hil.drone import free_tcp_port, toml_text
from sim_harness.hil.px4_logic import Px4Mode

from .daemon_rig import REPO, daemon_log

GUARD_S = 60.0  # liveness bound on a loaded machine; met in seconds normally


def hanging_model(path: Path, answered_calls: int) -> Path:
    """A policy that answers (0.5, 0, 0) m/s `answered_calls` times, then never returns."""
    import torch
    from torch import Tensor, nn

    class HangLater(nn.Module):
        def __init__(self, answered_calls: int) -> None:
            super().__init__()
            self.answered_calls = answered_calls
            self.calls = 0

        def forward(self, images: Tensor) -> Tensor:
            self.calls += 1
            acc = torch.zeros(images.shape[0], 3)
            while self.calls > self.answered_calls and bool(images.to(torch.float32).mean() >= 0):
                acc = acc + 0.0  # a native TorchScript loop, the GIL released: a hung model
            return acc + torch.tensor([0.5, 0.0, 0.0])

    with torchscript_calls():
        module = torch.jit.script(HangLater(answered_calls).eval())
    save_model(module, base_metadata(), path)
    return path


def write_config(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, model: Path
) -> Path:
    doc: dict[str, Any] = {
        "drone": {"id": "d1"},
        "cameras": {"faces": cameras.faces_config()},
        "policy": {"model_path": str(model)},
        "autopilot": {
            "url": f"udpin://127.0.0.1:{px4.config.client_port}",
            "discovery_timeout_s": 10.0,
            "health_timeout_s": 10.0,
            "offboard_prestream_s": 0.05,
        },
        "recorder": {"directory": str(tmp_path / "flights")},
        "telemetry": {"listen_endpoints": [f"tcp/127.0.0.1:{free_tcp_port()}"]},
        "daemon": {"failsafe_after_s": 30.0, "engage": "auto", "control_socket": ""},
    }
    path = tmp_path / "companion.toml"
    path.write_text(toml_text(doc))
    return path


class Child:
    """`companion run --config FILE` with its output (stdout and stderr) collected by a thread."""

    def __init__(self, config: Path) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "companion.cli", "run", "--config", str(config)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line)

    def wait_for(self, text: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while not any(text in line for line in self.lines):
            if time.monotonic() > deadline or self.process.poll() is not None:
                pytest.fail(f"no {text!r} (exit {self.process.poll()}):\n{self.output}")
            time.sleep(0.05)

    def finish(self, timeout_s: float) -> int:
        try:
            code = self.process.wait(timeout_s)
        finally:
            if self.process.poll() is None:
                self.process.kill()
                self.process.wait()
        self._reader.join(5.0)
        return code

    @property
    def output(self) -> str:
        return "".join(self.lines)


def test_sigterm_while_the_model_hangs_holds_and_exits_0(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator
) -> None:
    config = write_config(
        tmp_path, cameras, px4, hanging_model(tmp_path / "hang.pt", answered_calls=40)
    )
    child = Child(config)
    try:
        child.wait_for("pipeline healthy", GUARD_S)
        # 3 warm-up calls, then about 3.5 s of flying at 10 Hz before the model hangs for good.
        child.wait_for("the model has been running for", GUARD_S)
        child.process.send_signal(signal.SIGTERM)
        code = child.finish(GUARD_S)
    finally:
        with contextlib.suppress(ProcessLookupError):
            child.process.kill()
    assert code == 0, child.output
    assert "abandoned" in child.output  # the hung inference was left behind, said so
    assert px4.mode is Px4Mode.HOLD, child.output
    summary = summarize_log(daemon_log(tmp_path))
    assert summary["complete"], summary
    events = [(e["event"], e.get("detail")) for e in summary["health_events"]]
    assert ("stopped", "SIGTERM") in events, events


def wrong_input_model(path: Path) -> Path:
    """Valid hash and metadata, but its first call fails: a layer of the wrong size."""
    import torch
    from torch import Tensor, nn

    class WrongInput(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.head = nn.Linear(10, 3)

        def forward(self, images: Tensor) -> Tensor:
            return self.head(images.to(torch.float32).reshape(images.shape[0], -1))

    with torchscript_calls():
        save_model(torch.jit.script(WrongInput().eval()), base_metadata(), path)
    return path


def shipped_model_computed_wrongly(model: Path) -> Path:
    """A copy of the shipped policy whose recorded reference output is 8.9 m/s off in x: what
    the drone sees on a platform that computes the last layer wrong by that much."""
    shutil.copyfile(REPO / "models" / "swarm_cnn.pt", model)
    record = json.loads((REPO / "models" / "swarm_cnn.json").read_text())
    record["reference"]["output_body_flu_mps"][0] += 8.9
    sidecar_path(model).write_text(json.dumps(record))
    return model


@pytest.mark.parametrize(
    ("make_model", "reason"),
    [
        (
            wrong_input_model,
            "failed at warm-up: RuntimeError: mat1 and mat2 shapes cannot be multiplied "
            "(1x24576 and 10x3): refused",
        ),
        (shipped_model_computed_wrongly, "max error 8.9 m/s exceeds the tolerance 0.001 m/s"),
    ],
    ids=["warm-up-fails", "reference-output-wrong"],
)
def test_a_refused_model_exits_2_with_one_line_and_the_log_says_why(
    tmp_path: Path, cameras: CameraEmulator, px4: AutopilotEmulator, make_model: Any, reason: str
) -> None:
    config = write_config(tmp_path, cameras, px4, make_model(tmp_path / "model.pt"))
    done = subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(config)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=GUARD_S,
    )
    assert done.returncode == 2, done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("companion: error:")]
    assert len(errors) == 1 and reason in errors[0], done.stderr
    assert "Traceback" not in done.stderr, done.stderr
    assert not px4.setpoints() and px4.mode is Px4Mode.POSCTL  # nothing was commanded
    summary = summarize_log(daemon_log(tmp_path))
    assert summary["complete"], summary
    events = {e["event"]: str(e.get("detail")) for e in summary["health_events"]}
    assert reason in events["policy refused"], events
    assert events["stopped"].startswith("policy refused: ") and reason in events["stopped"]
