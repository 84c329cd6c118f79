"""systemd's notify protocol (sd_notify), a datagram to `$NOTIFY_SOCKET`: no library needed.

The service manager sets `NOTIFY_SOCKET` (a filesystem path, or `@name` for a socket in the
abstract namespace) and, with `WatchdogSec=`, `WATCHDOG_USEC` (and `WATCHDOG_PID`). Messages are
newline-separated `KEY=VALUE` lines: `READY=1`, `STOPPING=1`, `WATCHDOG=1`, `STATUS=text`.
Without `NOTIFY_SOCKET` (not run by systemd) every call is a no-op. Sending never raises: a
failed notification is logged, the daemon carries on.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


def _address(value: str) -> str | None:
    if value.startswith("@"):
        return "\0" + value[1:]  # abstract namespace
    if value.startswith("/"):
        return value
    return None


class SdNotifier:
    """Sends sd_notify messages. `enabled` tells whether a socket was given."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        raw = env.get("NOTIFY_SOCKET", "")
        self._address = _address(raw) if raw else None
        if raw and self._address is None:
            log.warning("NOTIFY_SOCKET=%r is neither a path nor @abstract: ignored", raw)
        self._sock: socket.socket | None = None
        self.watchdog_interval_s = self._watchdog_interval(env)

    def _watchdog_interval(self, env: Mapping[str, str]) -> float | None:
        """Half of WATCHDOG_USEC (systemd's advice), or None when no watchdog is set for us."""
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if self._address is None or not usec.isdigit() or int(usec) == 0:
            return None
        if pid and pid != str(os.getpid()):
            return None  # meant for another process (e.g. a wrapper that exec'd us)
        return int(usec) / 2e6

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def notify(self, *lines: str) -> bool:
        """Send `KEY=VALUE` lines as one datagram; True if it was sent."""
        if self._address is None:
            return False
        payload = "\n".join(lines).encode("utf-8")
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(payload, self._address)
        except OSError as exc:
            log.warning("sd_notify %s failed: %s", lines[0] if lines else "", exc)
            return False
        return True

    def ready(self, status: str = "") -> bool:
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def status(self, text: str) -> bool:
        return self.notify(f"STATUS={text}")

    def stopping(self, status: str = "") -> bool:
        return self.notify("STOPPING=1", *([f"STATUS={status}"] if status else []))

    def close(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
