"""PX4 parameters from a QGroundControl `.params` file, applied to the PX4 emulator.

The HIL harness's emulated autopilots take the offboard-loss rule from the parameter file the
drones are flashed with (`firmware_cfg/px4/companion.params`), so a killed daemon ends the way a
Pixracer with that file would: COM_OF_LOSS_T seconds without a setpoint, then COM_OBL_RC_ACT.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from companion.errors import ConfigError
from sim_harness.hil.px4_logic import Px4LogicConfig, Px4Mode
from sim_harness.learning.shipped import PROJECT_ROOT

SHIPPED_PARAMS = PROJECT_ROOT / "firmware_cfg" / "px4" / "companion.params"
# COM_OBL_RC_ACT: 0 Position, 1 Altitude, 2 Manual, 3 Return, 4 Land, 5 Hold (6 Terminate and
# 7 Disarm are not emulated: the vehicle would fall).
OFFBOARD_LOSS_ACTIONS = {
    0: Px4Mode.POSCTL,
    1: Px4Mode.ALTCTL,
    2: Px4Mode.MANUAL,
    3: Px4Mode.RTL,
    4: Px4Mode.LAND,
    5: Px4Mode.HOLD,
}


def read_params(path: Path) -> dict[str, float]:
    """Name -> value of every row (vehicle id, component id, name, value, type)."""
    values: dict[str, float] = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split("\t")
        if len(fields) != 5:
            raise ConfigError(f"{path}:{number}: expected 5 tab-separated columns")
        try:
            values[fields[2]] = float(fields[3])
        except ValueError as exc:
            raise ConfigError(f"{path}:{number}: {fields[2]} value {fields[3]!r}") from exc
    return values


def logic_config(path: Path = SHIPPED_PARAMS, base: Px4LogicConfig | None = None) -> Px4LogicConfig:
    """`base` (default: the emulator's defaults) with the file's offboard-loss rule."""
    params = read_params(path)
    config = base or Px4LogicConfig()
    if "COM_OF_LOSS_T" in params:
        config = dataclasses.replace(config, offboard_loss_timeout_s=params["COM_OF_LOSS_T"])
    if "COM_OBL_RC_ACT" in params:
        action = int(params["COM_OBL_RC_ACT"])
        if action not in OFFBOARD_LOSS_ACTIONS:
            raise ConfigError(f"{path}: COM_OBL_RC_ACT {action} is not emulated")
        config = dataclasses.replace(config, offboard_loss_mode=OFFBOARD_LOSS_ACTIONS[action])
    return config


def param_table(config: Px4LogicConfig) -> dict[str, tuple[float, int]]:
    """PX4's stock parameter table with the offboard-loss rule of `config` (for the emulator)."""
    from sim_harness.hil.px4_param_server import PX4_STOCK

    action = next(
        a for a, mode in OFFBOARD_LOSS_ACTIONS.items() if mode is config.offboard_loss_mode
    )
    table = dict(PX4_STOCK)
    table["COM_OF_LOSS_T"] = (config.offboard_loss_timeout_s, PX4_STOCK["COM_OF_LOSS_T"][1])
    table["COM_OBL_RC_ACT"] = (action, PX4_STOCK["COM_OBL_RC_ACT"][1])
    return table


def with_param(config: Px4LogicConfig, name: str, value: float) -> Px4LogicConfig:
    """`config` after PARAM_SET `name` = `value` (only the offboard-loss rule is emulated)."""
    if name == "COM_OF_LOSS_T" and value > 0.0:
        return dataclasses.replace(config, offboard_loss_timeout_s=value)
    if name == "COM_OBL_RC_ACT" and int(value) in OFFBOARD_LOSS_ACTIONS:
        return dataclasses.replace(config, offboard_loss_mode=OFFBOARD_LOSS_ACTIONS[int(value)])
    return config
