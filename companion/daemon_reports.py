"""Plain-dict payloads the daemon hands to the flight recorder and to Zenoh telemetry.

Kept apart from the loop so the loop reads as control flow. Frames and units follow the names:
PX4 local NED for autopilot values, body FLU for policy outputs, seconds on the monotonic clock
for ages. Every function returns JSON-ready values (NaN is turned into null by the encoders).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from companion.autopilot_types import AutopilotTelemetry, OffboardState
from companion.camera.rig import RigImage
from companion.camera.serial_link import SerialCameraLink
from companion.control import ControlOutput
from companion.health import HealthDecision
from companion.policy import PolicyOutput


def telemetry_payload(telemetry: AutopilotTelemetry, now_s: float) -> dict[str, Any]:
    """What the autopilot reported, with each value's age (s); None where nothing arrived yet."""
    out: dict[str, Any] = {}
    for name in ("position_ned_m", "velocity_ned_mps", "q_ned_frd_wxyz"):
        stamped = getattr(telemetry, name)
        out[name] = None if stamped is None else stamped.value.tolist()
        out[f"{name}_age_s"] = None if stamped is None else round(now_s - stamped.t_s, 4)
    mode = telemetry.flight_mode
    out["flight_mode"] = None if mode is None else mode.value.value
    out["armed"] = None if telemetry.armed is None else telemetry.armed.value
    out["in_air"] = None if telemetry.in_air is None else telemetry.in_air.value
    out.update(power_and_gps_payload(telemetry, now_s))
    return out


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def power_and_gps_payload(telemetry: AutopilotTelemetry, now_s: float) -> dict[str, Any]:
    """`battery` {remaining_pct (0..100), voltage_v} and `gps` {fix_type ("fix_3d", ...),
    satellites}, each with its age (s); every value null until the autopilot reported it."""
    battery, gps = telemetry.battery, telemetry.gps
    return {
        "battery": {
            "remaining_pct": None if battery is None else _rounded(battery.value.remaining_pct, 1),
            "voltage_v": None if battery is None else _rounded(battery.value.voltage_v, 2),
        },
        "battery_age_s": None if battery is None else round(now_s - battery.t_s, 4),
        "gps": {
            "fix_type": None if gps is None else gps.value.fix_type.value,
            "satellites": None if gps is None else gps.value.satellites,
        },
        "gps_age_s": None if gps is None else round(now_s - gps.t_s, 4),
    }


def state_payload(
    decision: HealthDecision,
    telemetry: AutopilotTelemetry,
    offboard: OffboardState,
    now_s: float,
) -> dict[str, Any]:
    """The drone's state for `swarm/<id>/state`: health state plus the autopilot's view."""
    return {
        "health": decision.state.value,
        "offboard": offboard.value,
        **telemetry_payload(telemetry, now_s),
    }


def setpoint_payload(
    decision: HealthDecision,
    command: ControlOutput | None,
    *,
    sent: bool,
    tick_latency_s: float | None,
    image_age_s: float | None,
    late_s: float,
) -> dict[str, Any]:
    """One tick's command: every control stage (when computed), what was done, and timings.

    `tick_latency_s`: from the tick's rig snapshot (all six frames present) to the setpoint
    sent, for ticks that used a new image; `image_age_s`: from the newest tile's arrival to the
    send; `late_s`: how late the tick started after its deadline.
    """
    out: dict[str, Any] = {
        "state": decision.state.value,
        "action": decision.action.value,
        "reason": decision.reason,
        "sent": sent,
        "tick_latency_s": tick_latency_s,
        "image_age_s": image_age_s,
        "late_s": round(late_s, 6),
    }
    if command is not None:
        out.update(command.as_dict())
    return out


def policy_payload(output: PolicyOutput, image: RigImage) -> dict[str, Any]:
    """A policy result and the image it came from (per-face sequence numbers, times)."""
    return {
        **output.as_dict(),
        "seqs": list(image.seqs),
        "oldest_capture_time_s": image.oldest_capture_time_s,
        "oldest_receive_time_s": image.oldest_receive_time_s,
    }


def links_payload(links: Mapping[str, SerialCameraLink]) -> dict[str, Any]:
    """Per face: frame rate, parser error counters and the last error (what the ground station
    shows), then the link's state. Counters count since the daemon started; `fps` is over the
    last 2 s; `last_error` is "" until something went wrong, `last_error_age_s` null then."""
    out: dict[str, Any] = {}
    for face, link in links.items():
        status = link.status()
        counters = status.counters
        error_age_s = status.last_error_age_s
        out[face] = {
            "fps": round(status.fps, 2),
            "bad_headers": counters.corrupted_headers,
            "bad_payloads": counters.corrupted_payloads,
            "dropped_bytes": counters.dropped_bytes,
            "seq_gaps": counters.sequence_gaps,
            "last_error": status.last_error or "",
            "last_error_age_s": None if error_age_s is None else round(error_age_s, 3),
            "invalid_messages": counters.invalid_messages,
            "missed_messages": counters.missed_messages,
            "device": status.device,
            "connected": status.connected,
            "camera_uid": status.camera_uid,
            "frames_ok": status.frames_ok,
            "age_s": None if status.last_frame_age_s is None else round(status.last_frame_age_s, 3),
            "reconnects": status.reconnects,
        }
    return out


# What changes a camera record in the flight log (the rest, rates and ages, change every time).
LINK_CHANGE_KEYS = (
    "bad_headers",
    "bad_payloads",
    "dropped_bytes",
    "seq_gaps",
    "last_error",
    "invalid_messages",
    "connected",
    "camera_uid",
    "reconnects",
)


def links_signature(report: Mapping[str, Any]) -> tuple[Any, ...]:
    """The part of a `links_payload` whose change is worth a flight-log record at once."""
    return tuple(
        (face, tuple(entry.get(key) for key in LINK_CHANGE_KEYS))
        for face, entry in sorted(report.items())
    )
