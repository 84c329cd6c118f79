"""`companion check --autopilot`: the live autopilot's parameters against a QGroundControl `.params`
file, over MAVSDK's param plugin. Lists every difference: a name the autopilot does not have, a
value that differs, a type that differs.

PX4 answers a parameter request for every name it has and says nothing for one it does not know,
so "missing" cannot tell a misspelled name from one that only exists on some boards. `BOARD_ONLY`
names the parameters of the file that a flight controller without serial ports (PX4 SITL) does not
have: those are reported as warnings ("not on this board"), every other missing name as a failure.
"""

from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.errors import AutopilotError, ConfigError

INT32, REAL32 = 6, 9
DEFAULT_PARAMS = Path("/etc/vision-swarm/companion.params")

# Parameters of the shipped file that exist only where the board has the hardware they configure.
BOARD_ONLY: dict[str, str] = {
    # MAVLink instance 1 on TELEM2: PX4 creates MAV_1_CONFIG only on boards with serial ports.
    "MAV_1_CONFIG": "serial-port setting: only on boards with TELEM ports (not SITL)",
    # The TELEM2 baud rate: exists only where the board has a TELEM2 UART.
    "SER_TEL2_BAUD": "serial-port setting: only on boards with a TELEM2 port (not SITL)",
}


@dataclass(frozen=True)
class ParamRow:
    """One row of a `.params` file: name, value and MAV_PARAM_TYPE (6 INT32, 9 REAL32)."""

    name: str
    value: float
    param_type: int


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
            return f"{self.name}: not on this autopilot ({self.detail})"
        if self.kind == "missing":
            return f"{self.name}: the autopilot has no such parameter (misspelled or removed?)"
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
            value, param_type = float(fields[3]), int(fields[4])
        except ValueError as exc:
            raise ConfigError(f"{path}:{number}: {fields[2]}: {exc}") from exc
        if param_type not in (INT32, REAL32):
            raise ConfigError(f"{path}:{number}: {fields[2]}: type {param_type} is not 6 or 9")
        rows.append(ParamRow(fields[2], value, param_type))
    return rows


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


async def read_live(
    url: str, rows: list[ParamRow], discovery_timeout_s: float = 10.0, call_timeout_s: float = 10.0
) -> dict[str, tuple[str, float | None, str]]:
    """Read every row's parameter from the autopilot on `url` (MAVSDK, as a ground station).

    Returns name -> (status, value, detail): status "ok", "missing" (the autopilot does not have
    it), "wrong type" (it has it with the other type: value read that way) or "no answer".
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
    finally:
        mavsdk.destroy()
    return results


def check_autopilot(
    url: str, params_path: str | Path, discovery_timeout_s: float = 10.0
) -> tuple[list[ParamRow], list[ParamDifference]]:
    """Read the file, read the autopilot, compare (blocking: runs its own event loop)."""
    rows = read_params_file(params_path)
    live = asyncio.run(read_live(url, rows, discovery_timeout_s))
    return rows, compare(rows, live)


def autopilot_items(url: str, params_path: str | Path, discovery_timeout_s: float) -> list[Any]:
    """`companion check` report lines: one per difference, or one "ok" line."""
    from companion.check import FAIL, OK, WARN, CheckItem

    try:
        rows, differences = check_autopilot(url, params_path, discovery_timeout_s)
    except (AutopilotError, ConfigError) as exc:
        return [CheckItem("parameters", FAIL, str(exc))]
    items = [CheckItem("parameters", FAIL if d.is_failure else WARN, d.line()) for d in differences]
    failures = sum(d.is_failure for d in differences)
    summary = f"{len(rows)} in {params_path} read from {url}: {failures} difference(s)"
    return [CheckItem("parameters", FAIL if failures else OK, summary), *items]
