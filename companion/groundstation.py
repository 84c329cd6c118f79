"""The ground station's SSH side: run validated commands on the drones, start/stop their service.

`companion ground launch --hosts drone1 drone2 ...` runs, on every host in parallel,
`ssh [-o OPTION ...] -o BatchMode=yes -o ConnectTimeout=5 [USER@]HOST -- sudo -n systemctl ACTION
UNIT` (the drones need key-based SSH and a sudoers rule for those commands, see
docs/operator-guide.md). Each host gets `timeout_s`; the report says which failed and why: when
an action fails on the drone, the unit's last journal lines (`sudo -n journalctl -u UNIT -n 20
--no-pager -o cat`, over the same SSH) are shown under it, since systemctl itself only says
"see systemctl status".

`SshTarget.argv(remote_argv)` builds the ssh line for any remote argv: every word is validated
and quoted (`shlex.join`), so nothing given on the command line can inject remote shell syntax.
The live monitor is `companion.ground_monitor`, the log download `companion.ground_logs`.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shlex
import signal
from collections.abc import Sequence
from dataclasses import dataclass, replace

from companion.errors import ConfigError
from companion.ground_monitor import (
    DEFAULT_MONITOR_ENDPOINT,
    SwarmTable,
    monitor_zenoh_config,
    run_monitor,
)
from companion.service_unit import LAUNCH_TIMEOUT_S  # above the unit's start+stop timeouts

__all__ = [
    "ACTIONS",
    "DEFAULT_MONITOR_ENDPOINT",
    "DEFAULT_UNIT",
    "JOURNAL_LINES",
    "LaunchResult",
    "RemoteResult",
    "SshTarget",
    "SwarmTable",
    "format_launch",
    "journal_argv",
    "launch",
    "monitor_zenoh_config",
    "run_monitor",
    "run_remote",
    "ssh_command",
    "systemctl_argv",
]

DEFAULT_UNIT = "vision-swarm-companion.service"
ACTIONS = ("start", "stop", "restart", "status", "is-active")
# Actions whose failure is explained by the unit's journal (status prints its own lines).
_JOURNAL_ACTIONS = ("start", "stop", "restart")
JOURNAL_LINES = 20
SSH_OPTIONS = ("-o", "BatchMode=yes", "-o", "ConnectTimeout=5")
SSH_FAILED = 255  # ssh's own exit status: could not connect or authenticate
_HOST_RE = re.compile(r"^[A-Za-z0-9_.:\[\]%-]{1,253}$")
_USER_RE = re.compile(r"^[a-z_][a-z0-9_-]{0,31}$")
_UNIT_RE = re.compile(r"^[A-Za-z0-9@_.:-]{1,200}$")
_OPTION_RE = re.compile(r"^[A-Za-z][A-Za-z0-9]*[= ][^\x00-\x1f]+$")


@dataclass(frozen=True)
class SshTarget:
    """One drone as ssh reaches it. `options` are extra `-o KEY=VALUE`s, placed before the
    defaults (ssh keeps the first value it reads, so they override BatchMode/ConnectTimeout);
    `config_file` is passed as `-F FILE`."""

    host: str
    user: str | None = None
    port: int | None = None
    ssh: str = "ssh"
    options: tuple[str, ...] = ()
    config_file: str | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.host, str) or not _HOST_RE.match(self.host):
            raise ConfigError(f"ground.hosts: {self.host!r} is not a host name or address")
        if self.host.startswith("-"):
            raise ConfigError(f"ground.hosts: {self.host!r} is not a host name or address")
        if self.user is not None and not _USER_RE.match(self.user):
            raise ConfigError(f"ground.user: {self.user!r} is not a user name")
        if self.port is not None and not 1 <= self.port <= 65535:
            raise ConfigError(f"ground.port: {self.port} is outside the allowed range [1, 65535]")
        object.__setattr__(self, "options", tuple(self.options))
        for option in self.options:
            if not isinstance(option, str) or not _OPTION_RE.match(option):
                raise ConfigError(
                    f"ground.ssh_option: {option!r} is not an ssh option KEY=VALUE, "
                    "e.g. 'StrictHostKeyChecking=accept-new'"
                )
        if self.config_file is not None and (
            not self.config_file or self.config_file.startswith("-")
        ):
            raise ConfigError(f"ground.ssh_config: {self.config_file!r} is not a file path")

    @property
    def destination(self) -> str:
        return f"{self.user}@{self.host}" if self.user else self.host

    def argv(self, remote_argv: Sequence[str]) -> list[str]:
        """The local argv that runs `remote_argv` on the drone, each word quoted for its shell."""
        words = list(remote_argv)
        if not words or not all(isinstance(w, str) and w for w in words):
            raise ConfigError(f"ground: remote command {words!r} must be non-empty words")
        if any(ch in w for w in words for ch in "\x00\n\r"):
            raise ConfigError(f"ground: remote command {words!r} contains a control character")
        argv = [self.ssh]
        if self.config_file is not None:
            argv += ["-F", self.config_file]
        for option in self.options:
            argv += ["-o", option]
        argv += SSH_OPTIONS
        if self.port is not None:
            argv += ["-p", str(self.port)]
        return [*argv, self.destination, "--", shlex.join(words)]


def _check_unit(unit: str) -> None:
    if not _UNIT_RE.match(unit):
        raise ConfigError(f"ground.unit: {unit!r} is not a systemd unit name")


def systemctl_argv(action: str, unit: str = DEFAULT_UNIT) -> list[str]:
    """`sudo -n systemctl ACTION UNIT` (ACTION one of `ACTIONS`)."""
    if action not in ACTIONS:
        raise ConfigError(f"ground.action: {action!r} must be one of {', '.join(ACTIONS)}")
    _check_unit(unit)
    return ["sudo", "-n", "systemctl", action, unit]


def journal_argv(unit: str = DEFAULT_UNIT, lines: int = JOURNAL_LINES) -> list[str]:
    """`sudo -n journalctl -u UNIT -n LINES --no-pager -o cat`: the unit's last log lines."""
    _check_unit(unit)
    return ["sudo", "-n", "journalctl", "-u", unit, "-n", str(lines), "--no-pager", "-o", "cat"]


def ssh_command(
    host: str,
    action: str = "start",
    *,
    user: str | None = None,
    unit: str = DEFAULT_UNIT,
    ssh: str = "ssh",
    port: int | None = None,
    options: Sequence[str] = (),
    config_file: str | None = None,
) -> list[str]:
    """The argv that runs `sudo -n systemctl ACTION UNIT` on `host` (validated: no injection)."""
    target = SshTarget(host, user, port, ssh, tuple(options), config_file)
    return target.argv(systemctl_argv(action, unit))


@dataclass(frozen=True)
class RemoteResult:
    """What one host answered: exit status (None: timed out or not started) and output."""

    host: str
    argv: tuple[str, ...]
    returncode: int | None
    output: str  # stdout, and stderr too unless run with merge_stderr=False
    stderr: str = ""  # stderr when run with merge_stderr=False

    @property
    def ok(self) -> bool:
        return self.returncode == 0


@dataclass(frozen=True)
class LaunchResult(RemoteResult):
    """A systemctl action's result, with the unit's last journal lines when it failed."""

    journal: tuple[str, ...] = ()
    journal_error: str = ""  # why no journal lines are shown, if none are


async def run_remote(
    host: str, argv: Sequence[str], timeout_s: float, *, merge_stderr: bool = True
) -> RemoteResult:
    """Run one ssh argv; kill its whole process group after `timeout_s`."""
    try:
        process = await asyncio.create_subprocess_exec(
            *argv,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.STDOUT if merge_stderr else asyncio.subprocess.PIPE,
            start_new_session=True,  # its own process group: a timeout kills all of it
        )
    except OSError as exc:
        return RemoteResult(host, tuple(argv), None, f"cannot run {argv[0]}: {exc.strerror}")
    try:
        out, err = await asyncio.wait_for(process.communicate(), timeout_s)
    except TimeoutError:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)
        await process.wait()
        return RemoteResult(host, tuple(argv), None, f"no answer within {timeout_s:g} s")
    stderr = err.decode(errors="replace").strip() if err else ""
    return RemoteResult(host, tuple(argv), process.returncode, out.decode(errors="replace"), stderr)


async def _launch_one(target: SshTarget, action: str, unit: str, timeout_s: float) -> LaunchResult:
    result = await run_remote(target.host, target.argv(systemctl_argv(action, unit)), timeout_s)
    launched = LaunchResult(result.host, result.argv, result.returncode, result.output.strip())
    failed_remotely = result.returncode not in (0, None, SSH_FAILED)
    if not failed_remotely or action not in _JOURNAL_ACTIONS:
        return launched
    journal = await run_remote(target.host, target.argv(journal_argv(unit)), min(timeout_s, 10.0))
    text = journal.output.strip()
    if journal.ok:
        if not text:
            return replace(launched, journal_error="no entries for the unit")
        return replace(launched, journal=tuple(text.splitlines()))
    last = text.splitlines()[-1] if text else f"exit {journal.returncode}"
    return replace(launched, journal_error=f"not readable: {last}")


async def launch(
    hosts: Sequence[str],
    action: str = "start",
    *,
    user: str | None = None,
    unit: str = DEFAULT_UNIT,
    ssh: str = "ssh",
    port: int | None = None,
    options: Sequence[str] = (),
    config_file: str | None = None,
    timeout_s: float = LAUNCH_TIMEOUT_S,
) -> list[LaunchResult]:
    """Run the action on every host in parallel; results in the order of `hosts`."""
    systemctl_argv(action, unit)  # validate before anything runs
    targets = [SshTarget(h, user, port, ssh, tuple(options), config_file) for h in hosts]
    return list(await asyncio.gather(*(_launch_one(t, action, unit, timeout_s) for t in targets)))


def _indented(lines: Sequence[str], limit: int) -> list[str]:
    shown = list(lines)[-limit:]
    skipped = len(lines) - len(shown)
    return ([f"    ... ({skipped} earlier lines)"] if skipped else []) + [f"    {x}" for x in shown]


def format_launch(results: Sequence[LaunchResult], action: str) -> str:
    """One line per host; a failure also shows what the host printed and the unit's journal."""
    lines = []
    for result in results:
        output = result.output.splitlines()
        if result.ok:
            verdict = "ok"
        elif result.returncode is None:
            verdict = "FAILED"
        else:
            verdict = f"FAILED (exit {result.returncode})"
        show_all = action == "status" or (not result.ok and len(output) > 1)
        detail = "" if show_all or not output else f": {output[-1]}"
        lines.append(f"{result.host:<24} {action:<9} {verdict}{detail}")
        if show_all:
            lines += _indented(output, 40)
        if result.journal:
            lines.append(f"  journal (last {len(result.journal)} lines of the unit):")
            lines += _indented(result.journal, JOURNAL_LINES)
        elif result.journal_error:
            lines.append(f"  journal: {result.journal_error}")
    failed = sum(not r.ok for r in results)
    lines.append(f"{len(results) - failed}/{len(results)} hosts ok")
    return "\n".join(lines)
