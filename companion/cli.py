"""`companion`: the onboard program's command line.

companion conventions      # frame conventions and flocking defaults this build uses
companion --version
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import asdict

from companion import __version__, frames
from companion.errors import CompanionError
from companion.flocking import FlockingParams


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("conventions", help="print frame conventions and flocking defaults")
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


def run(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "conventions":
        print(conventions_text())
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return run(argv)
    except CompanionError as exc:
        print(f"companion: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
