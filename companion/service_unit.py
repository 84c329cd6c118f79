"""The systemd unit that runs the daemon, read the way systemd reads it (stdlib only).

What the rest of the package needs from it: which directories the sandboxed daemon may write
(`companion check` refuses a recorder directory outside them) and how long systemd waits for a
start and a stop (the ground station waits a little longer than that, so that it never reports a
failed start that then succeeds). tests/systemd checks these constants against the shipped unit.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

UNIT_NAME = "vision-swarm-companion.service"
INSTALLED_UNIT = Path("/etc/systemd/system") / UNIT_NAME
SHIPPED_UNIT = Path(__file__).resolve().parents[1] / "systemd" / UNIT_NAME  # in a checkout

START_TIMEOUT_S = 120.0  # TimeoutStartSec= of the shipped unit
STOP_TIMEOUT_S = 20.0  # TimeoutStopSec= of the shipped unit
SSH_CONNECT_TIMEOUT_S = 5.0  # ssh -o ConnectTimeout of `companion ground launch`
# `ground launch` waits for `systemctl ACTION` to return: a restart is a stop and then a start,
# each bounded by systemd; 10 s more cover SSH's connection and sudo.
LAUNCH_TIMEOUT_S = STOP_TIMEOUT_S + START_TIMEOUT_S + SSH_CONNECT_TIMEOUT_S + 5.0

# Directory settings systemd creates, owned by User=, under these roots (systemd.exec).
_MANAGED_ROOTS = {
    "StateDirectory": "/var/lib",
    "RuntimeDirectory": "/run",
    "CacheDirectory": "/var/cache",
    "LogsDirectory": "/var/log",
}
_LIST_KEYS = {"ReadWritePaths", "SupplementaryGroups", *_MANAGED_ROOTS}


def read_service_section(path: Path) -> dict[str, list[str]]:
    """The [Service] settings of a unit file and of its drop-ins (`<unit>.d/*.conf`, applied in
    name order, as systemd does). List settings accumulate; an empty assignment clears them;
    any other setting keeps its last value. Raises OSError when the unit file cannot be read."""
    files = [path]
    dropins = path.with_name(path.name + ".d")
    if dropins.is_dir():
        files += sorted(dropins.glob("*.conf"))
    settings: dict[str, list[str]] = {}
    for file in files:
        for key, value in _assignments(file.read_text(encoding="utf-8")):
            if key in _LIST_KEYS:
                settings[key] = (settings.get(key, []) + shlex.split(value)) if value else []
            else:
                settings[key] = [value]
    return settings


def _assignments(text: str) -> list[tuple[str, str]]:
    """(key, value) of every line in [Service]; continuation lines (trailing backslash) joined."""
    out: list[tuple[str, str]] = []
    section = ""
    pending = ""
    for raw in text.splitlines():
        line = pending + raw.strip()
        pending = ""
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        if not line or line[0] in "#;":
            continue
        if line.startswith("["):
            section = line.strip("[]")
        elif section == "Service" and "=" in line:
            key, value = line.split("=", 1)
            out.append((key.strip(), value.strip()))
    return out


@dataclass(frozen=True)
class ServiceSandbox:
    """What the unit lets the daemon write.

    `writable` is None when the unit does not make the file system read-only
    (ProtectSystem= other than "strict"); otherwise every directory the daemon may write, as
    absolute paths. `managed` are those systemd creates and hands to `user` at each start."""

    source: Path
    user: str | None
    groups: tuple[str, ...]
    writable: tuple[PurePosixPath, ...] | None
    managed: tuple[PurePosixPath, ...]

    def writable_root(self, path: Path) -> PurePosixPath | None:
        """The writable directory that holds `path` (absolute), or None if the unit forbids it.
        Only meaningful when `writable` is not None."""
        target = PurePosixPath(path)
        for root in self.writable or ():
            if target == root or root in target.parents:
                return root
        return None


def sandbox_of(unit_path: Path) -> ServiceSandbox:
    """The sandbox of an installed (or shipped) unit file, drop-ins included."""
    settings = read_service_section(unit_path)
    managed = tuple(
        PurePosixPath(root) / name
        for key, root in _MANAGED_ROOTS.items()
        for name in settings.get(key, [])
    )
    strict = settings.get("ProtectSystem", [""])[-1] == "strict"
    rw = tuple(PurePosixPath(p.lstrip("-+")) for p in settings.get("ReadWritePaths", []))
    user = settings.get("User", [None])[-1]
    groups = tuple(settings.get("Group", [])) + tuple(settings.get("SupplementaryGroups", []))
    return ServiceSandbox(
        source=unit_path,
        user=user,
        groups=groups,
        writable=tuple(dict.fromkeys(rw + managed)) if strict else None,
        managed=managed,
    )


def timeout_s(unit_path: Path, key: str) -> float:
    """A time setting of the unit in seconds ("120", "120s", "2min", "1min 30s")."""
    value = read_service_section(unit_path)[key][-1]
    units = {"ms": 1e-3, "s": 1.0, "sec": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}
    total = 0.0
    for part in value.replace("min", "min ").split():
        number = part.rstrip("abcdefghijklmnopqrstuvwxyz")
        total += float(number) * units[part[len(number) :] or "s"]
    return total
