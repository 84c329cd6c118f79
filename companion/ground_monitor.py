"""The ground station's live monitor: a table of every drone's Zenoh telemetry, and of each link.

`companion ground monitor --connect tcp/DRONE:7447 ...` opens one Zenoh peer session per endpoint
(multicast scouting and gossip off, so each session hears only what comes over its own link),
subscribes to `swarm/**` and prints, every `interval_s`, a table of every drone heard (health
state, flight mode, armed, battery, GPS fix, position, commanded velocity, per-camera frame
rates, the age of its last message, reason) and one line per endpoint: connecting (nothing heard
yet), connected but silent, or which drones it carries. A drone silent for more than
`stale_after_s` is marked STALE. It only subscribes: it cannot command anything.
"""

from __future__ import annotations

import json
import re
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

from companion.errors import ConfigError, TelemetryError

DEFAULT_MONITOR_ENDPOINT = "tcp/127.0.0.1:7447"
STALE_AFTER_S = 2.0
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_FACE_ORDER = ("front", "right", "back", "left", "up", "down")


def check_endpoints(option: str, endpoints: Sequence[str]) -> tuple[str, ...]:
    """The endpoints if each is PROTO/HOST:PORT; else a ConfigError naming `option`."""
    for endpoint in endpoints:
        match = _ENDPOINT_RE.match(endpoint) if isinstance(endpoint, str) else None
        if match is None or not 1 <= int(match.group(3)) <= 65535:
            raise ConfigError(
                f"monitor {option}: {endpoint!r} is not an endpoint tcp/HOST:PORT (port 1-65535),"
                " e.g. tcp/192.168.1.21:7447"
            )
    return tuple(endpoints)


def _fmt_vec(value: Any, digits: int = 1) -> str:
    if not isinstance(value, list) or len(value) != 3:
        return "-"
    return "(" + ", ".join("-" if v is None else f"{v:+.{digits}f}" for v in value) + ")"


def _number(value: Any) -> float | None:
    is_number = isinstance(value, int | float) and not isinstance(value, bool)
    return float(value) if is_number and value == value else None


def fmt_battery(value: Any) -> str:
    """`{"remaining_pct", "voltage_v"}` as `87% 15.8V`; "-" for what is missing."""
    if not isinstance(value, Mapping):
        return "-"
    pct, volts = _number(value.get("remaining_pct")), _number(value.get("voltage_v"))
    parts = ([] if pct is None else [f"{pct:.0f}%"]) + ([] if volts is None else [f"{volts:.1f}V"])
    return " ".join(parts) or "-"


def fmt_gps(value: Any) -> str:
    """`{"fix_type", "satellites"}` as `FIX_3D 12sat`; "-" for what is missing."""
    if not isinstance(value, Mapping):
        return "-"
    fix = value.get("fix_type")
    sats = _number(value.get("satellites"))
    parts = ([] if fix is None else [str(fix)]) + ([] if sats is None else [f"{sats:.0f}sat"])
    return " ".join(parts) or "-"


def fmt_camera_fps(value: Any) -> str:
    """`{"<face>": {"fps": ...}}` as `F10 R10 B10 L10 U10 D9.5` (face initial, frames/s)."""
    if not isinstance(value, Mapping):
        return "-"
    faces = [f for f in _FACE_ORDER if f in value] + [f for f in value if f not in _FACE_ORDER]
    cells, any_fps = [], False
    for face in faces:
        status = value[face]
        fps = _number(status.get("fps")) if isinstance(status, Mapping) else None
        any_fps = any_fps or fps is not None
        text = "-" if fps is None else (f"{fps:.0f}" if fps >= 9.95 else f"{fps:.1f}")
        cells.append(f"{str(face)[:1].upper()}{text}")
    return " ".join(cells) if any_fps else "-"


@dataclass
class _Link:
    """What one endpoint's session has done: since when, connected, last sample, drones."""

    endpoint: str
    opened_s: float
    connected_s: float | None = None  # since when connected; None: not connected
    lost_s: float | None = None  # when the connection was lost
    last_sample_s: float | None = None
    drones: set[str] = field(default_factory=set)


class SwarmTable:
    """Latest telemetry per drone and kind (`state`, `health`, `setpoint`), as a text table,
    plus one status line per endpoint.

    `update` is called from Zenoh's threads; `render` from the printing thread.
    """

    COLUMNS = (
        "drone", "health", "mode", "armed", "battery", "gps", "pos NED m", "cmd NED m/s",
        "camera fps", "age s", "reason",
    )  # fmt: skip

    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        *,
        endpoints: Sequence[str] = (),
        stale_after_s: float = STALE_AFTER_S,
    ) -> None:
        self._clock = clock
        self.stale_after_s = stale_after_s
        self._lock = threading.Lock()
        self._drones: dict[str, dict[str, tuple[float, dict[str, Any]]]] = {}
        now = clock()
        self._links = {e: _Link(e, now) for e in endpoints}
        self.received = 0

    def update(self, key: str, payload: bytes, endpoint: str | None = None) -> None:
        """One sample on `<prefix>/<drone>/<kind>` heard over `endpoint`; non-JSON kinds
        (preview) only count."""
        parts = key.split("/")
        if len(parts) < 3:
            return
        drone, kind = parts[-2], parts[-1]
        with self._lock:
            now = self._clock()
            self.received += 1
            link = self._links.get(endpoint) if endpoint is not None else None
            if link is not None:
                link.last_sample_s = now
                link.drones.add(drone)
            entry = self._drones.setdefault(drone, {})
            if kind in ("state", "health", "setpoint"):
                try:
                    message = json.loads(payload)
                except ValueError:
                    return
                data = message.get("data") if isinstance(message, dict) else None
                if isinstance(data, dict):
                    entry[kind] = (now, data)
            else:
                entry[kind] = (now, {})

    def set_connected(self, endpoint: str, connected: bool) -> None:
        """Whether `endpoint`'s session has a live Zenoh transport now."""
        with self._lock:
            link = self._links.get(endpoint)
            if link is None:
                return
            now = self._clock()
            if connected and link.connected_s is None:
                link.connected_s, link.lost_s = now, None
            elif not connected and link.connected_s is not None:
                link.connected_s, link.lost_s = None, now

    def drones(self) -> list[str]:
        with self._lock:
            return sorted(self._drones)

    def stale(self) -> list[str]:
        """Drones heard before but silent for more than `stale_after_s`."""
        now = self._clock()
        with self._lock:
            return [
                drone
                for drone in sorted(self._drones)
                if now - max(t for t, _ in self._drones[drone].values()) > self.stale_after_s
            ]

    def rows(self) -> list[tuple[str, ...]]:
        now = self._clock()
        rows: list[tuple[str, ...]] = []
        with self._lock:
            for drone in sorted(self._drones):
                kinds = self._drones[drone]
                state = kinds.get("state", (now, {}))[1]
                health = kinds.get("health", (now, {}))[1]
                setpoint = kinds.get("setpoint", (now, {}))[1]
                age_s = now - max(t for t, _ in kinds.values())
                armed = state.get("armed")
                rows.append(
                    (
                        drone,
                        str(health.get("state") or state.get("health") or "?"),
                        str(state.get("flight_mode") or "?"),
                        "?" if armed is None else ("yes" if armed else "no"),
                        fmt_battery(state.get("battery") or health.get("battery")),
                        fmt_gps(state.get("gps") or health.get("gps")),
                        _fmt_vec(state.get("position_ned_m")),
                        _fmt_vec(setpoint.get("vel_ned"), 2),
                        fmt_camera_fps(health.get("cameras")),
                        f"{age_s:.1f}" + (" STALE" if age_s > self.stale_after_s else ""),
                        str(health.get("reason") or "")[:60],
                    )
                )
        return rows

    def link_lines(self) -> list[str]:
        """One line per endpoint: connecting, connected and silent, or the drones it carries."""
        now = self._clock()
        lines = []
        with self._lock:
            for link in self._links.values():  # in the order given
                if link.connected_s is not None:
                    state = f"connected for {now - link.connected_s:.1f} s"
                elif link.lost_s is not None:
                    state = f"DISCONNECTED {now - link.lost_s:.1f} s ago, reconnecting"
                else:
                    state = f"connecting for {now - link.opened_s:.1f} s"
                if link.last_sample_s is None:
                    heard = "nothing heard"
                else:
                    silent_s = now - link.last_sample_s
                    heard = f"{', '.join(sorted(link.drones))}: last message {silent_s:.1f} s ago"
                    if silent_s > self.stale_after_s:
                        heard += " SILENT"
                lines.append(f"  {link.endpoint}  {state}; {heard}")
        return ["links:", *lines] if lines else []

    def render(self) -> str:
        rows = [self.COLUMNS, *self.rows()]
        widths = [max(len(row[i]) for row in rows) for i in range(len(self.COLUMNS))]
        lines = [
            "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip()
            for row in rows
        ]
        if len(rows) == 1:
            lines.append("(no drone heard yet)")
        stale = self.stale()
        if stale:
            lines.append(f"STALE (nothing for > {self.stale_after_s:g} s): {', '.join(stale)}")
        return "\n".join(lines + self.link_lines())


def monitor_zenoh_config(connect: Sequence[str], listen: Sequence[str] = ()) -> Any:
    """A peer session config: explicit endpoints, multicast scouting and gossip off."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return conf


def _connected(session: Any) -> bool:
    info = session.info
    return bool(list(info.peers_zid()) or list(info.routers_zid()))


def run_monitor(
    connect: Sequence[str] = (DEFAULT_MONITOR_ENDPOINT,),
    *,
    listen: Sequence[str] = (),
    key: str = "swarm/**",
    interval_s: float = 1.0,
    duration_s: float | None = None,
    out: IO[str] = sys.stdout,
    clear: bool = False,
    stale_after_s: float = STALE_AFTER_S,
) -> SwarmTable:
    """Subscribe and print the table every `interval_s` until `duration_s` (None: Ctrl-C).

    One session per `connect` endpoint, one more listening on `listen` (if any).
    """
    connect = check_endpoints("--connect", connect)
    listen = check_endpoints("--listen", listen)
    if not connect and not listen:
        raise ConfigError("monitor --connect: give at least one endpoint tcp/HOST:PORT")
    import zenoh

    labels = [*connect] + (["listen " + " ".join(listen)] if listen else [])
    table = SwarmTable(endpoints=labels, stale_after_s=stale_after_s)
    sessions: list[tuple[str, Any]] = []
    subscribers: list[Any] = []
    try:
        for label in labels:
            conf = (
                monitor_zenoh_config([], listen)
                if label.startswith("listen ")
                else monitor_zenoh_config([label])
            )
            try:
                session = zenoh.open(conf)
            except zenoh.ZError as exc:
                raise TelemetryError(
                    f"monitor: cannot open a Zenoh session for {label}: {exc}"
                ) from None
            sessions.append((label, session))

            def on_sample(sample: Any, label: str = label) -> None:
                table.update(str(sample.key_expr), sample.payload.to_bytes(), label)

            subscribers.append(session.declare_subscriber(key, on_sample))
        start = time.monotonic()
        while duration_s is None or time.monotonic() - start < duration_s:
            wait = interval_s
            if duration_s is not None:
                wait = min(interval_s, max(0.0, start + duration_s - time.monotonic()))
            time.sleep(wait)
            for label, session in sessions:
                table.set_connected(label, _connected(session))
            if clear:
                out.write("\x1b[H\x1b[2J")
            out.write(table.render() + "\n\n")
            out.flush()
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        for _, session in sessions:
            session.close()
    return table
