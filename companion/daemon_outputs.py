"""The daemon's side outputs after each tick: flight log, Zenoh telemetry, systemd notifications.

Nothing here may slow the control loop: the recorder and the telemetry publisher only take
latest values / queue messages (their I/O runs on their own threads), sd_notify is one datagram.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from companion import daemon_reports as reports
from companion.autopilot_types import AutopilotTelemetry, OffboardState
from companion.camera.rig import RigImage
from companion.camera.serial_link import SerialCameraLink
from companion.control import ControlOutput
from companion.flight_log import TOPIC_CAMERAS
from companion.health import HealthDecision, HealthState
from companion.recorder import TOPIC_SETPOINT, TOPIC_TELEMETRY, FlightRecorder
from companion.sdnotify import SdNotifier
from companion.telemetry import TelemetryPublisher

log = logging.getLogger(__name__)
LINK_REPORT_EVERY_S = 0.5
LINK_LOG_EVERY_S = 5.0  # a /cameras record at least this often; at once on a counter change
_LEVELS = {
    HealthState.STARTING: "info",
    HealthState.ACTIVE: "info",
    HealthState.HOVER: "warning",
    HealthState.STOPPING: "info",
}


@dataclass(frozen=True)
class TickTimes:
    """One tick's times (s, monotonic) and images: the new snapshot, the one flown this tick."""

    now_s: float  # tick start = rig snapshot time
    late_s: float  # start - deadline
    sent_s: float  # after the setpoint was handed to the autopilot
    new_image: RigImage | None  # a snapshot not seen before
    fresh: RigImage | None  # the image whose inference finished within this tick

    @property
    def latency_s(self) -> float | None:
        """All six frames present (snapshot) -> setpoint sent, for images flown this tick."""
        return None if self.fresh is None else self.sent_s - self.now_s

    @property
    def image_age_s(self) -> float | None:
        """Newest tile's arrival -> setpoint sent, for images flown this tick."""
        return None if self.fresh is None else self.sent_s - max(self.fresh.receive_times_s)


class Outputs:
    """Recorder + telemetry + sd_notify, fed once per tick by the daemon."""

    def __init__(
        self,
        recorder: FlightRecorder,
        telemetry: TelemetryPublisher,
        notifier: SdNotifier,
        links: Mapping[str, SerialCameraLink],
        *,
        wall_ns_of: Callable[[float], int],
        watchdog_max_late_s: float,
    ) -> None:
        self.recorder = recorder
        self.telemetry = telemetry
        telemetry.on_event = self.event  # "telemetry unavailable" / "telemetry up" in the log
        self.notifier = notifier
        self._links = links
        self._wall_ns_of = wall_ns_of
        self._watchdog_max_late_s = watchdog_max_late_s
        self._last_watchdog_s = float("-inf")
        self._last_links_s = float("-inf")
        self._links_report: dict[str, Any] = {}
        self._links_logged: tuple[Any, ...] | None = None
        self._last_links_log_s = float("-inf")
        self.ready_sent = False

    def event(self, event: str, level: str, detail: Any) -> None:
        """A health event for the flight log."""
        self.recorder.record_health(event, level, detail)

    def tick(
        self,
        decision: HealthDecision,
        command: ControlOutput | None,
        sent: bool,
        times: TickTimes,
        telemetry: AutopilotTelemetry,
        offboard: OffboardState,
        counters: Mapping[str, Any],
    ) -> None:
        now_s = times.now_s
        if times.new_image is not None:
            image = times.new_image
            stamp_ns = self._wall_ns_of(image.oldest_capture_time_s)
            self.recorder.record_frame(image.image, publish_time_ns=stamp_ns)
            self.telemetry.update_preview(image.image)
        if command is not None:
            payload = reports.setpoint_payload(
                decision,
                command,
                sent=sent,
                tick_latency_s=times.latency_s if sent else None,
                image_age_s=times.image_age_s if sent else None,
                late_s=times.late_s,
            )
            self.recorder.record(TOPIC_SETPOINT, payload)
            self.telemetry.update_setpoint(payload)
        self.recorder.record(TOPIC_TELEMETRY, reports.telemetry_payload(telemetry, now_s))
        self.telemetry.update_state(reports.state_payload(decision, telemetry, offboard, now_s))
        if self._links and now_s - self._last_links_s >= LINK_REPORT_EVERY_S:
            self._last_links_s = now_s
            self._links_report = reports.links_payload(self._links)
            self._log_links(now_s)
        self.telemetry.update_health(
            {
                "state": decision.state.value,
                "reason": decision.reason,
                "healthy": decision.healthy,
                **counters,
                "recorder_dropped": self.recorder.stats().dropped,
                "cameras": self._links_report,
            }
        )
        if decision.transition is not None:
            self.transition(decision)
        if decision.healthy and not self.ready_sent:
            self.ready_sent = True
            self.notifier.ready(f"healthy, {decision.state.value}")
            log.info("pipeline healthy: READY")
        interval = self.notifier.watchdog_interval_s
        on_time = times.late_s <= self._watchdog_max_late_s
        if interval is not None and on_time and now_s - self._last_watchdog_s >= interval:
            self._last_watchdog_s = now_s
            self.notifier.watchdog()

    def _log_links(self, now_s: float) -> None:
        """Record the camera report when its counters changed, else every LINK_LOG_EVERY_S."""
        signature = reports.links_signature(self._links_report)
        if signature == self._links_logged and now_s - self._last_links_log_s < LINK_LOG_EVERY_S:
            return
        self._links_logged = signature
        self._last_links_log_s = now_s
        self.recorder.record(TOPIC_CAMERAS, self._links_report)

    def transition(self, decision: HealthDecision) -> None:
        """Log, record and announce (systemd STATUS) a state change."""
        transition = decision.transition
        if transition is None:
            return
        event = f"{transition.source.value} -> {transition.target.value}"
        level = _LEVELS.get(transition.target, "error")
        log.log(logging.getLevelName(level.upper()), "health %s: %s", event, transition.reason)
        self.recorder.record_health(event, level, transition.reason)
        reason = f": {transition.reason}" if transition.reason else ""
        self.notifier.status(f"{transition.target.value}{reason}"[:200])
