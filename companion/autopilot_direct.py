"""MAVSDK's MavlinkDirect for the adapter: the autopilot's HEARTBEAT and CURRENT_MODE, raw
DO_SET_MODE and setpoint messages. The messages' meaning is in `companion.autopilot_mavlink`.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from typing import Any

from mavsdk.asyncio import MavsdkError
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectAsync
from mavsdk.plugins.mavlink_direct import MavlinkDirectError, MavlinkMessage

from companion import autopilot_mavlink as mav
from companion.errors import AutopilotError

logger = logging.getLogger(__name__)
OWN_COMPONENT_ID = 195  # what MAVSDK uses for a companion computer (MAV_COMP_ID_PATHPLANNER)


class DirectLink:
    """Raw MAVLink to and from the autopilot `target_system` (component 1) through MAVSDK."""

    def __init__(self, system: Any, own_system_id: int, target_system: int) -> None:
        self._direct = MavlinkDirectAsync(system)
        self._own_system_id = own_system_id
        self.target_system = target_system

    async def run(
        self,
        on_status: Callable[[mav.VehicleStatus], None],
        on_mode_report: Callable[[mav.ModeReport], None],
    ) -> None:
        """Feed every autopilot HEARTBEAT and CURRENT_MODE to the callbacks, until cancelled."""
        async with asyncio.TaskGroup() as group:
            group.create_task(self._follow("HEARTBEAT", mav.vehicle_status, on_status))
            group.create_task(self._follow("CURRENT_MODE", mav.mode_report, on_mode_report))

    async def _follow(
        self, name: str, parse: Callable[[dict[str, Any]], Any], handler: Any
    ) -> None:
        async for message in self._direct.subscribe_message(name):
            if message.system_id != self.target_system:
                continue
            if message.component_id != mav.AUTOPILOT_COMPONENT_ID:
                continue
            value = parse(mav.parse_fields(message.fields_json))
            if value is not None:
                handler(value)

    async def set_mode(self, custom_mode: int) -> int:
        """DO_SET_MODE to `custom_mode`; returns the COMMAND_ACK result (0: accepted)."""
        fields = mav.set_mode_fields(self.target_system, custom_mode)
        ack = await self._direct.send_command(self._message("COMMAND_LONG", fields))
        result = mav.parse_fields(ack.fields_json).get("result")
        if result is None:
            raise AutopilotError("DO_SET_MODE: no COMMAND_ACK")
        return int(result)

    async def send_setpoint(self, fields: dict[str, Any]) -> None:
        """One SET_POSITION_TARGET_LOCAL_NED (built by `velocity_setpoint_fields`)."""
        await self._direct.send_message(self._message("SET_POSITION_TARGET_LOCAL_NED", fields))

    def _message(self, name: str, fields: dict[str, Any]) -> MavlinkMessage:
        return MavlinkMessage(
            name,
            self._own_system_id,
            OWN_COMPONENT_ID,
            self.target_system,
            mav.AUTOPILOT_COMPONENT_ID,
            json.dumps(fields),
        )

    def destroy(self) -> None:
        try:
            self._direct.destroy()
        except (MavsdkError, MavlinkDirectError, AttributeError) as exc:
            logger.debug("mavlink direct destroy: %s", exc)
