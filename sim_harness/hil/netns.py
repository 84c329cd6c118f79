"""Loopback-only Linux network namespaces for real PX4 SITL (which binds its UDP ports on all
interfaces: it must never run where another machine could reach it or be reached).

`NetNamespace` creates one with `ip netns add` and brings up only `lo`; processes run in it through
`ip netns exec` (`command()`), and this process can create sockets in it (`entered()`: the calling
thread joins the namespace with setns(2) for the duration; sockets keep the namespace they were
created in). Deleting the namespace (`close()`) ends its loopback. Needs root (CAP_SYS_ADMIN) and
iproute2; `unavailable_reason()` says plainly when either is missing.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import subprocess
import uuid
from collections.abc import Iterator, Sequence
from types import TracebackType

from sim_harness.errors import SimError

CLONE_NEWNET = 0x4000_0000
NETNS_DIR = "/run/netns"
_libc = ctypes.CDLL(None, use_errno=True)


class NamespaceError(SimError):
    """A network namespace could not be created, entered or deleted."""


def _ip(*args: str, timeout_s: float = 10.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["ip", *args], capture_output=True, text=True, timeout=timeout_s, check=False
    )


def unavailable_reason() -> str | None:
    """Why loopback-only namespaces cannot be made here (None: they can)."""
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is missing: apt-get install -y iproute2"
    probe = f"vsprobe-{uuid.uuid4().hex[:8]}"
    made = _ip("netns", "add", probe)
    if made.returncode != 0:
        return f"`ip netns add` is not permitted here ({made.stderr.strip()}): run as root"
    _ip("netns", "del", probe)
    return None


def _setns(fd: int) -> None:
    if _libc.setns(fd, CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        raise NamespaceError(f"setns: {os.strerror(err)}")


class NetNamespace:
    """One loopback-only network namespace. Use as a context manager, or create()/close()."""

    def __init__(self, name: str | None = None) -> None:
        self.name = name or f"vswarm-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self._created = False

    def create(self) -> NetNamespace:
        made = _ip("netns", "add", self.name)
        if made.returncode != 0:
            raise NamespaceError(f"ip netns add {self.name}: {made.stderr.strip()}")
        self._created = True
        up = _ip("netns", "exec", self.name, "ip", "link", "set", "lo", "up")
        if up.returncode != 0:
            self.close()
            raise NamespaceError(f"{self.name}: bringing up lo failed: {up.stderr.strip()}")
        return self

    def close(self) -> None:
        """Delete the namespace (its processes must have ended). Idempotent."""
        if self._created:
            self._created = False
            gone = _ip("netns", "del", self.name)
            if gone.returncode != 0 and os.path.exists(os.path.join(NETNS_DIR, self.name)):
                raise NamespaceError(f"ip netns del {self.name}: {gone.stderr.strip()}")

    def __enter__(self) -> NetNamespace:
        return self.create()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def command(self, argv: Sequence[str]) -> list[str]:
        """`argv` run inside the namespace (`ip netns exec NAME ...`)."""
        return ["ip", "netns", "exec", self.name, *argv]

    def interfaces(self) -> list[str]:
        """The names of the namespace's network interfaces (only `lo` when all is well)."""
        shown = _ip("netns", "exec", self.name, "ip", "-o", "link", "show")
        return [line.split(":")[1].strip().split("@")[0] for line in shown.stdout.splitlines()]

    @contextlib.contextmanager
    def entered(self) -> Iterator[None]:
        """The calling thread is in the namespace inside the block (sockets made there stay)."""
        own = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
        try:
            target = os.open(os.path.join(NETNS_DIR, self.name), os.O_RDONLY)
        except OSError as exc:
            os.close(own)
            raise NamespaceError(f"{self.name}: {exc}") from exc
        try:
            _setns(target)
            try:
                yield
            finally:
                _setns(own)
        finally:
            os.close(target)
            os.close(own)
