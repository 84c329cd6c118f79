"""`companion engage | disengage | status` on the drone: the daemon's control socket.

companion engage [--config FILE | --socket PATH]      # "ground" mode: engage OFFBOARD
companion disengage [--config FILE | --socket PATH]   # stop commanding: zero velocity, Hold
companion status [--config FILE | --socket PATH]      # health state, reason, offboard state

The socket is only reachable by root and the service user: run these with sudo (the ground
station does, over SSH: `companion ground engage --hosts ...`). Exit status: 0 the daemon accepted,
1 it refused (the message says why), 2 no daemon answered or bad usage.
"""

from __future__ import annotations

import argparse
from typing import Any

from companion.control_channel import COMMANDS, send_command

DEFAULT_CONFIG = "/etc/vision-swarm/companion.toml"


def add_control_parsers(sub: Any) -> None:
    """The three subcommands, on `sub` (argparse subparsers)."""
    helps = {
        "engage": 'engage OFFBOARD ([daemon] engage = "ground")',
        "disengage": "stop commanding: zero velocity, then Hold",
        "status": "the daemon's health state and why",
    }
    for command in COMMANDS:
        parser = sub.add_parser(command, help=helps[command])
        where = parser.add_mutually_exclusive_group()
        where.add_argument("--config", help=f"the companion TOML file (default: {DEFAULT_CONFIG})")
        where.add_argument("--socket", help="the control socket path (instead of --config)")
        parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait")


def socket_of(args: argparse.Namespace) -> str:
    """The socket path: --socket, or the config's `[daemon] control_socket`."""
    if args.socket:
        return str(args.socket)
    from companion.config import load_config
    from companion.errors import ConfigError

    path = load_config(args.config or DEFAULT_CONFIG).daemon.control_socket
    if not path:
        raise ConfigError('daemon.control_socket: "" in the config: this daemon has none')
    return path


def cmd_control(args: argparse.Namespace) -> int:
    reply = send_command(socket_of(args), args.command, args.timeout)
    state = reply.get("state", "?")
    print(
        f"{args.command}: {reply.get('message', '')} (state {state}, engage = "
        f"{reply.get('engage_mode', '?')}, offboard {reply.get('offboard', '?')})"
    )
    return 0 if reply.get("ok") else 1
