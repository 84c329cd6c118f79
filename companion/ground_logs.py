"""`companion ground logs pull`: download the drones' flight logs over SSH, only what is new.

Per host, in parallel, two SSH commands (no rsync needed on the drone, only POSIX tools):

1. a listing of `REMOTE_DIR/*.mcap`: size, whether a recorder is writing it (it holds an
   exclusive `flock`: `flock -n -s FILE true` fails), and whether it ends with the MCAP magic
   (complete, footer written);
2. `tar -C REMOTE_DIR -cf - -- NAME ...` of the files to fetch, read as a stream here.

Into `DEST/<host>/`: a file being written is skipped (pull again after the flight); a file
already here with the same size is skipped; every other file is written as `.NAME.part` and
renamed once all its bytes arrived, so an interrupted pull never leaves a truncated log under a
final name. A log without footer (its daemon was killed) is pulled and reported INCOMPLETE:
`companion log recover` makes a complete copy.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import shlex
import signal
import subprocess
import tarfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from companion.errors import ConfigError
from companion.groundstation import SshTarget, run_remote
from companion.log_budget import MCAP_MAGIC

DEFAULT_REMOTE_DIR = "/var/lib/vision-swarm/flights"
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,200}\.mcap$")
_DIR_RE = re.compile(r"^/[A-Za-z0-9_./-]{0,400}$")
# ssh's keep-alives end a pull whose link died (a transfer itself has no time limit).
_KEEPALIVE = ("ServerAliveInterval=5", "ServerAliveCountMax=3")
# $1: the folder. One line per file: size, writing (1 yes, 0 no, ? no flock), last 8 bytes, name.
_LIST_SCRIPT = (
    'cd -- "$1" || exit 3; for f in *.mcap; do [ -f "$f" ] || continue; '
    'if flock -n -s "$f" true 2>/dev/null; then w=0; elif [ $? -eq 1 ]; then w=1; else w=?; fi; '
    "t=$(tail -c 8 -- \"$f\" | od -An -tx1 | tr -d ' \\n'); "
    'printf "%s %s %s %s\\n" "$(wc -c < "$f")" "$w" "${t:-none}" "$f"; done'
)
_CHUNK_BYTES = 1 << 20


@dataclass(frozen=True)
class RemoteLog:
    """One `*.mcap` on the drone, as listed."""

    name: str
    size_bytes: int
    writing: bool | None  # None: the drone has no `flock` to tell
    complete: bool


@dataclass
class PullResult:
    """What one host's pull did."""

    host: str
    pulled: list[str] = field(default_factory=list)
    pulled_bytes: int = 0
    incomplete: list[str] = field(default_factory=list)  # pulled without footer
    present: list[str] = field(default_factory=list)  # already in DEST with the same size
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (name, why)
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


def check_remote_dir(remote_dir: str) -> str:
    if not _DIR_RE.match(remote_dir) or "/../" in f"{remote_dir}/":
        raise ConfigError(
            f"ground.remote_dir: {remote_dir!r} must be an absolute path of A-Z a-z 0-9 _ . / -"
        )
    return remote_dir


def list_argv(remote_dir: str) -> list[str]:
    """The remote argv that lists `remote_dir`'s logs (see `_LIST_SCRIPT`)."""
    return ["sh", "-c", _LIST_SCRIPT, "sh", check_remote_dir(remote_dir)]


def tar_argv(remote_dir: str, names: Sequence[str]) -> list[str]:
    return ["tar", "-C", check_remote_dir(remote_dir), "-cf", "-", "--", *names]


def parse_listing(text: str) -> list[RemoteLog]:
    """The listing's lines as `RemoteLog`s (names not matching the recorder's are kept, as
    given, for the caller to skip)."""
    logs = []
    for line in text.splitlines():
        parts = line.strip().split(" ", 3)
        if len(parts) != 4 or not parts[0].isdigit():
            continue
        size, writing, tail, name = parts
        logs.append(
            RemoteLog(
                name=name,
                size_bytes=int(size),
                writing=None if writing == "?" else writing == "1",
                complete=tail == MCAP_MAGIC.hex(),
            )
        )
    return logs


def plan_pull(logs: Sequence[RemoteLog], dest: Path, result: PullResult) -> list[RemoteLog]:
    """Which logs to fetch into `dest`; records the others in `result`."""
    wanted = []
    for item in sorted(logs, key=lambda log: log.name):
        if not _NAME_RE.match(item.name):
            result.skipped.append((item.name, "not a flight-log name"))
        elif item.writing:
            result.skipped.append((item.name, "being written (pull again after the flight)"))
        elif (dest / item.name).is_file() and (dest / item.name).stat().st_size == item.size_bytes:
            result.present.append(item.name)
        else:
            wanted.append(item)
    return wanted


def _receive_tar(argv: list[str], dest: Path, wanted: dict[str, RemoteLog]) -> tuple[int, str]:
    """Run the tar-over-ssh argv and write each member; returns (bytes, error or "")."""
    received: set[str] = set()
    written = 0
    process = subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )
    assert process.stdout is not None and process.stderr is not None
    error = ""
    try:
        with tarfile.open(fileobj=process.stdout, mode="r|") as archive:
            for member in archive:
                name = member.name.removeprefix("./")
                source = archive.extractfile(member) if member.isreg() else None
                if name not in wanted or source is None:
                    error = error or f"unexpected member {member.name!r} in the tar stream"
                    continue
                part = dest / f".{name}.part"
                with open(part, "wb") as out:
                    while chunk := source.read(_CHUNK_BYTES):
                        out.write(chunk)
                if part.stat().st_size != member.size:
                    part.unlink()
                    error = error or f"{name}: cut short"
                    continue
                os.utime(part, (member.mtime, member.mtime))
                os.replace(part, dest / name)
                received.add(name)
                written += member.size
    except (tarfile.TarError, OSError) as exc:
        error = error or f"{type(exc).__name__}: {exc}"
    finally:
        with contextlib.suppress(ProcessLookupError):
            if process.poll() is None and error:
                os.killpg(process.pid, signal.SIGKILL)
        process.stdout.close()
        stderr = process.stderr.read().decode(errors="replace").strip()
        process.stderr.close()
        returncode = process.wait()
    missing = sorted(set(wanted) - received)
    if returncode != 0 or missing:
        last = stderr.splitlines()[-1] if stderr else f"exit {returncode}"
        error = error or f"tar over ssh failed ({last}); not received: {', '.join(missing)}"
    return written, error


async def pull_host(
    target: SshTarget, dest_root: Path, remote_dir: str, timeout_s: float
) -> PullResult:
    """List, plan and fetch one host's logs into `dest_root/<host>/`."""
    result = PullResult(target.host)
    listing = await run_remote(
        target.host, target.argv(list_argv(remote_dir)), timeout_s, merge_stderr=False
    )
    if not listing.ok:
        why = listing.stderr.splitlines()[-1] if listing.stderr else listing.output.strip()
        result.error = f"cannot list {remote_dir}: {why or f'exit {listing.returncode}'}"
        return result
    logs = parse_listing(listing.output)
    dest = dest_root / target.host
    dest.mkdir(parents=True, exist_ok=True)
    wanted = {log.name: log for log in plan_pull(logs, dest, result)}
    if not wanted:
        return result
    keepalive = SshTarget(
        target.host, target.user, target.port, target.ssh,
        (*target.options, *_KEEPALIVE), target.config_file,
    )  # fmt: skip
    argv = keepalive.argv(tar_argv(remote_dir, sorted(wanted)))
    written, error = await asyncio.to_thread(_receive_tar, argv, dest, wanted)
    for name in sorted(wanted):
        if (dest / name).is_file() and (dest / name).stat().st_size == wanted[name].size_bytes:
            result.pulled.append(name)
            if not wanted[name].complete:
                result.incomplete.append(name)
    result.pulled_bytes = written
    result.error = error
    return result


async def pull_logs(
    targets: Sequence[SshTarget],
    dest: Path,
    *,
    remote_dir: str = DEFAULT_REMOTE_DIR,
    timeout_s: float = 20.0,
) -> list[PullResult]:
    """Pull every host's new logs in parallel; results in the order of `targets`."""
    check_remote_dir(remote_dir)
    return list(await asyncio.gather(*(pull_host(t, dest, remote_dir, timeout_s) for t in targets)))


def format_pull(results: Sequence[PullResult], dest: Path) -> str:
    lines = []
    for r in results:
        verdict = "ok" if r.ok else "FAILED"
        counts = f"{len(r.pulled)} pulled ({r.pulled_bytes / 1e6:.1f} MB), "
        counts += f"{len(r.present)} already here, {len(r.skipped)} skipped"
        lines.append(f"{r.host:<24} {verdict}: {counts}" + (f"; {r.error}" if r.error else ""))
        lines += [f"    skipped {name}: {why}" for name, why in r.skipped]
        lines += [
            f"    INCOMPLETE {name}: no footer (its daemon was killed); "
            f"companion log recover {shlex.quote(str(dest / r.host / name))} OUT.mcap"
            for name in r.incomplete
        ]
    failed = sum(not r.ok for r in results)
    lines.append(f"{len(results) - failed}/{len(results)} hosts ok; logs in {dest}/<host>/")
    return "\n".join(lines)
