"""Emulator fidelity: one scripted MAVSDK sequence against our pymavlink PX4 emulator and against
real PX4 (SITL + SIH), comparing what MAVSDK sees.

    .venv/bin/python benchmarks/emulator_fidelity.py   # needs PX4_SITL_TARBALL and root for PX4

The sequence (both autopilots with COM_OBL_RC_ACT 5 / COM_OF_LOSS_T 1 s, the shipped file's rule):
connect, wait healthy, arm, take off, offboard start (1 s pre-stream), 1.5 m/s north for 3 s, a
pilot switch to Hold (PX4: DO_SET_MODE from a ground station; emulator: its pilot hook), offboard
again, a 2 s link pause (a UDP relay between MAVSDK and the autopilot drops everything), 2 s with
the link back, an offboard loss (the relay drops MAVSDK's side only: setpoints stop, telemetry
goes on), the link back, the pilot's Hold, land. MAVSDK's view: call durations, when its
flight-mode telemetry showed each mode, telemetry rates while hovering, speed reached. The
autopilot's own view: its mode changes (emulator: exact stamps; PX4: 1 Hz heartbeats on the GCS
link, and the time of its "Failsafe activated" message). Writes
benchmarks/results/emulator_fidelity.json. Real PX4 runs in a loopback-only network namespace,
this script re-run inside it (`--inner`).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim_harness.hil.px4_logic import Px4Mode  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "emulator_fidelity.json"
PAUSE_S = 2.0  # shorter than MAVSDK's heartbeat timeout (3 s), after which it stops re-sending
LOSS_PARAMS = {"COM_OBL_RC_ACT": 5, "COM_OF_LOSS_T": 1.0}


class Relay:
    """UDP relay: the autopilot sends to `listen_port`, MAVSDK listens on `client_port`."""

    def __init__(self, listen_port: int, client_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", listen_port))
        self.sock.settimeout(0.05)
        self.client = ("127.0.0.1", client_port)
        self.autopilot: tuple[str, int] | None = None
        self.drop_down = self.drop_up = False  # to MAVSDK / to the autopilot
        self._stop = threading.Event()
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65536)
            except (TimeoutError, OSError):
                continue
            if addr == self.client:
                if self.autopilot is not None and not self.drop_up:
                    self.sock.sendto(data, self.autopilot)
            else:
                self.autopilot = addr
                if not self.drop_down:
                    self.sock.sendto(data, self.client)

    def close(self) -> None:
        self._stop.set()
        self.sock.close()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Watch:
    """MAVSDK's telemetry as it arrives: flight modes with times, counts per stream."""

    def __init__(self) -> None:
        self.modes: list[tuple[float, str]] = []
        self.counts = {"position_velocity_ned": 0, "attitude_quaternion": 0, "flight_mode": 0}
        self.velocity: tuple[float, float, float] = (math.nan,) * 3
        self.in_air = False
        self.armed = False
        self.armable = False

    def mode(self) -> str:
        return self.modes[-1][1] if self.modes else "?"

    def first_mode_since(self, name: str, t_s: float) -> float | None:
        return next((t - t_s for t, m in self.modes if m == name and t >= t_s), None)


async def sequence(system_url: str, relay: Relay, pilot: Any) -> dict[str, Any]:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, VelocityNedYaw
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    out: dict[str, Any] = {}
    watch = Watch()
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER))
    t0 = time.monotonic()
    await mavsdk.add_any_connection(system_url)
    system = await mavsdk.first_autopilot(30.0)
    out["discovery_s"] = time.monotonic() - t0
    action, offboard, tel = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)

    async def consume(stream: Any, name: str, on: Any = None) -> None:
        async for item in stream:
            watch.counts[name] = watch.counts.get(name, 0) + 1
            if on is not None:
                on(item)

    def on_mode(m: Any) -> None:
        if not watch.modes or watch.modes[-1][1] != m.name:
            watch.modes.append((time.monotonic(), m.name))

    def on_vel(pv: Any) -> None:
        v = pv.velocity
        watch.velocity = (v.north_m_s, v.east_m_s, v.down_m_s)

    tasks = [
        asyncio.create_task(consume(tel.subscribe_flight_mode(), "flight_mode", on_mode)),
        asyncio.create_task(
            consume(tel.subscribe_position_velocity_ned(), "position_velocity_ned", on_vel)
        ),
        asyncio.create_task(consume(tel.subscribe_attitude_quaternion(), "attitude_quaternion")),
        asyncio.create_task(
            consume(tel.subscribe_in_air(), "in_air", lambda a: setattr(watch, "in_air", a))
        ),
        asyncio.create_task(
            consume(tel.subscribe_armed(), "armed", lambda a: setattr(watch, "armed", a))
        ),
        asyncio.create_task(
            consume(
                tel.subscribe_health(), "health", lambda h: setattr(watch, "armable", h.is_armable)
            )
        ),
    ]

    async def until(cond: Any, timeout_s: float) -> float | None:
        start = time.monotonic()
        while not cond():
            if time.monotonic() - start > timeout_s:
                return None
            await asyncio.sleep(0.01)
        return time.monotonic() - start

    async def timed(call: Any) -> float:
        start = time.monotonic()
        await call
        return time.monotonic() - start

    out["healthy_s"] = await until(lambda: watch.armable, 60.0)
    out["arm_call_s"] = await timed(action.arm())
    t = time.monotonic()
    out["takeoff_call_s"] = await timed(action.takeoff())
    out["takeoff_to_hold_s"] = await until(
        lambda: (
            watch.in_air
            and watch.mode() == "HOLD"
            and watch.first_mode_since("TAKEOFF", t) is not None
        ),
        60.0,
    )
    before = dict(watch.counts)
    await asyncio.sleep(3.0)
    out["rates_hz"] = {k: (watch.counts[k] - before.get(k, 0)) / 3.0 for k in watch.counts}

    await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
    await asyncio.sleep(1.0)
    t = time.monotonic()
    out["offboard_start_call_s"] = await timed(offboard.start())
    out["offboard_seen_s"] = await until(
        lambda: watch.first_mode_since("OFFBOARD", t) is not None, 5.0
    )
    await offboard.set_velocity_ned(VelocityNedYaw(1.5, 0.0, 0.0, 0.0))
    await asyncio.sleep(3.0)
    out["speed_after_3s_mps"] = math.hypot(watch.velocity[0], watch.velocity[1])

    t = time.monotonic()
    pilot.set_mode(Px4Mode.HOLD)
    out["pilot_hold_seen_s"] = await until(
        lambda: watch.first_mode_since("HOLD", t) is not None, 5.0
    )
    await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
    t = time.monotonic()
    await offboard.start()
    out["offboard_again_seen_s"] = await until(
        lambda: watch.first_mode_since("OFFBOARD", t) is not None, 5.0
    )

    relay.drop_down = relay.drop_up = True
    t_pause = time.monotonic()
    await asyncio.sleep(PAUSE_S)
    out["mode_at_end_of_pause"] = pilot.truth_mode()
    relay.drop_down = relay.drop_up = False
    await asyncio.sleep(2.0)
    out["mode_2s_after_link_back"] = pilot.truth_mode()
    out["mavsdk_modes_after_pause"] = [m for tt, m in watch.modes if tt >= t_pause]
    out["link_pause_autopilot"] = pilot.changes_since(t_pause)

    pilot.set_mode(Px4Mode.HOLD)  # whatever the pause left, a known start for the loss phase
    await until(lambda: watch.mode() == "HOLD", 4.0)
    await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
    t = time.monotonic()
    await offboard.start()
    out["offboard_before_loss_seen_s"] = await until(
        lambda: watch.first_mode_since("OFFBOARD", t) is not None, 5.0
    )
    relay.drop_up = True  # MAVSDK's setpoints stop arriving; telemetry still flows
    t_loss = time.monotonic()
    out["offboard_loss_seen_s"] = await until(
        lambda: watch.first_mode_since("HOLD", t_loss) is not None, 6.0
    )
    out["offboard_loss_autopilot"] = pilot.changes_since(t_loss)
    await asyncio.sleep(3.0)  # MAVSDK has seen HOLD and stopped re-sending by now
    relay.drop_up = False
    await asyncio.sleep(1.0)
    out["mode_1s_after_loss_link_back"] = pilot.truth_mode()
    # One setpoint, no mode request: what a restarted companion sends first (issue 19 finding 2).
    t_back = time.monotonic()
    await offboard.set_velocity_ned(VelocityNedYaw(0.0, 0.0, 0.0, 0.0))
    out["resumed_offboard_by_one_setpoint_s"] = await until(
        lambda: watch.first_mode_since("OFFBOARD", t_back) is not None, 4.0
    )
    out["resume_autopilot"] = pilot.changes_since(t_back)
    pilot.set_mode(Px4Mode.HOLD)
    await until(lambda: watch.mode() == "HOLD", 4.0)
    out["land_call_s"] = await timed(action.land())
    out["land_to_disarmed_s"] = await until(lambda: not watch.armed, 60.0)
    out["mavsdk_modes"] = [(round(tt - t0, 2), m) for tt, m in watch.modes]
    for task in tasks:
        task.cancel()
    await asyncio.sleep(0.2)
    mavsdk.destroy()
    return out


class EmulatorPilot:
    def __init__(self, emulator: Any) -> None:
        self.emulator = emulator
        self.t0_wall = time.monotonic() - emulator.now_s()

    def set_mode(self, mode: Px4Mode) -> None:
        self.emulator.pilot_switch_mode(mode)

    def truth_mode(self) -> str:
        return self.emulator.mode.name

    def changes_since(self, t_s: float) -> list[tuple[float, str, str]]:
        return [
            (round(c.t_s + self.t0_wall - t_s, 3), c.new.name, c.reason)
            for c in self.emulator.mode_changes()
            if c.t_s + self.t0_wall >= t_s
        ]


class GcsPilot:
    def __init__(self, gcs: Any) -> None:
        self.gcs = gcs

    def set_mode(self, mode: Px4Mode) -> None:
        self.gcs.set_mode(mode)

    def truth_mode(self) -> str:
        mode = self.gcs.mode
        return "?" if mode is None else mode.name

    def changes_since(self, t_s: float) -> list[tuple[float, str, str]]:
        changes = [
            (round(m.t_s - t_s, 3), m.mode.name if m.mode else "?", "heartbeat (1 Hz)")
            for m in self.gcs.mode_changes(t_s)
        ]
        texts = [(round(t - t_s, 3), "-", text.strip()) for t, text in self.gcs.texts if t >= t_s]
        return sorted(changes + [x for x in texts if "ailsafe" in x[2]])


def run_emulator() -> dict[str, Any]:
    from sim_harness.hil.autopilot_emulator import AutopilotEmulator
    from sim_harness.hil.emulator_config import EmulatorConfig
    from sim_harness.hil.px4_params import logic_config

    relay_port, client_port = free_port(), free_port()
    with AutopilotEmulator(EmulatorConfig(relay_port, px4=logic_config())) as emulator:
        relay = Relay(relay_port, client_port)
        try:
            return asyncio.run(
                sequence(f"udpin://127.0.0.1:{client_port}", relay, EmulatorPilot(emulator))
            )
        finally:
            relay.close()


def run_px4_inner() -> dict[str, Any]:
    from sim_harness.hil.px4_gcs import GroundStation

    client_port = free_port()
    relay = Relay(14540, client_port)
    with GroundStation(18570) as gcs:
        try:
            return asyncio.run(sequence(f"udpin://127.0.0.1:{client_port}", relay, GcsPilot(gcs)))
        finally:
            relay.close()


def run_px4() -> dict[str, Any] | str:
    from sim_harness.hil.px4_sitl import (
        Px4Instance,
        Px4Sitl,
        tarball_from_env,
        unavailable_reason,
        unpack,
    )

    reason = unavailable_reason()
    if reason is not None:
        return f"not run: {reason}"
    tarball = tarball_from_env()
    assert tarball is not None
    with (
        tempfile.TemporaryDirectory(prefix="px4-build-") as build,
        Px4Sitl(unpack(tarball, Path(build))) as sitl,
    ):
        sitl.start([Px4Instance(0, params=LOSS_PARAMS)])
        argv = sitl.namespace.command([sys.executable, __file__, "--inner"])
        done = subprocess.run(argv, capture_output=True, text=True, timeout=400, check=False)
        if done.returncode != 0:
            return f"failed: {done.stderr[-2000:]}"
        return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if args.inner:
        print(json.dumps(run_px4_inner()))
        return
    results = {
        "command": "python benchmarks/emulator_fidelity.py",
        "loss_params": LOSS_PARAMS,
        "emulator": run_emulator(),
        "px4_sitl": run_px4(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
