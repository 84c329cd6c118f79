"""Six serial camera links + the rig against the pty camera emulator, in one process.

    python benchmarks/camera_links.py [--seconds 10] [--rate-hz 10]

Measures, per frame, the host receive latency (receive time minus the emulated camera's true
capture time, both on the same monotonic clock), the error of the links' capture-time estimate,
the share of 10 Hz rig snapshots that were ready, the cost of `Rig.snapshot`, and the CPU time of
the event-loop thread in a second phase of the same length (the six links and a 10 Hz rig
snapshot only; the emulator runs in its own thread). Prints a summary and writes JSON
(default benchmarks/results/camera_links.json).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.camera.layout import FACE_NAMES
from companion.camera.rig import Rig
from companion.camera.serial_link import links_from_config, run_links
from companion.camera.slot import CameraFrame
from sim_harness.experiments.machine import machine
from sim_harness.hil.camera_emulator import CameraEmulator

RESULTS = Path(__file__).resolve().parent / "results"  # not the working folder's


def percentiles_ms(values_s: list[float]) -> dict[str, float]:
    arr = np.asarray(values_s) * 1e3
    return {
        "p50": float(np.percentile(arr, 50)),
        "p90": float(np.percentile(arr, 90)),
        "p99": float(np.percentile(arr, 99)),
        "max": float(arr.max()),
    }


async def measure(emu: CameraEmulator, seconds: float) -> dict[str, Any]:
    config = emu.rig_config()
    links = links_from_config(config)
    rig = Rig(config, links)
    task = asyncio.create_task(run_links(links))
    try:
        deadline = time.monotonic() + 10.0
        while not rig.snapshot(time.monotonic()).ready:
            assert time.monotonic() < deadline, "rig never became ready"
            await asyncio.sleep(0.01)
        latencies_s: list[float] = []
        estimate_errors_s: list[float] = []
        snapshot_costs_s: list[float] = []
        ready = ticks = 0
        seen: dict[str, CameraFrame | None] = dict.fromkeys(FACE_NAMES)
        wall0 = time.monotonic()
        next_tick = wall0
        while time.monotonic() - wall0 < seconds:
            for face, link in links.items():  # sample every new frame
                frame = link.latest()
                if frame is not None and frame is not seen[face]:
                    seen[face] = frame
                    true_capture_s = emu.boot_time_s(face) + frame.capture_timestamp_us * 1e-6
                    latencies_s.append(frame.receive_time_s - true_capture_s)
                    estimate_errors_s.append(frame.capture_time_s - true_capture_s)
            if time.monotonic() >= next_tick:
                next_tick += 0.1
                t0 = time.perf_counter()
                result = rig.snapshot(time.monotonic())
                snapshot_costs_s.append(time.perf_counter() - t0)
                ticks += 1
                ready += result.ready
            await asyncio.sleep(0.002)
        wall_s = time.monotonic() - wall0
        # CPU of the loop thread with only the links and a 10 Hz rig snapshot (no sampling).
        cpu0, wall0 = time.thread_time(), time.monotonic()
        while time.monotonic() - wall0 < seconds:
            rig.snapshot(time.monotonic())
            await asyncio.sleep(0.1)
        cpu_share = (time.thread_time() - cpu0) / (time.monotonic() - wall0)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    statuses = {face: link.status() for face, link in links.items()}
    return {
        "frames_received": sum(s.frames_ok for s in statuses.values()),
        "frames_sent": sum(emu.stats(face).frames_sent for face in FACE_NAMES),
        "frames_dropped_by_cameras": sum(emu.stats(face).frames_dropped for face in FACE_NAMES),
        "parser_dropped_bytes": sum(s.counters.dropped_bytes for s in statuses.values()),
        "receive_latency_ms": percentiles_ms(latencies_s),
        "capture_estimate_error_ms": percentiles_ms(estimate_errors_s),
        "rig_ready_share": ready / max(ticks, 1),
        "rig_snapshot_us_median": statistics.median(snapshot_costs_s) * 1e6,
        "loop_thread_cpu_share": cpu_share,
        "measured_s": wall_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate-hz", type=float, default=10.0)
    parser.add_argument("--out", type=Path, default=RESULTS / "camera_links.json")
    args = parser.parse_args()
    with (
        tempfile.TemporaryDirectory() as directory,
        CameraEmulator(directory, rate_hz=args.rate_hz) as emu,
    ):
        results = asyncio.run(measure(emu, args.seconds))
    report = {
        "benchmark": "camera_links",
        "rate_hz": args.rate_hz,
        "cameras": len(FACE_NAMES),
        "machine": machine(),
        "results": results,
    }
    print(json.dumps(report, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
