"""The autopilot's telemetry as the adapter receives it: MAVSDK's subscriptions and the raw
HEARTBEAT / CURRENT_MODE (`companion.autopilot_direct`), folded into one `AutopilotTelemetry`.

Every value is stamped with its receive time on the adapter's clock. Mode reports (heartbeat or
CURRENT_MODE) also go to `on_mode`, which decides whether the vehicle was engaged or taken over.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import AsyncIterator, Callable
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion import autopilot_mavlink as mav
from companion.autopilot_direct import DirectLink
from companion.autopilot_types import (
    AutopilotTelemetry,
    BatteryState,
    FlightMode,
    GpsFixType,
    GpsState,
    Stamped,
)
from companion.geo import GlobalPosition, HomePosition

FloatArray = NDArray[np.float64]
logger = logging.getLogger(__name__)


def _vector(*components: Any) -> FloatArray:
    vec = np.array([float(c) for c in components], dtype=np.float64)
    vec.flags.writeable = False
    return vec


class TelemetryFeed:
    """The latest telemetry (`value`); `health_ok`: PX4 reports local position and home."""

    def __init__(
        self, clock: Callable[[], float], on_mode: Callable[[FlightMode, str], None]
    ) -> None:
        self._clock = clock
        self._on_mode = on_mode
        self.value = AutopilotTelemetry()
        self.health_ok = False

    async def run(self, api: Any, direct: DirectLink | None) -> None:
        """Consume every subscription until cancelled."""
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(
                    self._consume(api.subscribe_position_velocity_ned(), self._on_pos_vel)
                )
                group.create_task(
                    self._consume(api.subscribe_attitude_quaternion(), self._on_attitude)
                )
                group.create_task(self._consume(api.subscribe_flight_mode(), self._on_flight_mode))
                group.create_task(self._consume(api.subscribe_armed(), self._on_armed))
                group.create_task(self._consume(api.subscribe_in_air(), self._on_in_air))
                group.create_task(self._consume(api.subscribe_health(), self._on_health))
                group.create_task(self._consume(api.subscribe_home(), self._on_home))
                group.create_task(self._consume(api.subscribe_battery(), self._on_battery))
                group.create_task(self._consume(api.subscribe_gps_info(), self._on_gps_info))
                if direct is not None:
                    group.create_task(direct.run(self._on_status, self._on_mode_report))
        except* Exception as group_error:  # logged: the daemon sees stale telemetry stamps
            logger.error("autopilot telemetry stopped: %s", group_error.exceptions)

    async def _consume(
        self, stream: AsyncIterator[Any], handler: Callable[[Any, float], None]
    ) -> None:
        async for item in stream:
            handler(item, self._clock())

    def _on_pos_vel(self, item: Any, t_s: float) -> None:
        pos, vel = item.position, item.velocity
        self.value = replace(
            self.value,
            position_ned_m=Stamped(_vector(pos.north_m, pos.east_m, pos.down_m), t_s),
            velocity_ned_mps=Stamped(_vector(vel.north_m_s, vel.east_m_s, vel.down_m_s), t_s),
        )

    def _on_attitude(self, q: Any, t_s: float) -> None:
        self.value = replace(self.value, q_ned_frd_wxyz=Stamped(_vector(q.w, q.x, q.y, q.z), t_s))

    def _on_flight_mode(self, raw: Any, t_s: float) -> None:
        mode = FlightMode.__members__.get(getattr(raw, "name", ""), FlightMode.UNKNOWN)
        self.value = replace(self.value, flight_mode=Stamped(mode, t_s))
        self._on_mode(mode, "heartbeat")

    def _on_status(self, status: mav.VehicleStatus) -> None:
        self.value = replace(self.value, status=Stamped(status, self._clock()))

    def _on_mode_report(self, report: mav.ModeReport) -> None:
        t_s = self._clock()
        self.value = replace(
            self.value,
            mode_report=Stamped(report, t_s),
            flight_mode=Stamped(report.mode, t_s),
        )
        self._on_mode(report.mode, "CURRENT_MODE")

    def _on_armed(self, armed: Any, t_s: float) -> None:
        self.value = replace(self.value, armed=Stamped(bool(armed), t_s))

    def _on_in_air(self, in_air: Any, t_s: float) -> None:
        self.value = replace(self.value, in_air=Stamped(bool(in_air), t_s))

    def _on_home(self, home: Any, t_s: float) -> None:
        position = GlobalPosition(
            float(home.latitude_deg), float(home.longitude_deg), float(home.absolute_altitude_m)
        )
        if not all(math.isfinite(v) for v in vars(position).values()):
            return  # no global home yet
        local = (home.local_north_m, home.local_east_m, home.local_down_m)
        local_ned = tuple(float(c) if math.isfinite(float(c)) else 0.0 for c in local)
        value = HomePosition(position, (local_ned[0], local_ned[1], local_ned[2]))
        self.value = replace(self.value, home=Stamped(value, t_s))

    def _on_battery(self, battery: Any, t_s: float) -> None:
        # MAVSDK 4 reports remaining_percent in 0..100 (not 0..1); NaN when PX4 does not know.
        remaining, voltage = float(battery.remaining_percent), float(battery.voltage_v)
        value = BatteryState(
            remaining_pct=remaining if math.isfinite(remaining) else None,
            voltage_v=voltage if math.isfinite(voltage) else None,
        )
        self.value = replace(self.value, battery=Stamped(value, t_s))

    def _on_gps_info(self, info: Any, t_s: float) -> None:
        name = getattr(info.fix_type, "name", "")
        fix = GpsFixType.__members__.get(name, GpsFixType.NO_GPS)
        value = GpsState(fix_type=fix, satellites=int(info.num_satellites))
        self.value = replace(self.value, gps=Stamped(value, t_s))

    def _on_health(self, health: Any, t_s: float) -> None:
        self.health_ok = bool(health.is_local_position_ok and health.is_home_position_ok)
