"""The daemon's local control channel: `companion engage | disengage | status` on the drone.

A unix socket (`[daemon] control_socket`, default /run/vision-swarm/control.sock; systemd makes
its directory, mode 0750, owned by the service user). The socket itself is mode 0660: only root
and the service user (and its group, which holds no one else) can connect. Nothing listens on
the network: the ground station reaches it by running `companion engage` over SSH.

Protocol: the client sends one command line (`engage`, `disengage` or `status`, at most
`MAX_LINE` bytes); the daemon answers one JSON line `{"ok": bool, "message": str, ...}` and
closes. The daemon decides (`Handler`); this module only moves the lines.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

from companion.errors import CompanionError

log = logging.getLogger(__name__)
COMMANDS = ("engage", "disengage", "status")
MAX_LINE = 64
READ_TIMEOUT_S = 2.0
SOCKET_MODE = 0o660
Handler = Callable[[str], dict[str, Any]]


class ControlError(CompanionError):
    """The control socket cannot be opened or reached."""


class ControlChannel:
    """The daemon's side: `await open()`, then every connection's command goes to `handler`."""

    def __init__(self, path: str, handler: Handler) -> None:
        self.path = Path(path)
        self._handler = handler
        self._server: asyncio.Server | None = None

    async def open(self) -> None:
        """Listen; raises `ControlError` if the path is unusable or another daemon listens."""
        if self.path.exists() or self.path.is_symlink():
            if not stat.S_ISSOCK(self.path.lstat().st_mode):
                raise ControlError(f"control socket {self.path}: exists and is not a socket")
            if _answers(self.path):
                raise ControlError(f"control socket {self.path}: another daemon listens on it")
            self.path.unlink()  # left by a killed daemon
        try:
            self._server = await asyncio.start_unix_server(self._serve, path=str(self.path))
            os.chmod(self.path, SOCKET_MODE)
        except OSError as exc:
            raise ControlError(f"control socket {self.path}: {exc.strerror or exc}") from exc
        log.info("control socket: %s", self.path)

    async def close(self) -> None:
        server, self._server = self._server, None
        if server is None:
            return
        server.close()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(server.wait_closed(), 1.0)
        with contextlib.suppress(OSError):
            self.path.unlink()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            line = await asyncio.wait_for(reader.readline(), READ_TIMEOUT_S)
            command = line.decode("ascii", "replace").strip()
            if len(line) > MAX_LINE or command not in COMMANDS:
                reply: dict[str, Any] = {
                    "ok": False,
                    "message": f"unknown command {command[:MAX_LINE]!r}: one of "
                    + ", ".join(COMMANDS),
                }
            else:
                reply = self._handler(command)
            writer.write(json.dumps(reply).encode() + b"\n")
            await writer.drain()
        except (TimeoutError, ConnectionError) as exc:
            log.debug("control connection dropped: %s", exc)
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()


def _answers(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(0.5)
        try:
            sock.connect(str(path))
        except OSError:
            return False
    return True


def send_command(path: str | Path, command: str, timeout_s: float = 5.0) -> dict[str, Any]:
    """The client: send `command`, return the daemon's JSON answer (raises `ControlError`)."""
    if command not in COMMANDS:
        raise ControlError(f"unknown command {command!r}: one of {', '.join(COMMANDS)}")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(str(path))
            sock.sendall(command.encode() + b"\n")
            data = b""
            while not data.endswith(b"\n"):
                chunk = sock.recv(4096)
                if not chunk:
                    break
                data += chunk
        except FileNotFoundError:
            raise ControlError(
                f"no daemon at {path}: is the service running? (systemctl status)"
            ) from None
        except PermissionError:
            raise ControlError(
                f"{path}: permission denied (run as root or the service user)"
            ) from None
        except OSError as exc:
            raise ControlError(f"{path}: {exc.strerror or exc}") from exc
    try:
        reply = json.loads(data)
    except ValueError:
        raise ControlError(f"{path}: no answer from the daemon") from None
    if not isinstance(reply, dict):
        raise ControlError(f"{path}: malformed answer {reply!r}")
    return reply
