"""`companion`: the onboard program's command line.

companion run --config FILE            # the daemon (systemd runs this)
companion check --config FILE          # config, model hash and metadata, devices: ready to fly?
companion check --autopilot [--config FILE | --url URL] [--params FILE]
                                       # the live autopilot's parameters against a .params file
companion log summary FILE             # what a flight log (MCAP) holds
companion log recover FILE OUT         # rewrite a log cut short by a crash as a complete file
companion ground launch --hosts H ...  # systemctl start|stop|... on the drones over SSH
companion ground monitor --connect E   # live table of the swarm's Zenoh telemetry
companion conventions                  # frame conventions and flocking defaults this build uses
companion --version

Exit status: 0 success, 1 a check or a remote command failed, 2 a usage or configuration error
(one line on stderr).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Sequence
from dataclasses import asdict

from companion import __version__, frames
from companion.errors import CompanionError, ConfigError
from companion.flocking import FlockingParams
from companion.service_unit import INSTALLED_UNIT, LAUNCH_TIMEOUT_S

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("conventions", help="print frame conventions and flocking defaults")

    run = sub.add_parser("run", help="run the onboard daemon until SIGTERM/SIGINT")
    run.add_argument("--config", required=True, help="the companion TOML file")
    check = sub.add_parser("check", help="check a config, its model and devices (no flying)")
    check.add_argument("--config", help="the companion TOML file")
    check.add_argument(
        "--autopilot",
        action="store_true",
        help="also read the live autopilot's parameters and list every difference from --params "
        "(stop the daemon first: it holds the link)",
    )
    check.add_argument("--url", help="the autopilot link (default: the config's [autopilot] url)")
    check.add_argument(
        "--params", help="QGroundControl .params file (default: /etc/vision-swarm/companion.params)"
    )
    check.add_argument(
        "--timeout", type=float, default=10.0, help="seconds to wait for the autopilot"
    )
    check.add_argument(
        "--unit",
        default=str(INSTALLED_UNIT),
        help="the service's unit file: the recorder directory must be one it lets the service "
        "write (default: the installed unit; skipped if absent)",
    )

    log_parser = sub.add_parser("log", help="flight logs")
    log = log_parser.add_subparsers(dest="log_command", required=True)
    summary = log.add_parser("summary", help="what a flight log (MCAP) holds")
    summary.add_argument("file", help="an .mcap flight log (also one cut short by a crash)")
    summary.add_argument("--max-events", type=int, default=20, help="health events to list")
    recover = log.add_parser("recover", help="rewrite a crash-cut log as a complete MCAP file")
    recover.add_argument("file", help="the .mcap left by a killed daemon")
    recover.add_argument("out", help="the complete, indexed copy to write (must not exist)")

    ground = sub.add_parser("ground", help="ground station").add_subparsers(
        dest="ground_command", required=True
    )
    launch = ground.add_parser("launch", help="systemctl ACTION the service on drones over SSH")
    launch.add_argument("--hosts", nargs="+", required=True, help="drone host names or addresses")
    launch.add_argument("--action", default="start", help="start, stop, restart, status")
    launch.add_argument("--user", default=None, help="SSH user (default: ssh's)")
    launch.add_argument("--port", type=int, default=None, help="SSH port")
    launch.add_argument("--unit", default=None, help="systemd unit name")
    launch.add_argument("--ssh", default="ssh", help="the ssh program")
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
    monitor.add_argument("--clear", action="store_true", help="redraw in place (a terminal)")
    return parser


def conventions_text() -> str:
    params = asdict(FlockingParams())
    lines = [
        f"world frame (simulation): {frames.WORLD_FRAME} (x east, y north, z up)",
        f"autopilot frame (PX4/MAVSDK): {frames.AUTOPILOT_FRAME} (x north, y east, z down)",
        f"body frame of CNN targets: {frames.BODY_FRAME} (x forward, y left, z up)",
        "quaternions: Hamilton, scalar first (w, x, y, z), body -> world",
        "flocking defaults (paper, Table I): "
        + ", ".join(f"{key}={value:g}" for key, value in params.items()),
    ]
    return "\n".join(lines)


def _stop_before_start(signum: int, frame: object) -> None:
    raise SystemExit(0)  # nothing commands the vehicle yet: a clean exit


def cmd_run(config_path: str) -> int:
    # Until the daemon installs its own handlers (after the imports), SIGTERM is a clean exit.
    signal.signal(signal.SIGTERM, _stop_before_start)
    from companion.autopilot import forward_mavsdk_logs
    from companion.config import load_config
    from companion.daemon import Daemon

    config = load_config(config_path)
    logging.basicConfig(level=config.daemon.log_level.upper(), format=LOG_FORMAT, force=True)
    forward_mavsdk_logs()
    asyncio.run(Daemon(config).run())
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from pathlib import Path

    from companion.check import CheckItem, format_report, has_failures, run_checks

    if args.config is None and not (args.autopilot and args.url):
        raise ConfigError("check: give --config FILE, or --autopilot with --url URL")
    items = run_checks(args.config, Path(args.unit)) if args.config is not None else []
    if args.autopilot:
        from companion.param_check import DEFAULT_PARAMS, autopilot_items

        url = args.url or _config_url(args.config)
        params = args.params or str(DEFAULT_PARAMS)
        items += autopilot_items(url, params, args.timeout)
    elif args.params or args.url:
        raise ConfigError("check: --params and --url need --autopilot")
    items = items or [CheckItem("check", "FAIL", "nothing to check")]
    print(format_report(items))
    return 1 if has_failures(items) else 0


def _config_url(config_path: str) -> str:
    from companion.config import load_config

    return load_config(config_path).autopilot.url


def cmd_log(args: argparse.Namespace) -> int:
    from pathlib import Path

    from companion.errors import RecorderError
    from companion.flight_log import format_summary, recover_log, summarize_log

    if not Path(args.file).is_file():
        raise RecorderError(f"{args.file}: no such flight log")
    if args.log_command == "summary":
        print(format_summary(summarize_log(args.file), max_events=args.max_events))
        return 0
    if Path(args.out).exists():
        raise RecorderError(f"{args.out}: already exists; choose a new file")
    count = recover_log(args.file, args.out)
    print(f"{args.out}: {count} messages recovered from {args.file}")
    return 0


def cmd_ground(args: argparse.Namespace) -> int:
    from companion import groundstation as ground

    if args.ground_command == "launch":
        unit = args.unit or ground.DEFAULT_UNIT
        options = {"user": args.user, "unit": unit, "ssh": args.ssh, "port": args.port}
        if args.dry_run:
            for host in args.hosts:
                print(" ".join(ground.ssh_command(host, args.action, **options)))
            return 0
        results = asyncio.run(
            ground.launch(args.hosts, args.action, timeout_s=args.timeout, **options)
        )
        print(ground.format_launch(results, args.action))
        return 0 if all(r.ok for r in results) else 1
    connect = args.connect if args.connect is not None else [ground.DEFAULT_MONITOR_ENDPOINT]
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C ends the monitor
        ground.run_monitor(
            connect,
            listen=args.listen,
            key=args.key,
            interval_s=args.interval,
            duration_s=args.duration,
            clear=args.clear,
        )
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "conventions":
        print(conventions_text())
        return 0
    if args.command == "run":
        return cmd_run(args.config)
    if args.command == "check":
        return cmd_check(args)
    if args.command == "log":
        return cmd_log(args)
    return cmd_ground(args)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return run(argv)
    except CompanionError as exc:
        print(f"companion: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
