"""Costs of the companion's per-tick side of the pipeline: policy hop, control law, recorder,
telemetry, and how much a killed recorder loses.

    python benchmarks/companion_pipeline.py [--ticks 300] [--kills 3]

- policy: `await Policy.infer` end to end vs the bare TorchScript call (a small conv net scripted
  here, ~1 ms), so the difference is the worker-thread hop and the output checks;
- control: one `ControlLaw.step` (one drone);
- recorder: caller-side cost of one tick's records (frame + policy + setpoint + telemetry), and
  bytes on disk per tick (zstd chunks) -> MB per hour at 10 Hz;
- telemetry: `await publish_once()` with three JSON values on loopback (nobody subscribed);
- crash loss: a child process records at 10 Hz (flush_every_s = 1) and is SIGKILLed at random
  times; loss = kill time - last log time found in the file.

Prints a table and writes JSON (default benchmarks/results/companion_pipeline.json).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from companion.control import ControlConfig, ControlLaw
from companion.flight_log import TOPIC_TELEMETRY, LogReader
from companion.model_file import base_metadata, save_model
from companion.policy import Policy, PolicyConfig
from companion.recorder import (
    TOPIC_POLICY,
    TOPIC_SETPOINT,
    FlightRecorder,
    RecorderConfig,
)
from companion.telemetry import TelemetryConfig, TelemetryPublisher
from sim_harness.experiments.machine import machine

REPO = Path(__file__).resolve().parents[1]


class SmallNet(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv1 = torch.nn.Conv2d(1, 16, 5, stride=2, padding=2)
        self.conv2 = torch.nn.Conv2d(16, 32, 3, stride=2, padding=1)
        self.conv3 = torch.nn.Conv2d(32, 64, 3, stride=2, padding=1)
        self.fc = torch.nn.Linear(64, 3)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = (images.to(torch.float32).unsqueeze(1) - 100.0) / 50.0
        x = torch.relu(self.conv1(x))
        x = torch.relu(self.conv2(x))
        x = torch.relu(self.conv3(x))
        return self.fc(x.mean(dim=(2, 3))) * 0.01


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q))


def bench_policy(tmp: Path, ticks: int) -> dict[str, float]:
    path = tmp / "small.pt"
    save_model(torch.jit.script(SmallNet().eval()), base_metadata(), path)
    policy = Policy.load(PolicyConfig(model_path=path, threads=1, warmup_runs=10))
    image = np.random.default_rng(0).integers(0, 255, (64, 384), dtype=np.uint8)
    batch = torch.from_numpy(image).unsqueeze(0)
    direct, hop = [], []
    for _ in range(ticks):
        t = time.perf_counter()
        policy._run_model(batch)
        direct.append(time.perf_counter() - t)

    async def run() -> None:
        for _ in range(ticks):
            t = time.perf_counter()
            out = await policy.infer(image)
            hop.append(time.perf_counter() - t)
            assert out.ok, out.reason

    asyncio.run(run())
    policy.close()
    return {
        "model_call_median_ms": 1e3 * statistics.median(direct),
        "infer_median_ms": 1e3 * statistics.median(hop),
        "infer_p99_ms": 1e3 * pct(hop, 99),
        "hop_overhead_median_ms": 1e3 * (statistics.median(hop) - statistics.median(direct)),
    }


def bench_control(ticks: int) -> dict[str, float]:
    law = ControlLaw(ControlConfig(migration_point_enu=(30.0, 0.0, 5.0), low_pass_cutoff_hz=2.0))
    times = []
    for i in range(ticks):
        t = time.perf_counter()
        law.step([1.0, 0.1 * (i % 3), 0.0], [0.9, 0.0, 0.0, 0.43589], [1.0, 2.0, 5.0], 0.9)
        times.append(time.perf_counter() - t)
    return {"step_median_us": 1e6 * statistics.median(times), "step_p99_us": 1e6 * pct(times, 99)}


def bench_recorder(tmp: Path, ticks: int) -> dict[str, float]:
    rng = np.random.default_rng(1)
    law = ControlLaw(ControlConfig())
    setpoint = law.step([1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 5.0], 0.0).as_dict()
    # A smooth image with noise compresses like a camera image, not like white noise.
    base = np.tile(np.linspace(40, 200, 384), (64, 1))
    times = []
    rec = FlightRecorder(RecorderConfig(directory=tmp / "rec"))
    rec.start()
    for i in range(ticks):
        image = np.clip(base + rng.normal(0, 6, base.shape) + i % 7, 0, 255).astype(np.uint8)
        t = time.perf_counter()
        rec.record_frame(image)
        rec.record(TOPIC_POLICY, {"vel_body_flu": [0.3, 0.1, 0.0], "ok": True, "latency_s": 0.002})
        rec.record(TOPIC_SETPOINT, setpoint)
        rec.record(TOPIC_TELEMETRY, {"pos_ned": [1.0, 2.0, -5.0], "q": [1, 0, 0, 0], "armed": True})
        times.append(time.perf_counter() - t)
        time.sleep(0.001)
    rec.close()
    size = sum(p.stat().st_size for p in rec.files)
    per_tick = size / ticks
    return {
        "record_tick_median_us": 1e6 * statistics.median(times),
        "record_tick_p99_us": 1e6 * pct(times, 99),
        "bytes_per_tick": per_tick,
        "mb_per_hour_at_10hz": per_tick * 10 * 3600 / 1e6,
        "dropped": rec.stats().dropped,
    }


def bench_telemetry(ticks: int) -> dict[str, float]:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    cfg = TelemetryConfig(drone_id="bench", listen_endpoints=(f"tcp/127.0.0.1:{port}",))
    times: list[float] = []

    async def run() -> None:
        async with TelemetryPublisher(cfg) as pub:
            for i in range(ticks):
                pub.update_state({"pos_enu": [1.0, 2.0, 5.0], "i": i})
                pub.update_health({"ok": True})
                pub.update_setpoint({"vel_ned": [0.1, 0.2, 0.0]})
                t = time.perf_counter()
                await pub.publish_once()
                times.append(time.perf_counter() - t)

    asyncio.run(run())
    return {"publish_once_median_ms": 1e3 * statistics.median(times)}


CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from companion.recorder import FlightRecorder, RecorderConfig, TOPIC_TELEMETRY
    rec = FlightRecorder(RecorderConfig(directory=Path(sys.argv[1]), flush_every_s=1.0))
    rec.start()
    print(rec.files[0], flush=True)
    while True:
        rec.record(TOPIC_TELEMETRY, {"t": time.time_ns()})
        time.sleep(0.1)
    """
)


def bench_crash_loss(tmp: Path, kills: int) -> dict[str, Any]:
    losses = []
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for k in range(kills):
        directory = tmp / f"kill{k}"
        child = subprocess.Popen(
            [sys.executable, "-c", CHILD, str(directory)],
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert child.stdout is not None
        path = Path(child.stdout.readline().strip())
        time.sleep(2.0 + random.uniform(0.0, 1.0))
        killed_ns = time.time_ns()
        child.send_signal(signal.SIGKILL)
        child.wait()
        last = max(m.log_time_ns for m in LogReader(path).messages() if m.topic == TOPIC_TELEMETRY)
        losses.append((killed_ns - last) / 1e9)
    return {"loss_s": losses, "loss_max_s": max(losses)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=300)
    parser.add_argument("--kills", type=int, default=3)
    parser.add_argument(
        "--out", type=Path, default=REPO / "benchmarks/results/companion_pipeline.json"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        results = {
            "policy": bench_policy(tmp, args.ticks),
            "control": bench_control(args.ticks),
            "recorder": bench_recorder(tmp, args.ticks),
            "telemetry": bench_telemetry(args.ticks),
            "crash": bench_crash_loss(tmp, args.kills),
            "machine": machine(),
        }
    for section, values in results.items():
        for key, value in values.items():
            shown = f"{value:.3f}" if isinstance(value, float) else str(value)
            print(f"{section:<10} {key:<28} {shown}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
