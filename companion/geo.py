"""Global (WGS-84 latitude, longitude, altitude AMSL) to the daemon's local ENU frame.

The daemon flies in PX4's local frame (ENU here, NED in PX4), whose origin is the EKF origin PX4
set where the drone was switched on. An operator in the field knows the goal as a global
position, so `[control] migration_point_global` is converted here, with the home position PX4
reports (HOME_POSITION: its global position and where it lies in the local frame):

    local_enu(point) = flat_earth_enu(point - home_global) + home_local_enu

Flat earth (an equirectangular offset on a sphere of the WGS-84 equatorial radius, as PX4's own
emulator here uses): the horizontal error grows with the square of the distance, under 0.1 m at
1 km and under 1 m at 3 km, which is fine for a swarm's goal a few km away at most.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from companion.errors import ConfigError
from companion.validation import require_range, require_vector3

if TYPE_CHECKING:
    from companion.autopilot_types import Stamped

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)
EARTH_RADIUS_M = 6_378_137.0
MAX_OFFSET_M = 5_000.0  # a point farther from home than this is refused (flat earth, typos)


@dataclass(frozen=True)
class GlobalPosition:
    """Latitude and longitude in degrees, altitude in metres above mean sea level."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float


@dataclass(frozen=True)
class HomePosition:
    """PX4's home: its global position, and where it lies in the local frame (NED, m)."""

    position: GlobalPosition
    local_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def z_enu_m(self) -> float:
        """The home's height in the local ENU frame (up from the EKF origin)."""
        return -self.local_ned_m[2]


def require_global(field: str, value: object) -> tuple[float, float, float]:
    """`[lat_deg, lon_deg, alt_amsl_m]` with latitude in [-90, 90], longitude in [-180, 180] and
    altitude in [-500, 10000] m, or a `ConfigError` naming `field`."""
    if isinstance(value, str | bytes):
        raise ConfigError(f"{field}: expected [lat_deg, lon_deg, alt_amsl_m], got {value!r}")
    lat, lon, alt = require_vector3(field, value)  # type: ignore[arg-type]
    require_range(f"{field}[0] (latitude, deg)", lat, -90.0, 90.0)
    require_range(f"{field}[1] (longitude, deg)", lon, -180.0, 180.0)
    require_range(f"{field}[2] (altitude AMSL, m)", alt, -500.0, 10_000.0)
    return (lat, lon, alt)


def enu_offset_m(point: GlobalPosition, origin: GlobalPosition) -> FloatArray:
    """East, north, up (m) of `point` from `origin`, flat earth."""
    d_lat = math.radians(point.lat_deg - origin.lat_deg)
    d_lon = math.radians((point.lon_deg - origin.lon_deg + 180.0) % 360.0 - 180.0)
    north = d_lat * EARTH_RADIUS_M
    east = d_lon * EARTH_RADIUS_M * math.cos(math.radians(origin.lat_deg))
    return np.array([east, north, point.alt_amsl_m - origin.alt_amsl_m], dtype=np.float64)


def global_to_local_enu(point: GlobalPosition, home: HomePosition) -> FloatArray:
    """`point` in the local ENU frame whose home is `home` (m); raises `ValueError` when it is
    more than `MAX_OFFSET_M` from home or the home is not finite."""
    values = (*vars(home.position).values(), *home.local_ned_m)
    if not all(math.isfinite(float(v)) for v in values):
        raise ValueError(f"home position is not finite: {home}")
    offset = enu_offset_m(point, home.position)
    distance = float(np.linalg.norm(offset[:2]))
    if distance > MAX_OFFSET_M:
        raise ValueError(
            f"the point is {distance / 1000:.1f} km from home (more than "
            f"{MAX_OFFSET_M / 1000:g} km: flat earth is not good enough, or a typo)"
        )
    north, east, down = home.local_ned_m
    return offset + np.array([east, north, -down], dtype=np.float64)


class MigrationFromHome:
    """`[control] migration_point_global` in the daemon's local ENU frame, kept up to date with
    the home position PX4 reports (it re-sends it, and moves it when re-armed elsewhere)."""

    MOVED_M = 0.1  # a home update moving the converted point more than this is logged

    def __init__(
        self,
        point: tuple[float, float, float] | None,
        event: Callable[[str, str, Any], None],
    ) -> None:
        self._point = None if point is None else GlobalPosition(*point)
        self._event = event
        self._home: HomePosition | None = None  # the home the point was converted with
        self._enu: FloatArray | None = None

    def resolve(self, home: Stamped[HomePosition] | None) -> tuple[FloatArray | None, str]:
        """(the point in local ENU, "") or (None, why not: no home yet, so neither engage nor
        fly); (None, "") when the point is not global (the control law uses its config)."""
        if self._point is None:
            return None, ""
        if home is None:
            return None, "waiting for PX4's home position (migration_point_global needs it)"
        if home.value != self._home:
            try:
                local = global_to_local_enu(self._point, home.value)
            except ValueError as exc:
                return None, f"migration_point_global not usable: {exc}"
            previous, self._home, self._enu = self._enu, home.value, local
            if previous is None or float(np.linalg.norm(local - previous)) > self.MOVED_M:
                detail = {
                    "home": [*vars(home.value.position).values()],
                    "home_local_ned_m": list(home.value.local_ned_m),
                    "migration_point_global": list(vars(self._point).values()),
                    "migration_point_enu": [round(float(c), 3) for c in local],
                }
                log.info(
                    "migration point from PX4's home: local ENU %s", detail["migration_point_enu"]
                )
                self._event("migration point", "info", detail)
        return self._enu, ""
