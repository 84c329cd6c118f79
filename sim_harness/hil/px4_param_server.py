"""PX4's parameter protocol for the emulator: PARAM_REQUEST_READ, PARAM_SET, PARAM_REQUEST_LIST.

The table holds PX4's stock defaults (PX4 main, 02e73e3b6f, read from real PX4 SITL) for the
parameters the companion's parameter file and the emulated rules touch, plus the Pixracer's
serial-port parameters (MAV_1_CONFIG, SER_TEL2_BAUD) that SITL lacks: the emulator plays a board.
Answers as PX4 does: PARAM_VALUE with the name, value (INT32 bytewise in the float), type, count
and index. A name it does not have (read or set) gets PARAM_ERROR DOES_NOT_EXIST: PX4 SITL sent
that to MAVSDK, which then fails at once instead of retrying for seconds (a raw pymavlink client
saw no answer at all from the same PX4). A PARAM_SET with another type than the table's is
refused (no answer). `on_change` tells the emulator when a value changed (COM_OF_LOSS_T and
COM_OBL_RC_ACT change its offboard-loss rule at once, as on PX4).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT_TYPES = range(1, 9)

# name: (stock value, type). Values as real PX4 SITL reports them with no parameter file loaded.
PX4_STOCK: dict[str, tuple[float, int]] = {
    "MAV_1_CONFIG": (0, INT32),  # board-only (TELEM2 on a Pixracer): not in SITL
    "MAV_1_MODE": (2, INT32),
    "MAV_1_RATE": (0, INT32),
    "MAV_1_FORWARD": (0, INT32),
    "SER_TEL2_BAUD": (57600, INT32),  # board-only
    "COM_OF_LOSS_T": (1.0, REAL32),
    "COM_OBL_RC_ACT": (0, INT32),  # 0: Position mode
    "COM_RCL_EXCEPT": (0, INT32),
    "COM_FAIL_ACT_T": (5.0, REAL32),
    "COM_OBC_LOSS_T": (5.0, REAL32),
    "COM_RC_OVERRIDE": (1, INT32),  # bit 0 auto modes only: sticks do not take over OFFBOARD
    "NAV_RCL_ACT": (2, INT32),  # RC loss: Return
    "RTL_RETURN_ALT": (30.0, REAL32),  # SITL's airframe (the metadata's default is 60)
    "RTL_CONE_ANG": (45, INT32),
    "RTL_DESCEND_ALT": (10.0, REAL32),
    "RTL_LAND_DELAY": (0.0, REAL32),
    "COM_LOW_BAT_ACT": (3, INT32),
    "COM_ARM_WO_GPS": (1, INT32),
    "EKF2_REQ_NSATS": (6, INT32),
    "EKF2_REQ_EPH": (3.0, REAL32),
    "MPC_XY_VEL_MAX": (12.0, REAL32),
    "MPC_XY_CRUISE": (5.0, REAL32),
    "MPC_VEL_MANUAL": (10.0, REAL32),
    "MPC_Z_VEL_MAX_UP": (3.0, REAL32),
    "MPC_Z_VEL_MAX_DN": (1.5, REAL32),
    "MPC_TKO_SPEED": (1.5, REAL32),
    "MPC_LAND_SPEED": (0.7, REAL32),
    "MIS_TAKEOFF_ALT": (2.5, REAL32),
    "NAV_DLL_ACT": (0, INT32),
    "GF_ACTION": (2, INT32),
    "GF_MAX_HOR_DIST": (0.0, REAL32),
    "GF_MAX_VER_DIST": (0.0, REAL32),
}


def as_wire(value: float, param_type: int) -> float:
    """The float PARAM_VALUE carries (integers bytewise)."""
    if param_type in _INT_TYPES:
        return float(struct.unpack("<f", struct.pack("<i", round(value)))[0])
    return float(value)


def from_wire(value: float, param_type: int) -> float:
    """The number a PARAM_SET's float field means for `param_type`."""
    if param_type in _INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    return float(struct.unpack("<f", struct.pack("<f", value))[0])  # REAL32 precision


@dataclass
class Param:
    name: str
    value: float
    param_type: int


class ParamServer:
    """A parameter table and PX4's answers. Not thread-safe: the emulator holds its lock."""

    def __init__(
        self,
        table: Mapping[str, tuple[float, int]] | None = None,
        on_change: Callable[[str, float], None] | None = None,
    ) -> None:
        source = PX4_STOCK if table is None else table
        self._params = {
            name: Param(name, from_wire(as_wire(v, t), t), t) for name, (v, t) in source.items()
        }
        self._order = list(self._params)
        self._on_change = on_change

    def value(self, name: str) -> float | None:
        param = self._params.get(name)
        return None if param is None else param.value

    def values(self) -> dict[str, float]:
        return {name: p.value for name, p in self._params.items()}

    def set_value(self, name: str, value: float) -> None:
        """Set a known parameter directly (a test's start-up state)."""
        param = self._params[name]
        param.value = from_wire(as_wire(value, param.param_type), param.param_type)
        if self._on_change is not None:
            self._on_change(name, param.value)

    def handle(
        self, mav: mavlink.MAVLink, msg: mavlink.MAVLink_message
    ) -> list[mavlink.MAVLink_message]:
        """The PARAM_VALUE messages PX4 would send for a parameter request (maybe none)."""
        kind = msg.get_type()
        if kind == "PARAM_REQUEST_LIST":
            return [self._value_msg(mav, name) for name in self._order]
        if kind == "PARAM_REQUEST_READ":
            name = self._name_of(msg.param_id, int(msg.param_index))
            if name is None:
                return [self._unknown(mav, msg, int(msg.param_index))]
            return [self._value_msg(mav, name)]
        if kind == "PARAM_SET":
            name = str(msg.param_id)
            param = self._params.get(name)
            if param is None:
                return [self._unknown(mav, msg, -1)]
            if int(msg.param_type) != param.param_type:
                return []
            new = from_wire(float(msg.param_value), param.param_type)
            if new != param.value:
                param.value = new
                if self._on_change is not None:
                    self._on_change(name, new)
            return [self._value_msg(mav, name)]
        return []

    @staticmethod
    def _unknown(
        mav: mavlink.MAVLink, msg: mavlink.MAVLink_message, index: int
    ) -> mavlink.MAVLink_message:
        return mav.param_error_encode(
            msg.get_srcSystem(),
            msg.get_srcComponent(),
            str(msg.param_id).encode(),
            index,
            mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST,
        )

    def _name_of(self, param_id: str, index: int) -> str | None:
        if index >= 0:
            return self._order[index] if index < len(self._order) else None
        name = str(param_id)
        return name if name in self._params else None

    def _value_msg(self, mav: mavlink.MAVLink, name: str) -> mavlink.MAVLink_message:
        param = self._params[name]
        return mav.param_value_encode(
            name.encode(),
            as_wire(param.value, param.param_type),
            param.param_type,
            len(self._order),
            self._order.index(name),
        )


def load_rows(server: ParamServer, rows: Iterable[tuple[str, float]]) -> None:
    """Set every known (name, value); unknown names are skipped, as PX4 ignores them."""
    for name, value in rows:
        if server.value(name) is not None:
            server.set_value(name, value)
