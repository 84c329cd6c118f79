"""`companion params file`: the shipped PX4 parameter file rendered for one drone, or for many.

QGroundControl refuses a `.params` file whose vehicle id column is not the drone's MAVLink system
id (MAV_SYS_ID), so every drone of the swarm needs its own file. The shipped
`firmware_cfg/px4/companion.params` is the template (and drone 1's file): rendering keeps every
row, comment and value and puts the drone's id in the vehicle id column, with a header line that
says which drone the file is for.

    companion params file --sysid 3 > drone3.params
    companion params file --drones 1-9 --out params/        # params/drone1.params ... drone9
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from companion.errors import ConfigError
from companion.param_check import DEFAULT_PARAMS, read_params_file

# MAV_SYS_ID's range in PX4's parameter metadata.
SYSID_MIN, SYSID_MAX = 1, 250
# The template in a checkout of the repository (the ground station's copy), else the installed one.
CHECKOUT_TEMPLATE = (
    Path(__file__).resolve().parents[1] / "firmware_cfg" / "px4" / "companion.params"
)
_ID_LIST = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*$")


def default_template() -> Path:
    """The checkout's `firmware_cfg/px4/companion.params`, else /etc/vision-swarm's copy."""
    for candidate in (CHECKOUT_TEMPLATE, DEFAULT_PARAMS):
        if candidate.is_file():
            return candidate
    raise ConfigError(
        f"no parameter template at {CHECKOUT_TEMPLATE} or {DEFAULT_PARAMS}: give --template FILE"
    )


def check_sysid(sysid: int, field: str = "--sysid") -> int:
    """`sysid` if it is a valid MAV_SYS_ID, else a ConfigError naming the field and the range."""
    if not SYSID_MIN <= sysid <= SYSID_MAX:
        raise ConfigError(f"{field} {sysid}: must be {SYSID_MIN}..{SYSID_MAX} (MAV_SYS_ID)")
    return sysid


def parse_id_list(spec: str, field: str = "--drones") -> list[int]:
    """System ids from "1-9", "1,3,5" or "2-4,7": sorted, each once, each a valid MAV_SYS_ID."""
    text = spec.replace(" ", "")
    if not _ID_LIST.match(text):
        raise ConfigError(f"{field} {spec!r}: expected ids and ranges such as 1-9 or 1,3,5-7")
    ids: set[int] = set()
    for part in text.split(","):
        first, _, last = part.partition("-")
        low, high = int(first), int(last or first)
        if high < low:
            raise ConfigError(f"{field} {spec!r}: range {part} must go up (FIRST-LAST)")
        for sysid in (low, high):
            check_sysid(sysid, field)
        ids.update(range(low, high + 1))
    return sorted(ids)


def render(template_text: str, sysid: int, template_name: str = "companion.params") -> str:
    """The template with every row's vehicle id column set to `sysid`, and a header line."""
    check_sysid(sysid)
    lines = [
        f"# Drone with MAV_SYS_ID {sysid}: rendered from {template_name} by "
        f"`companion params file --sysid {sysid}` (vehicle id column {sysid}).",
    ]
    for line in template_text.splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            fields = line.split("\t")
            line = "\t".join([str(sysid), *fields[1:]])
        lines.append(line)
    return "\n".join(lines) + "\n"


def render_file(template: Path, sysid: int) -> str:
    """`render` of a template file, which must read as a parameter file first."""
    read_params_file(template)  # a malformed template fails here, naming its line
    return render(template.read_text(), sysid, template.name)


def write_files(template: Path, ids: list[int], out_dir: Path) -> list[Path]:
    """`out_dir`/drone<ID>.params for every id (replaced where they exist); the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for sysid in ids:
        path = out_dir / f"drone{sysid}.params"
        path.write_text(render_file(template, sysid))
        written.append(path)
    return written


def add_params_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """`companion params file ...` on the CLI's subcommands."""
    params = sub.add_parser("params", help="PX4 parameter files").add_subparsers(
        dest="params_command", required=True
    )
    file = params.add_parser(
        "file", help="the PX4 parameter file for one drone (stdout) or several (--out DIR)"
    )
    which = file.add_mutually_exclusive_group(required=True)
    which.add_argument("--sysid", type=int, help="the drone's MAV_SYS_ID (1..250): to stdout")
    which.add_argument("--drones", help="system ids such as 1-9 or 1,3,5-7: one file each")
    file.add_argument("--out", help="with --drones: the folder for drone<ID>.params")
    file.add_argument(
        "--template", help="the template (default: firmware_cfg/px4/companion.params)"
    )


def cmd_params(args: argparse.Namespace) -> int:
    """Run `companion params file`; 0 on success (errors raise ConfigError)."""
    template = Path(args.template) if args.template else default_template()
    if not template.is_file():
        raise ConfigError(f"--template {template}: no such file")
    if args.sysid is not None:
        if args.out is not None:
            raise ConfigError("--out goes with --drones (--sysid writes to stdout)")
        print(render_file(template, args.sysid), end="")
        return 0
    if args.out is None:
        raise ConfigError("--drones needs --out DIR")
    for path in write_files(template, parse_id_list(args.drones), Path(args.out)):
        print(path)
    return 0
