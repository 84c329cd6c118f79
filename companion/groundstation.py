"""The ground station: start/stop the drones' services over SSH, watch their telemetry live.

`companion ground launch --hosts drone1 drone2 ...` runs, on every host in parallel,
`ssh -o BatchMode=yes -o ConnectTimeout=5 [USER@]HOST -- sudo -n systemctl ACTION UNIT`
(the drones need key-based SSH and a sudoers rule for that one command, see
docs/operator-guide.md). Each host gets `timeout_s`; the report says which failed and why.

`companion ground monitor --connect tcp/DRONE:7447 ...` opens a Zenoh peer session (multicast
scouting off, explicit endpoints, loopback by default), subscribes to `swarm/**` and prints a
table of every drone heard: health state, flight mode, position, commanded velocity, reason and
the age of the last message. It only subscribes: it cannot command anything.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import shlex
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import IO, Any

from companion.errors import ConfigError
from companion.service_unit import LAUNCH_TIMEOUT_S  # above the unit's start+stop timeouts

DEFAULT_UNIT = "vision-swarm-companion.service"
ACTIONS = ("start", "stop", "restart", "status", "is-active")
SSH_OPTIONS = ("-o", "BatchMode=yes", "-o", "ConnectTimeout=5")
DEFAULT_MONITOR_ENDPOINT = "tcp/127.0.0.1:7447"
_HOST_RE = re.compile(r"^[A-Za-z0-9_.:\[\]%-]{1,253}$")
_USER_RE = re.compile(r"^[a-z_][a-z0-9_-]{0,31}$")
_UNIT_RE = re.compile(r"^[A-Za-z0-9@_.:-]{1,200}$")

# -- launch ---------------------------------------------------------------------------------


def ssh_command(
    host: str,
    action: str = "start",
    *,
    user: str | None = None,
    unit: str = DEFAULT_UNIT,
    ssh: str = "ssh",
    port: int | None = None,
) -> list[str]:
    """The argv that runs `sudo -n systemctl ACTION UNIT` on `host` (validated: no injection)."""
    if not _HOST_RE.match(host) or host.startswith("-"):
        raise ConfigError(f"ground.hosts: {host!r} is not a host name or address")
    if action not in ACTIONS:
        raise ConfigError(f"ground.action: {action!r} must be one of {', '.join(ACTIONS)}")
    if user is not None and not _USER_RE.match(user):
        raise ConfigError(f"ground.user: {user!r} is not a user name")
    if not _UNIT_RE.match(unit):
        raise ConfigError(f"ground.unit: {unit!r} is not a systemd unit name")
    argv = [ssh, *SSH_OPTIONS]
    if port is not None:
        if not 1 <= port <= 65535:
            raise ConfigError(f"ground.port: {port} is outside the allowed range [1, 65535]")
        argv += ["-p", str(port)]
    target = f"{user}@{host}" if user else host
    remote = shlex.join(["sudo", "-n", "systemctl", action, unit])
    return [*argv, target, "--", remote]


@dataclass(frozen=True)
class LaunchResult:
    """What one host answered: exit status (None: timed out or not started) and output."""

    host: str
    argv: tuple[str, ...]
    returncode: int | None
    output: str

    @property
    def ok(self) -> bool:
        return self.returncode == 0


async def _run_one(host: str, argv: list[str], timeout_s: float) -> LaunchResult:
    try:
        process = await asyncio.create_subprocess_exec(
            *argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT,
            start_new_session=True,  # its own process group: a timeout kills all of it
        )
    except OSError as exc:
        return LaunchResult(host, tuple(argv), None, f"cannot run {argv[0]}: {exc.strerror}")
    try:
        out, _ = await asyncio.wait_for(process.communicate(), timeout_s)
    except TimeoutError:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        await process.wait()
        return LaunchResult(host, tuple(argv), None, f"no answer within {timeout_s:g} s")
    text = out.decode(errors="replace").strip()
    return LaunchResult(host, tuple(argv), process.returncode, text)


async def launch(
    hosts: Sequence[str],
    action: str = "start",
    *,
    user: str | None = None,
    unit: str = DEFAULT_UNIT,
    ssh: str = "ssh",
    port: int | None = None,
    timeout_s: float = LAUNCH_TIMEOUT_S,
) -> list[LaunchResult]:
    """Run the action on every host in parallel; results in the order of `hosts`."""
    commands = [ssh_command(h, action, user=user, unit=unit, ssh=ssh, port=port) for h in hosts]
    runs = (_run_one(host, argv, timeout_s) for host, argv in zip(hosts, commands, strict=True))
    return list(await asyncio.gather(*runs))


def format_launch(results: Sequence[LaunchResult], action: str) -> str:
    lines = []
    for result in results:
        if result.ok:
            verdict = "ok"
        elif result.returncode is None:
            verdict = "FAILED"
        else:
            verdict = f"FAILED (exit {result.returncode})"
        detail = result.output.splitlines()[-1] if result.output else ""
        lines.append(f"{result.host:<24} {action:<9} {verdict}" + (f": {detail}" if detail else ""))
    failed = sum(not r.ok for r in results)
    lines.append(f"{len(results) - failed}/{len(results)} hosts ok")
    return "\n".join(lines)


# -- monitor --------------------------------------------------------------------------------


def _fmt_vec(value: Any, digits: int = 1) -> str:
    if not isinstance(value, list) or len(value) != 3:
        return "-"
    return "(" + ", ".join("-" if v is None else f"{v:+.{digits}f}" for v in value) + ")"


class SwarmTable:
    """Latest telemetry per drone and kind (`state`, `health`, `setpoint`), as a text table.

    `update` is called from Zenoh's threads; `render` from the printing thread.
    """

    COLUMNS = ("drone", "health", "mode", "armed", "pos NED m", "cmd NED m/s", "age s", "reason")

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._drones: dict[str, dict[str, tuple[float, dict[str, Any]]]] = {}
        self.received = 0

    def update(self, key: str, payload: bytes) -> None:
        """One sample on `<prefix>/<drone>/<kind>`; non-JSON kinds (preview) only count."""
        parts = key.split("/")
        if len(parts) < 3:
            return
        drone, kind = parts[-2], parts[-1]
        with self._lock:
            self.received += 1
            entry = self._drones.setdefault(drone, {})
            if kind in ("state", "health", "setpoint"):
                try:
                    message = json.loads(payload)
                except ValueError:
                    return
                data = message.get("data") if isinstance(message, dict) else None
                if isinstance(data, dict):
                    entry[kind] = (self._clock(), data)
            else:
                entry[kind] = (self._clock(), {})

    def drones(self) -> list[str]:
        with self._lock:
            return sorted(self._drones)

    def rows(self) -> list[tuple[str, ...]]:
        now = self._clock()
        rows: list[tuple[str, ...]] = []
        with self._lock:
            for drone in sorted(self._drones):
                kinds = self._drones[drone]
                state = kinds.get("state", (now, {}))[1]
                health = kinds.get("health", (now, {}))[1]
                setpoint = kinds.get("setpoint", (now, {}))[1]
                last = max(t for t, _ in kinds.values())
                armed = state.get("armed")
                rows.append(
                    (
                        drone,
                        str(health.get("state") or state.get("health") or "?"),
                        str(state.get("flight_mode") or "?"),
                        "?" if armed is None else ("yes" if armed else "no"),
                        _fmt_vec(state.get("position_ned_m")),
                        _fmt_vec(setpoint.get("vel_ned"), 2),
                        f"{now - last:.1f}",
                        str(health.get("reason") or "")[:60],
                    )
                )
        return rows

    def render(self) -> str:
        rows = [self.COLUMNS, *self.rows()]
        widths = [max(len(row[i]) for row in rows) for i in range(len(self.COLUMNS))]
        lines = [
            "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows
        ]
        if len(rows) == 1:
            lines.append("(no drone heard yet)")
        return "\n".join(lines)


def monitor_zenoh_config(connect: Sequence[str], listen: Sequence[str] = ()) -> Any:
    """A peer session config: explicit endpoints, multicast scouting off."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return conf


def run_monitor(
    connect: Sequence[str] = (DEFAULT_MONITOR_ENDPOINT,),
    *,
    listen: Sequence[str] = (),
    key: str = "swarm/**",
    interval_s: float = 1.0,
    duration_s: float | None = None,
    out: IO[str] = sys.stdout,
    clear: bool = False,
) -> SwarmTable:
    """Subscribe and print the table every `interval_s` until `duration_s` (None: Ctrl-C)."""
    import zenoh

    table = SwarmTable()
    session = zenoh.open(monitor_zenoh_config(connect, listen))
    try:
        subscriber = session.declare_subscriber(
            key, lambda sample: table.update(str(sample.key_expr), sample.payload.to_bytes())
        )
        try:
            start = time.monotonic()
            while duration_s is None or time.monotonic() - start < duration_s:
                wait = interval_s
                if duration_s is not None:
                    wait = min(interval_s, max(0.0, start + duration_s - time.monotonic()))
                time.sleep(wait)
                if clear:
                    out.write("\x1b[H\x1b[2J")
                out.write(table.render() + "\n\n")
                out.flush()
        finally:
            subscriber.undeclare()  # type: ignore[no-untyped-call]
    finally:
        session.close()  # type: ignore[no-untyped-call]
    return table
