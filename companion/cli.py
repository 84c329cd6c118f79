"""`companion`: the onboard program's command line.

companion run --config FILE            # the daemon (systemd runs this)
companion check --config FILE          # config, model hash and metadata, devices: ready to fly?
companion check --autopilot [--config FILE | --url URL] [--params FILE]
                                       # the live autopilot's parameters against a .params file
companion params file --sysid N        # the PX4 parameter file for drone N (--drones 1-9 --out DIR)
companion log summary FILE             # what a flight log (MCAP) holds
companion log recover FILE OUT         # rewrite a log cut short by a crash as a complete file
companion ground launch --hosts H ...  # systemctl start|stop|... on the drones over SSH
companion ground monitor --connect E   # live table of the swarm's Zenoh telemetry
companion ground logs pull --hosts H ... --dest DIR   # the drones' new flight logs over SSH
companion engage | disengage | status  # the running daemon's control socket (sudo)
companion conventions                  # frame conventions and flocking defaults this build uses
companion --version [--config FILE]    # version, source commit, the model's SHA-256

Exit status: 0 success, 1 a check or a remote command failed, 2 a usage or configuration error
(one line on stderr).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import signal
import sys
from collections.abc import Sequence
from dataclasses import asdict

from companion import frames
from companion.control_cli import add_control_parsers, cmd_control
from companion.errors import CompanionError, ConfigError
from companion.flocking import FlockingParams
from companion.ground_cli import add_ground_parser, cmd_ground
from companion.service_unit import INSTALLED_UNIT

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--version",
        action="store_true",
        help="print the version, the source commit and the model's SHA-256, then exit "
        "(companion --version [--config FILE]: that config's model)",
    )
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

    from companion.px4_params_file import add_params_parser

    add_params_parser(sub)
    log_parser = sub.add_parser("log", help="flight logs")
    log = log_parser.add_subparsers(dest="log_command", required=True)
    summary = log.add_parser("summary", help="what a flight log (MCAP) holds")
    summary.add_argument("file", help="an .mcap flight log (also one cut short by a crash)")
    summary.add_argument("--max-events", type=int, default=20, help="health events to list")
    recover = log.add_parser("recover", help="rewrite a crash-cut log as a complete MCAP file")
    recover.add_argument("file", help="the .mcap left by a killed daemon")
    recover.add_argument("out", help="the complete, indexed copy to write (must not exist)")

    add_ground_parser(sub)
    add_control_parsers(sub)
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


def cmd_version(argv: Sequence[str]) -> int:
    from companion.version import version_text

    parser = argparse.ArgumentParser(prog="companion --version")
    parser.add_argument("--config", help="the companion TOML file whose model to hash")
    print(version_text(parser.parse_args(argv).config))
    return 0


def run(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--version"]:
        return cmd_version(argv[1:])
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
    if args.command in ("engage", "disengage", "status"):
        return cmd_control(args)
    if args.command == "params":
        from companion.px4_params_file import cmd_params

        return cmd_params(args)
    return cmd_ground(args)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        code = run(argv)
    except CompanionError as exc:
        print(f"companion: error: {exc}", file=sys.stderr)
        code = 2
    _exit_now_if_a_model_hangs(code)
    return code


def _exit_now_if_a_model_hangs(code: int) -> None:
    """End the process with `code` at once if an abandoned model call still runs.

    The interpreter's normal exit would abort under it (SIGABRT, "terminate called without an
    active exception"; see `companion.model_thread`): everything is closed by now, so flush the
    logs and stdio and skip the interpreter's clean-up.
    """
    thread_module = sys.modules.get("companion.model_thread")  # loaded only with a policy
    if thread_module is None or not thread_module.abandoned_inferences():
        return
    logging.getLogger("companion").warning(
        "a hung model call is still running: ending the process without the interpreter's clean-up"
    )
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
