"""`companion ground ...`: the ground station's subcommands (parsers and dispatch).

companion ground launch --hosts H ... [--action start|stop|restart|status|is-active]
companion ground monitor --connect tcp/HOST:PORT ...
companion ground logs pull --hosts H ... --dest DIR
companion ground engage | disengage | status --hosts H ...   # the daemons' control sockets
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from pathlib import Path
from typing import Any

from companion.service_unit import LAUNCH_TIMEOUT_S


def _add_ssh_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hosts", nargs="+", required=True, help="drone host names or addresses")
    parser.add_argument("--user", default=None, help="SSH user (default: ssh's)")
    parser.add_argument("--port", type=int, default=None, help="SSH port")
    parser.add_argument("--ssh", default="ssh", help="the ssh program")
    parser.add_argument(
        "--ssh-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an ssh -o option, repeatable; it overrides the defaults (BatchMode=yes, "
        "ConnectTimeout=5), e.g. StrictHostKeyChecking=accept-new",
    )
    parser.add_argument("--ssh-config", default=None, help="an ssh config file (ssh -F FILE)")


def add_ground_parser(sub: Any) -> None:
    """The `ground` subcommand and its own subcommands, on `sub` (argparse subparsers)."""
    ground = sub.add_parser("ground", help="ground station").add_subparsers(
        dest="ground_command", required=True
    )
    launch = ground.add_parser("launch", help="systemctl ACTION the service on drones over SSH")
    _add_ssh_arguments(launch)
    launch.add_argument("--action", default="start", help="start, stop, restart, status, is-active")
    launch.add_argument("--unit", default=None, help="systemd unit name")
    launch.add_argument(
        "--timeout",
        type=float,
        default=LAUNCH_TIMEOUT_S,
        help="seconds per host (default: longer than the unit's start + stop timeouts)",
    )
    launch.add_argument("--dry-run", action="store_true", help="print the commands only")

    monitor = ground.add_parser("monitor", help="live table of swarm/** telemetry over Zenoh")
    monitor.add_argument(
        "--connect", nargs="+", default=None, help="Zenoh endpoints of the drones (tcp/HOST:PORT)"
    )
    monitor.add_argument("--listen", nargs="*", default=[], help="endpoints to listen on")
    monitor.add_argument("--key", default="swarm/**", help="key expression to subscribe to")
    monitor.add_argument("--interval", type=float, default=1.0, help="seconds between tables")
    monitor.add_argument("--duration", type=float, default=None, help="stop after this long")
    monitor.add_argument(
        "--stale-after", type=float, default=2.0, help="mark a drone silent this long STALE (s)"
    )
    monitor.add_argument("--clear", action="store_true", help="redraw in place (a terminal)")

    from companion.ground_engage import COMPANION_BIN, CONTROL_ACTIONS, DEFAULT_TIMEOUT_S

    helps = {
        "engage": 'engage OFFBOARD on drones whose [daemon] engage = "ground"',
        "disengage": "stop commanding: zero velocity, then Hold",
        "status": "each daemon's health state and why",
    }
    for action in CONTROL_ACTIONS:
        control = ground.add_parser(action, help=helps[action] + " (over SSH)")
        _add_ssh_arguments(control)
        control.add_argument(
            "--companion", default=COMPANION_BIN, help="the drone's companion program"
        )
        control.add_argument(
            "--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="seconds per host"
        )

    logs = ground.add_parser("logs", help="flight logs on the drones").add_subparsers(
        dest="logs_command", required=True
    )
    pull = logs.add_parser("pull", help="download the drones' new, closed flight logs over SSH")
    _add_ssh_arguments(pull)
    pull.add_argument("--dest", required=True, help="local folder; logs go to DEST/<host>/")
    pull.add_argument("--remote-dir", default=None, help="the drones' flight-log folder")
    pull.add_argument("--timeout", type=float, default=20.0, help="seconds for each host's listing")


def _targets(args: argparse.Namespace) -> list[Any]:
    from companion.groundstation import SshTarget

    options = tuple(args.ssh_option)
    return [
        SshTarget(host, args.user, args.port, args.ssh, options, args.ssh_config)
        for host in args.hosts
    ]


def cmd_ground(args: argparse.Namespace) -> int:
    from companion import groundstation as ground
    from companion.validation import require_range

    if args.ground_command == "launch":
        unit = args.unit or ground.DEFAULT_UNIT
        options = {
            "user": args.user,
            "unit": unit,
            "ssh": args.ssh,
            "port": args.port,
            "options": tuple(args.ssh_option),
            "config_file": args.ssh_config,
        }
        if args.dry_run:
            for host in args.hosts:
                print(" ".join(ground.ssh_command(host, args.action, **options)))
            return 0
        require_range("ground launch --timeout", args.timeout, 0.0, 3600.0, low_inclusive=False)
        results = asyncio.run(
            ground.launch(args.hosts, args.action, timeout_s=args.timeout, **options)
        )
        print(ground.format_launch(results, args.action))
        return 0 if all(r.ok for r in results) else 1
    if args.ground_command in ("engage", "disengage", "status"):
        from companion.ground_engage import control_all, format_control

        action = args.ground_command
        require_range(f"ground {action} --timeout", args.timeout, 0.0, 3600.0, low_inclusive=False)
        answers = asyncio.run(
            control_all(_targets(args), action, companion=args.companion, timeout_s=args.timeout)
        )
        print(format_control(answers, action))
        return 0 if all(r.ok for r in answers) else 1
    if args.ground_command == "logs":
        from companion import ground_logs

        require_range("ground logs pull --timeout", args.timeout, 0.0, 3600.0, low_inclusive=False)
        remote_dir = args.remote_dir or ground_logs.DEFAULT_REMOTE_DIR
        dest = Path(args.dest).expanduser()
        pulled = asyncio.run(
            ground_logs.pull_logs(
                _targets(args), dest, remote_dir=remote_dir, timeout_s=args.timeout
            )
        )
        print(ground_logs.format_pull(pulled, dest))
        return 0 if all(r.ok for r in pulled) else 1
    connect = args.connect if args.connect is not None else [ground.DEFAULT_MONITOR_ENDPOINT]
    require_range("ground monitor --interval", args.interval, 0.05, 3600.0)
    require_range(
        "ground monitor --stale-after", args.stale_after, 0.0, 3600.0, low_inclusive=False
    )
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C ends the monitor
        ground.run_monitor(
            connect,
            listen=args.listen,
            key=args.key,
            interval_s=args.interval,
            duration_s=args.duration,
            clear=args.clear,
            stale_after_s=args.stale_after,
        )
    return 0
