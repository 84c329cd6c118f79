"""`companion check --autopilot`: the live autopilot's parameters against a QGroundControl `.params`
file, over MAVSDK's param plugin. Lists every difference: a name the autopilot does not have, a
value that differs, a type that differs; and the autopilot's identity against the file's: the
vehicle id column against the autopilot's system id (QGroundControl refuses a file for another
vehicle id), the PX4 version the file states (`# PX4 version: MAJOR.MINOR`) against the one the
autopilot reports (AUTOPILOT_VERSION; a warning when major.minor differ).

PX4 answers a parameter request for every name it has and says nothing for one it does not know,
so "missing" cannot tell a misspelled name from one that only exists on some boards. `BOARD_ONLY`
names the parameters of the file that a flight controller without serial ports (PX4 SITL) does not
have: those are reported as warnings ("not on this board"), every other missing name as a failure
("no such parameter: misspelled, or needs a newer PX4").
"""

from __future__ import annotations

import asyncio
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.errors import AutopilotError, ConfigError

INT32, REAL32 = 6, 9
DEFAULT_PARAMS = Path("/etc/vision-swarm/companion.params")
_STATED_VERSION = re.compile(r"^#\s*PX4 version:\s*(\d+)\.(\d+)\s*$", re.MULTILINE)

# Parameters of the shipped file that exist only where the board has the hardware they configure.
BOARD_ONLY: dict[str, str] = {
    # MAVLink instance 1 on TELEM2: PX4 creates MAV_1_CONFIG only on boards with serial ports.
    "MAV_1_CONFIG": "serial-port setting: only on boards with TELEM ports (not SITL)",
    # The TELEM2 baud rate: exists only where the board has a TELEM2 UART.
    "SER_TEL2_BAUD": "serial-port setting: only on boards with a TELEM2 port (not SITL)",
}


@dataclass(frozen=True)
class ParamRow:
    """One row of a `.params` file: name, value, MAV_PARAM_TYPE (6 INT32, 9 REAL32) and the
    vehicle id column (the MAV_SYS_ID of the drone the file is for)."""

    name: str
    value: float
    param_type: int
    vehicle_id: int = 1


@dataclass(frozen=True)
class ParamDifference:
    """One difference. `kind`: "missing", "board-only", "different", "wrong type", "no answer"."""

    name: str
    kind: str
    expected: float
    actual: float | None = None
    detail: str = ""

    @property
    def is_failure(self) -> bool:
        return self.kind != "board-only"

    def line(self) -> str:
        if self.kind == "different":
            actual, expected = _show(self.actual), _show(self.expected)
            return f"{self.name}: {actual} on the autopilot, {expected} in the file"
        if self.kind == "board-only":
            return f"{self.name}: not on this board ({self.detail})"
        if self.kind == "missing":
            return f"{self.name}: no such parameter: misspelled, or needs a newer PX4"
        return f"{self.name}: {self.kind} ({self.detail})"


def _show(value: float | None) -> str:
    if value is None:
        return "-"
    return str(int(value)) if float(value).is_integer() else f"{value:g}"


def read_params_file(path: str | Path) -> list[ParamRow]:
    """Rows of a QGroundControl parameter file (`#` comments; vehicle, component, name, value,
    type, tab-separated). Raises `ConfigError` naming the line of a malformed row."""
    rows: list[ParamRow] = []
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise ConfigError(f"{path}: {exc.strerror or exc}") from exc
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split("\t")
        if len(fields) != 5:
            raise ConfigError(f"{path}:{number}: expected 5 tab-separated columns")
        try:
            vehicle_id, value, param_type = int(fields[0]), float(fields[3]), int(fields[4])
        except ValueError as exc:
            raise ConfigError(f"{path}:{number}: {fields[2]}: {exc}") from exc
        if param_type not in (INT32, REAL32):
            raise ConfigError(f"{path}:{number}: {fields[2]}: type {param_type} is not 6 or 9")
        if not 1 <= vehicle_id <= 255:
            raise ConfigError(f"{path}:{number}: vehicle id {vehicle_id}: must be 1..255")
        rows.append(ParamRow(fields[2], value, param_type, vehicle_id))
    return rows


def stated_version(text: str) -> tuple[int, int] | None:
    """The PX4 (major, minor) a parameter file states in a `# PX4 version: 1.17` line."""
    match = _STATED_VERSION.search(text)
    return None if match is None else (int(match.group(1)), int(match.group(2)))


def same_value(expected: float, actual: float, param_type: int) -> bool:
    """Equal as the autopilot stores them (INT32 exactly, REAL32 at float32 precision)."""
    if param_type == INT32:
        return round(expected) == round(actual)
    return bool(_f32(expected) == _f32(actual))


def _f32(value: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def compare(
    rows: list[ParamRow], live: dict[str, tuple[str, float | None, str]]
) -> list[ParamDifference]:
    """Differences between the file's rows and what was read (name -> (status, value, detail))."""
    out: list[ParamDifference] = []
    for row in rows:
        status, value, detail = live.get(row.name, ("no answer", None, "not read"))
        if status == "ok" and value is not None:
            if not same_value(row.value, value, row.param_type):
                out.append(ParamDifference(row.name, "different", row.value, value))
        elif status == "missing":
            if row.name in BOARD_ONLY:
                out.append(
                    ParamDifference(row.name, "board-only", row.value, None, BOARD_ONLY[row.name])
                )
            else:
                out.append(ParamDifference(row.name, "missing", row.value))
        else:
            out.append(ParamDifference(row.name, status, row.value, value, detail))
    return out


@dataclass(frozen=True)
class AutopilotIdentity:
    """Who answered: MAVLink system id, PX4 version (major, minor, patch; None: not reported)
    and the firmware's git hash (may be empty)."""

    system_id: int
    version: tuple[int, int, int] | None = None
    git_hash: str = ""


def identity_findings(
    rows: list[ParamRow], stated: tuple[int, int] | None, identity: AutopilotIdentity
) -> list[tuple[str, str]]:
    """(verdict, line) for the file's vehicle id and PX4 version against the autopilot's.

    Verdicts as `companion check`: "ok", "warn", "FAIL". A vehicle id other than the autopilot's
    system id fails (QGroundControl refuses such a file); a PX4 version that differs in major.minor
    from the file's, or that cannot be compared, warns.
    """
    from companion.check import FAIL, OK, WARN

    out: list[tuple[str, str]] = []
    ids = sorted({row.vehicle_id for row in rows})
    if len(ids) > 1:
        out.append((FAIL, f"the file mixes vehicle ids {', '.join(map(str, ids))}"))
    elif ids and ids[0] != identity.system_id:
        out.append(
            (
                FAIL,
                f"the file is for vehicle id {ids[0]}, the autopilot is system "
                f"{identity.system_id} (MAV_SYS_ID): QGroundControl refuses to load it; use "
                f"`companion params file --sysid {identity.system_id}`, or set MAV_SYS_ID "
                f"{ids[0]} and reboot",
            )
        )
    elif ids:
        out.append((OK, f"vehicle id {ids[0]}: the autopilot's system id"))
    out.append(_version_finding(stated, identity, OK, WARN))
    return out


def _version_finding(
    stated: tuple[int, int] | None, identity: AutopilotIdentity, ok: str, warn: str
) -> tuple[str, str]:
    if stated is None:
        return warn, "the file states no PX4 version (a '# PX4 version: MAJOR.MINOR' line)"
    want = f"{stated[0]}.{stated[1]}"
    if identity.version is None:
        return warn, f"the autopilot did not report its version; the file is for PX4 {want}"
    running = ".".join(map(str, identity.version))
    git = f", git {identity.git_hash[:10]}" if identity.git_hash else ""
    if identity.version == (0, 0, 0):
        return warn, (
            f"the autopilot reports PX4 {running} (an untagged build{git}): cannot tell whether "
            f"it is {want}, the version the file was checked against"
        )
    if identity.version[:2] != stated:
        return warn, (
            f"the autopilot runs PX4 {running}{git}, the file was checked against {want}: "
            "parameter names, ranges and meanings may differ"
        )
    return ok, f"PX4 {running}: the version the file was checked against ({want})"


async def read_live(
    url: str, rows: list[ParamRow], discovery_timeout_s: float = 10.0, call_timeout_s: float = 10.0
) -> tuple[dict[str, tuple[str, float | None, str]], AutopilotIdentity]:
    """Read every row's parameter and the identity of the autopilot on `url` (MAVSDK, as a
    ground station).

    Returns name -> (status, value, detail): status "ok", "missing" (the autopilot does not have
    it), "wrong type" (it has it with the other type: value read that way) or "no answer"; and
    the autopilot's system id and version.
    """
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.param import ParamAsync
    from mavsdk.plugins.param import ParamError, ParamResult

    async def get(param: Any, name: str, param_type: int) -> float:
        call = param.get_param_int(name) if param_type == INT32 else param.get_param_float(name)
        return float(await asyncio.wait_for(call, call_timeout_s))

    results: dict[str, tuple[str, float | None, str]] = {}
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        await mavsdk.add_any_connection(url)
        system = await mavsdk.first_autopilot(discovery_timeout_s)
        if system is None:
            raise AutopilotError(f"no autopilot on {url} within {discovery_timeout_s:g} s")
        param = ParamAsync(system)
        for row in rows:
            try:
                results[row.name] = ("ok", await get(param, row.name, row.param_type), "")
            except ParamError as exc:
                if exc.result is ParamResult.DOES_NOT_EXIST:
                    results[row.name] = ("missing", None, "")
                elif exc.result is ParamResult.WRONG_TYPE:
                    other = REAL32 if row.param_type == INT32 else INT32
                    kind = "INT32" if other == INT32 else "REAL32"
                    results[row.name] = (
                        "wrong type",
                        await get(param, row.name, other),
                        f"{kind} on the autopilot",
                    )
                else:
                    results[row.name] = ("no answer", None, exc.result.name)
            except TimeoutError:
                results[row.name] = ("no answer", None, f"nothing within {call_timeout_s:g} s")
        identity = await _identity(system, call_timeout_s)
    finally:
        mavsdk.destroy()
    return results, identity


async def _identity(system: Any, timeout_s: float) -> AutopilotIdentity:
    """System id, and the version from AUTOPILOT_VERSION (None where it does not come)."""
    from mavsdk.asyncio.plugins.info import InfoAsync
    from mavsdk.plugins.info import InfoError

    system_id = int(await system.get_system_id())
    try:
        version = await asyncio.wait_for(InfoAsync(system).get_version(), timeout_s)
    except (InfoError, TimeoutError):
        return AutopilotIdentity(system_id)
    numbers = (
        int(version.flight_sw_major),
        int(version.flight_sw_minor),
        int(version.flight_sw_patch),
    )
    git_hash = str(version.flight_sw_git_hash or "")
    if not git_hash.strip("0"):  # MAVSDK shows a missing hash as zeros
        git_hash = ""
    return AutopilotIdentity(system_id, numbers, git_hash)


@dataclass(frozen=True)
class AutopilotCheck:
    """What `companion check --autopilot` found: the file's rows, the parameter differences, the
    autopilot's identity and the PX4 version the file states."""

    rows: list[ParamRow]
    differences: list[ParamDifference]
    identity: AutopilotIdentity
    stated_version: tuple[int, int] | None


def check_autopilot(
    url: str, params_path: str | Path, discovery_timeout_s: float = 10.0
) -> AutopilotCheck:
    """Read the file, read the autopilot, compare (blocking: runs its own event loop)."""
    rows = read_params_file(params_path)
    stated = stated_version(Path(params_path).read_text())
    live, identity = asyncio.run(read_live(url, rows, discovery_timeout_s))
    return AutopilotCheck(rows, compare(rows, live), identity, stated)


def autopilot_items(url: str, params_path: str | Path, discovery_timeout_s: float) -> list[Any]:
    """`companion check` report lines: the summary, one per difference, then the vehicle id and
    the PX4 version against the autopilot's."""
    from companion.check import FAIL, OK, WARN, CheckItem

    try:
        found = check_autopilot(url, params_path, discovery_timeout_s)
    except (AutopilotError, ConfigError) as exc:
        return [CheckItem("parameters", FAIL, str(exc))]
    differences = found.differences
    items = [CheckItem("parameters", FAIL if d.is_failure else WARN, d.line()) for d in differences]
    failures = sum(d.is_failure for d in differences)
    summary = f"{len(found.rows)} in {params_path} read from {url}: {failures} difference(s)"
    identity = [
        CheckItem("autopilot", verdict, line)
        for verdict, line in identity_findings(found.rows, found.stated_version, found.identity)
    ]
    return [CheckItem("parameters", FAIL if failures else OK, summary), *items, *identity]
