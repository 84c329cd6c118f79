"""`companion ground engage | disengage | status` end to end: the ground station's command line
over a real SSH connection (the `sshd` fixture) runs `sudo -n companion ACTION` on the "drone",
which talks to a real daemon's control socket; the daemon flies the PX4 emulator over MAVSDK.
The drone's sudo is the fixture's stand-in that allows exactly the sudoers rule's commands."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path
from typing import Any

from companion.ground_engage import CONTROL_ACTIONS
from companion.health import HealthState
from sim_harness.hil.px4_logic import Px4Mode

from ..daemon_rig import GUARD_S, until


def drone_companion(sshd: Any, control_socket_path: str) -> Path:
    """The drone's `companion` (this checkout's, at the test daemon's socket), and the sudoers
    rule's lines for its control commands."""
    wrapper = Path(sshd.bin_dir) / "companion"
    wrapper.write_text(
        f'#!/bin/sh\nexec {sys.executable} -m companion.cli "$@" --socket {control_socket_path}\n'
    )
    wrapper.chmod(0o755)
    with (Path(sshd.sudo_calls).parent / "allowed").open("a") as rule:
        rule.writelines(f"{wrapper} {action}\n" for action in CONTROL_ACTIONS)
    return wrapper


def test_ground_engage_and_disengage_over_ssh(
    sshd: Any, engage_rig: Any, control_socket_path: str
) -> None:
    wrapper = drone_companion(sshd, control_socket_path)
    rig = engage_rig()
    px4 = rig.px4
    daemon = rig.daemon(control_socket_path, engage="ground")

    def ground(action: str) -> subprocess.CompletedProcess[str]:
        argv = [sys.executable, "-m", "companion.cli", "ground", action, "--hosts", "127.0.0.1"]
        argv += [*sshd.cli_args(), "--companion", str(wrapper)]
        return subprocess.run(argv, capture_output=True, text=True, timeout=60)

    async def body() -> None:
        run = asyncio.create_task(daemon.run())
        try:
            await until(lambda: daemon.ready, GUARD_S, "a healthy pipeline")
            status = await asyncio.to_thread(ground, "status")
            assert status.returncode == 0, status.stdout + status.stderr
            assert "companion engage" in status.stdout and "1/1 hosts ok" in status.stdout
            assert px4.mode is Px4Mode.POSCTL

            engaged = await asyncio.to_thread(ground, "engage")
            assert engaged.returncode == 0, engaged.stdout + engaged.stderr
            await until(lambda: px4.mode is Px4Mode.OFFBOARD, GUARD_S, "OFFBOARD")
            await until(lambda: daemon.health.state is HealthState.ACTIVE, GUARD_S, "ACTIVE")

            released = await asyncio.to_thread(ground, "disengage")
            assert released.returncode == 0, released.stdout + released.stderr
            await until(lambda: px4.mode is Px4Mode.HOLD, GUARD_S, "HOLD")
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)
        assert [f"{wrapper} {a}" for a in ("status", "engage", "disengage")] == [
            line for line in sshd.sudo_log() if line.startswith(str(wrapper))
        ]

    asyncio.run(body())


def test_engage_is_refused_by_a_drone_that_is_not_in_ground_mode(
    sshd: Any, engage_rig: Any, control_socket_path: str
) -> None:
    wrapper = drone_companion(sshd, control_socket_path)
    rig = engage_rig()
    daemon = rig.daemon(control_socket_path, engage="operator")

    async def body() -> subprocess.CompletedProcess[str]:
        run = asyncio.create_task(daemon.run())
        try:
            await until(lambda: daemon.ready, GUARD_S, "a healthy pipeline")
            argv = [sys.executable, "-m", "companion.cli", "ground", "engage", "--hosts"]
            argv += ["127.0.0.1", *sshd.cli_args(), "--companion", str(wrapper)]
            return await asyncio.to_thread(
                subprocess.run, argv, capture_output=True, text=True, timeout=60
            )
        finally:
            daemon.request_stop("test over")
            await asyncio.wait_for(run, 15.0)

    refused = asyncio.run(body())
    assert refused.returncode == 1
    assert (
        "FAILED (exit 1)" in refused.stdout
        and "switching the vehicle to OFFBOARD" in refused.stdout
    )
    assert rig.px4.mode is Px4Mode.POSCTL
