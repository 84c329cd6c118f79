"""`[control] migration_point_global`: validation, and the conversion to the local ENU frame with
PX4's home position (companion.geo), checked against the emulator's own NED -> global conversion."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from companion.autopilot_types import Stamped
from companion.control import ControlConfig
from companion.errors import ConfigError
from companion.geo import (
    EARTH_RADIUS_M,
    GlobalPosition,
    HomePosition,
    MigrationFromHome,
    enu_offset_m,
    global_to_local_enu,
    require_global,
)
from sim_harness.hil.px4_messages import Home

HOME = GlobalPosition(47.397742, 8.545594, 488.0)


def test_a_point_north_east_and_up_of_home() -> None:
    north_deg = math.degrees(100.0 / EARTH_RADIUS_M)
    east_deg = math.degrees(50.0 / (EARTH_RADIUS_M * math.cos(math.radians(HOME.lat_deg))))
    point = GlobalPosition(HOME.lat_deg + north_deg, HOME.lon_deg + east_deg, 493.0)
    local = global_to_local_enu(point, HomePosition(HOME))
    np.testing.assert_allclose(local, [50.0, 100.0, 5.0], atol=1e-6)


@pytest.mark.parametrize("ned", [(0.0, 0.0, 0.0), (30.0, -12.5, -4.0), (-800.0, 1500.0, 20.0)])
def test_the_inverse_of_the_emulators_ned_to_global(ned: tuple[float, float, float]) -> None:
    lat, lon, alt = Home(HOME.lat_deg, HOME.lon_deg, HOME.alt_amsl_m).to_global(np.array(ned))
    local = global_to_local_enu(GlobalPosition(lat, lon, alt), HomePosition(HOME))
    np.testing.assert_allclose(local, [ned[1], ned[0], -ned[2]], atol=1e-6)


def test_home_away_from_the_ekf_origin_shifts_the_point() -> None:
    """PX4 reports where home lies in its local frame (HOME_POSITION x, y, z): added in ENU."""
    home = HomePosition(HOME, local_ned_m=(2.0, -3.0, -0.5))  # 2 m north, 3 m west, 0.5 m up
    local = global_to_local_enu(HOME, home)
    np.testing.assert_allclose(local, [-3.0, 2.0, 0.5], atol=1e-9)


def test_across_the_antimeridian() -> None:
    home = GlobalPosition(0.0, 179.9999, 0.0)
    point = GlobalPosition(0.0, -179.9999, 0.0)
    east = enu_offset_m(point, home)[0]
    assert east == pytest.approx(math.radians(0.0002) * EARTH_RADIUS_M, rel=1e-6)


def test_a_point_far_from_home_or_a_bad_home_is_refused() -> None:
    with pytest.raises(ValueError, match="km from home"):
        global_to_local_enu(
            GlobalPosition(HOME.lat_deg + 0.1, HOME.lon_deg, 488.0), HomePosition(HOME)
        )
    with pytest.raises(ValueError, match="not finite"):
        global_to_local_enu(HOME, HomePosition(GlobalPosition(math.nan, 8.5, 488.0)))


def test_the_config_takes_a_global_point() -> None:
    config = ControlConfig.from_dict({"migration_point_global": [47.4, 8.55, 500]})
    assert config.migration_point_global == (47.4, 8.55, 500.0)
    assert config.migration_point_enu is None


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([91.0, 8.5, 500.0], r"migration_point_global\[0\] \(latitude, deg\): 91 is outside"),
        ([47.0, -181.0, 500.0], r"migration_point_global\[1\] \(longitude, deg\): -181 is"),
        ([47.0, 8.5, 20000.0], r"migration_point_global\[2\] \(altitude AMSL, m\)"),
        ([47.0, 8.5], "migration_point_global: expected 3 numbers, got 2"),
        ("47.0, 8.5, 500", "migration_point_global: expected \\[lat_deg, lon_deg, alt_amsl_m\\]"),
        ([47.0, "x", 500.0], r"migration_point_global\[1\]: expected a number"),
    ],
)
def test_a_bad_global_point_is_refused_naming_the_field(value: Any, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        ControlConfig.from_dict({"migration_point_global": value})


def test_global_and_enu_points_are_mutually_exclusive() -> None:
    with pytest.raises(ConfigError, match=r"control.migration_point_global: .* not both"):
        ControlConfig.from_dict(
            {"migration_point_global": [47.4, 8.55, 500], "migration_point_enu": [30, 0, 5]}
        )


def test_require_global_returns_floats() -> None:
    assert require_global("f", (47, 8, 500)) == (47.0, 8.0, 500.0)


def test_the_migration_point_waits_for_home_then_converts_once() -> None:
    north_deg = math.degrees(40.0 / EARTH_RADIUS_M)
    events: list[tuple[str, Any]] = []
    point = (HOME.lat_deg + north_deg, HOME.lon_deg, 490.0)
    migration = MigrationFromHome(point, lambda e, _lvl, d: events.append((e, d)))
    local, why = migration.resolve(None)
    assert local is None and "waiting for PX4's home position" in why

    home = Stamped(HomePosition(HOME), 1.0)
    local, why = migration.resolve(home)
    assert why == ""
    np.testing.assert_allclose(local, [0.0, 40.0, 2.0], atol=1e-6)
    migration.resolve(home)
    assert [e for e, _ in events] == ["migration point"]  # logged once per home
    assert events[0][1]["migration_point_enu"] == [0.0, 40.0, 2.0]


def test_an_enu_point_needs_no_home() -> None:
    migration = MigrationFromHome(None, lambda *_: None)
    assert migration.resolve(None) == (None, "")
