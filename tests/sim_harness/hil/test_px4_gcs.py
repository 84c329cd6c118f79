"""The PX4 ground station's reading of PX4's own messages, without PX4: real MAVLink bytes, as PX4
(system 1, component 1) sends them, through the station's message handler."""

from __future__ import annotations

import time
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sim_harness.hil.px4_gcs import GroundStation
from sim_harness.hil.px4_logic import Px4Mode

HOME_AMSL_M = 488.0


def from_px4(build: Any) -> Any:
    """A message packed by system 1, component 1 and parsed back, header included."""
    sender = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    receiver = mavlink.MAVLink(None)
    return receiver.parse_buffer(build(sender).pack(sender))[0]


def heard(gcs: GroundStation, mode: Px4Mode, local_z_m: float, height_m: float) -> None:
    now = time.monotonic()
    armed = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    messages = (
        lambda m: m.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR,
            mavlink.MAV_AUTOPILOT_PX4,
            armed,
            mode.custom_mode,
            mavlink.MAV_STATE_ACTIVE,
        ),
        lambda m: m.local_position_ned_encode(0, 0.0, 0.0, local_z_m, 0.0, 0.0, 0.0),
        lambda m: m.global_position_int_encode(
            0,
            473977420,
            85455940,
            round((HOME_AMSL_M + height_m) * 1000),
            round(height_m * 1000),
            0,
            0,
            0,
            0,
        ),
    )
    for build in messages:
        gcs._on_message(from_px4(build), now)


def test_the_take_off_is_judged_above_home_not_from_the_estimators_origin() -> None:
    # Measured on a loaded machine: PX4's local frame started 0.74 m above the ground, so a
    # take-off to 4.59 m above home held at a local z of -3.85 m. That is a finished take-off.
    gcs = GroundStation(port=18570)
    heard(gcs, Px4Mode.HOLD, local_z_m=-3.85, height_m=4.59)
    assert gcs.home_alt_amsl_m == HOME_AMSL_M
    assert gcs.height_above_home_m == 4.59
    assert gcs.holding_at(4.59)


def test_the_take_off_is_not_done_before_the_height_or_outside_hold() -> None:
    gcs = GroundStation(port=18570)
    assert not gcs.holding_at(4.59)  # nothing heard yet
    heard(gcs, Px4Mode.HOLD, local_z_m=-4.6, height_m=3.9)  # the local z alone would pass
    assert not gcs.holding_at(4.59)
    heard(gcs, Px4Mode.TAKEOFF, local_z_m=-4.6, height_m=4.6)
    assert not gcs.holding_at(4.59)
    heard(gcs, Px4Mode.HOLD, local_z_m=-4.6, height_m=4.2)
    assert gcs.holding_at(4.59)
