"""Live telemetry over Zenoh: the drone publishes, nothing is accepted in return.

Key expressions (`{key_prefix}/{drone_id}/...`, default prefix `swarm`):

| key                     | encoding          | content                                        |
|-------------------------|-------------------|------------------------------------------------|
| swarm/<id>/state        | application/json  | what the daemon last reported as state         |
| swarm/<id>/health       | application/json  | health summary                                 |
| swarm/<id>/setpoint     | application/json  | last control output                            |
| swarm/<id>/preview      | image/png         | stitched 64x384 image, every `preview_every_s` |

Each JSON message is `{"drone_id", "seq", "stamp_ns" (wall clock, ns since the epoch), "age_s"
(time since the daemon last updated this value: a stalled pipeline shows as a growing age),
"data": {...}}`. The daemon hands values over with `update_*()` (latest-value slots, no queue);
`run()` publishes them at `rate_hz` (default 5 Hz). The session declares publishers only: no
subscriber, no queryable, so telemetry cannot command the drone.

Topology (decided here): by default the drone **listens** (`listen_endpoints`, default
`tcp/127.0.0.1:7447`) and ground monitors connect to it, so the drone never waits for a ground
station and any number of monitors may attach; set the listen endpoint to the drone's Wi-Fi
address (e.g. `tcp/192.168.1.21:7447`) to be reachable. `connect_endpoints` (e.g. a ground
router) may be used instead or as well. Multicast scouting is off by default (explicit
endpoints only), as every default endpoint is on loopback.

Nothing here blocks the event loop: opening the session, encoding and `put` run on one worker
thread; puts use congestion control DROP (a slow link loses telemetry, never stalls the drone).

Telemetry is a side output and never grounds the drone: when the session cannot be opened (the
listen address is not up yet, e.g. Wi-Fi still associating, or the port is taken) `open()` logs
one warning and returns False, and `run()` keeps retrying in the background, `retry_min_s`
doubling to `retry_max_s` (1 s to 30 s), publishing from the moment it opens. `on_event`, when
set (the daemon sets it to its flight-log events), hears "telemetry unavailable" and
"telemetry up".
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh
from numpy.typing import NDArray

from companion import jsonable
from companion.errors import ConfigError
from companion.sections import require_bool, section_from_dict
from companion.validation import require_range

log = logging.getLogger(__name__)

SECTION = "telemetry"
KINDS = ("state", "health", "setpoint")
PREVIEW = "preview"
MODES = ("peer", "client")
DEFAULT_PORT = 7447
_ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic)/(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_NAME_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def _endpoints(field: str, value: object) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, list | tuple):
        raise ConfigError(f"{field}: expected a list of endpoints like 'tcp/127.0.0.1:7447'")
    for item in value:
        match = _ENDPOINT_RE.match(item) if isinstance(item, str) else None
        if match is None or not 0 <= int(match.group(3)) <= 65535:
            raise ConfigError(
                f"{field}: {item!r} is not an endpoint PROTO/HOST:PORT (proto tcp, udp, tls or "
                "quic; port in [0, 65535]), e.g. 'tcp/127.0.0.1:7447'"
            )
    return tuple(value)


@dataclass(frozen=True)
class TelemetryConfig:
    """The `[telemetry]` section."""

    drone_id: str = "drone0"  # key segment: 1-64 of A-Z a-z 0-9 _ -
    enabled: bool = True
    listen_endpoints: tuple[str, ...] = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)
    connect_endpoints: tuple[str, ...] = ()
    mode: str = "peer"  # "peer" or "client" (client needs connect_endpoints: a router)
    multicast_scouting: bool = False
    rate_hz: float = 5.0
    preview_every_s: float | None = None  # None: no preview images
    key_prefix: str = "swarm"
    retry_min_s: float = 1.0  # first wait before re-opening a session that could not open
    retry_max_s: float = 30.0  # the wait doubles up to this

    def __post_init__(self) -> None:
        s = SECTION
        for name in ("drone_id", "key_prefix"):
            value = getattr(self, name)
            if not isinstance(value, str) or not _NAME_RE.match(value):
                raise ConfigError(f"{s}.{name}: {value!r} must be 1-64 of A-Z a-z 0-9 _ -")
        require_bool(f"{s}.enabled", self.enabled)
        listen = _endpoints(f"{s}.listen_endpoints", self.listen_endpoints)
        connect = _endpoints(f"{s}.connect_endpoints", self.connect_endpoints)
        object.__setattr__(self, "listen_endpoints", listen)
        object.__setattr__(self, "connect_endpoints", connect)
        if self.mode not in MODES:
            raise ConfigError(f"{s}.mode: {self.mode!r} is not one of {', '.join(MODES)}")
        require_bool(f"{s}.multicast_scouting", self.multicast_scouting)
        if self.mode == "client" and not connect:
            raise ConfigError(f"{s}.connect_endpoints: client mode needs at least one (a router)")
        if self.enabled and not (listen or connect or self.multicast_scouting):
            raise ConfigError(
                f"{s}.listen_endpoints: no listen or connect endpoint and no scouting: "
                "nobody could receive the telemetry"
            )
        require_range(f"{s}.rate_hz", self.rate_hz, 0.0, 100.0, low_inclusive=False)
        if self.preview_every_s is not None:
            require_range(f"{s}.preview_every_s", self.preview_every_s, 0.1, 3600.0)
        require_range(f"{s}.retry_min_s", self.retry_min_s, 0.0, 60.0, low_inclusive=False)
        require_range(f"{s}.retry_max_s", self.retry_max_s, self.retry_min_s, 600.0)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TelemetryConfig:
        """From the parsed `[telemetry]` table (endpoint lists become tuples)."""
        overrides: dict[str, Any] = {}
        if isinstance(data, Mapping):
            for name in ("listen_endpoints", "connect_endpoints"):
                if name in data:
                    overrides[name] = _endpoints(f"{SECTION}.{name}", data[name])
        return section_from_dict(cls, SECTION, data, **overrides)

    def key(self, kind: str) -> str:
        """Key expression of one kind of message, e.g. `swarm/drone0/state`."""
        return f"{self.key_prefix}/{self.drone_id}/{kind}"


def zenoh_config(config: TelemetryConfig) -> zenoh.Config:
    """The Zenoh session configuration: mode, explicit endpoints, multicast scouting."""
    zconf = zenoh.Config()
    zconf.insert_json5("mode", json.dumps(config.mode))
    zconf.insert_json5("listen/endpoints", json.dumps(list(config.listen_endpoints)))
    zconf.insert_json5("connect/endpoints", json.dumps(list(config.connect_endpoints)))
    zconf.insert_json5("scouting/multicast/enabled", json.dumps(config.multicast_scouting))
    return zconf


@dataclass(frozen=True)
class TelemetryStats:
    published: int  # messages put
    failed: int  # puts that raised
    last_error: str | None


class TelemetryPublisher:
    """Publishes the latest state, health, setpoint (and preview) at `rate_hz` over Zenoh.

    Use: `await open()`, then run `run()` as a task; call `update_*()` from the control loop;
    `await close()` at the end (or `async with`). Disabled (`enabled=False`): every call no-op.
    """

    def __init__(
        self,
        config: TelemetryConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.config = config
        self._clock = clock
        self._clock_ns = clock_ns
        self._lock = threading.Lock()
        self._slots: dict[str, tuple[float, Any]] = {}
        self._preview: tuple[float, NDArray[np.uint8]] | None = None
        self._last_preview_s: float | None = None
        self._seq = 0
        self._published = 0
        self._failed = 0
        self._last_error: str | None = None
        self._session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._executor: ThreadPoolExecutor | None = None
        self._open_attempts = 0
        self._first_failure_s: float | None = None
        self.on_event: Callable[[str, str, Any], None] | None = None  # (event, level, detail)

    # --- lifecycle ---------------------------------------------------------------------------

    async def open(self) -> bool:
        """Open the session and declare the publishers; True once open (or when disabled).

        False if Zenoh refused (listen address not available, port taken): logged once as a
        warning, and `run()` retries in the background. Never raises for that.
        """
        if not self.config.enabled or self._session is not None:
            return True
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="telemetry")
        self._open_attempts += 1
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(self._executor, self._open_session)
        except zenoh.ZError as exc:
            self._last_error = f"cannot open the telemetry session: {exc}"
            if self._first_failure_s is None:
                self._first_failure_s = self._clock()
                cfg = self.config
                log.warning(
                    "telemetry unavailable, flying without it; retrying every %g..%g s: %s",
                    cfg.retry_min_s,
                    cfg.retry_max_s,
                    exc,
                )
                self._emit("telemetry unavailable", "warning", {"error": str(exc)})
            return False
        if self._first_failure_s is not None:
            after_s = round(self._clock() - self._first_failure_s, 3)
            log.info("telemetry up after %d attempts (%.1f s)", self._open_attempts, after_s)
            detail = {"attempts": self._open_attempts, "after_s": after_s}
            self._emit("telemetry up", "info", detail)
            self._first_failure_s = None
        return True

    def _emit(self, event: str, level: str, detail: Any) -> None:
        if self.on_event is not None:
            self.on_event(event, level, detail)

    def _open_session(self) -> None:
        session = zenoh.open(zenoh_config(self.config))
        drop = zenoh.CongestionControl.DROP
        try:
            for kind in KINDS:
                self._publishers[kind] = session.declare_publisher(
                    self.config.key(kind),
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=drop,
                )
            self._publishers[PREVIEW] = session.declare_publisher(
                self.config.key(PREVIEW), encoding=zenoh.Encoding.IMAGE_PNG, congestion_control=drop
            )
        except zenoh.ZError:
            session.close()  # type: ignore[no-untyped-call]
            raise
        self._session = session
        log.info(
            "telemetry: %s, listen %s, connect %s",
            self.config.key("*"),
            list(self.config.listen_endpoints),
            list(self.config.connect_endpoints),
        )

    async def close(self) -> None:
        """Undeclare the publishers and close the session (idempotent)."""
        executor = self._executor
        if executor is None:
            return
        loop = asyncio.get_running_loop()
        try:
            await loop.run_in_executor(executor, self._close_session)
        finally:
            executor.shutdown(wait=False)
            self._executor = None

    def _close_session(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()  # type: ignore[no-untyped-call]
        self._publishers.clear()
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None

    async def __aenter__(self) -> TelemetryPublisher:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def is_open(self) -> bool:
        return self._session is not None

    def stats(self) -> TelemetryStats:
        return TelemetryStats(self._published, self._failed, self._last_error)

    # --- latest values (control loop) --------------------------------------------------------

    def _update(self, kind: str, value: Mapping[str, Any]) -> None:
        # A shallow copy: the caller may reuse its dict (nested containers must not be mutated).
        with self._lock:
            self._slots[kind] = (self._clock(), dict(value))

    def update_state(self, state: Mapping[str, Any]) -> None:
        self._update("state", state)

    def update_health(self, health: Mapping[str, Any]) -> None:
        self._update("health", health)

    def update_setpoint(self, setpoint: Mapping[str, Any]) -> None:
        self._update("setpoint", setpoint)

    def update_preview(self, image_u8: NDArray[np.uint8]) -> None:
        """Offer the latest stitched image; encoded and sent only every `preview_every_s`."""
        if self.config.preview_every_s is not None:
            with self._lock:
                self._preview = (self._clock(), image_u8)

    # --- publishing (worker thread) ----------------------------------------------------------

    def _put(self, kind: str, payload: bytes) -> None:
        try:
            self._publishers[kind].put(payload)
            self._published += 1
        except zenoh.ZError as exc:
            self._failed += 1
            self._last_error = str(exc)
            log.warning("telemetry put on %s failed: %s", kind, exc)

    def _publish_cycle(self) -> int:
        now = self._clock()
        with self._lock:
            slots = dict(self._slots)
            preview = self._preview
        if not self._publishers:
            return 0
        sent = 0
        self._seq += 1
        for kind, (updated_s, value) in slots.items():
            message = {
                "drone_id": self.config.drone_id,
                "seq": self._seq,
                "stamp_ns": self._clock_ns(),
                "age_s": round(now - updated_s, 4),
                "data": value,
            }
            try:
                payload = jsonable.dumps(message)
            except (TypeError, ValueError) as exc:
                self._failed += 1
                self._last_error = f"{kind}: {exc}"
                continue
            self._put(kind, payload)
            sent += 1
        every = self.config.preview_every_s
        due = self._last_preview_s is None or (
            every is not None and now - self._last_preview_s >= every
        )
        if preview is not None and due:
            png = encode_png(preview[1])
            if png is not None:
                self._put(PREVIEW, png)
                sent += 1
            self._last_preview_s = now
        return sent

    async def publish_once(self) -> int:
        """Publish the current values now (off the loop); returns the number of messages."""
        if self._executor is None:
            return 0
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._executor, self._publish_cycle)

    async def run(self) -> None:
        """Open the session if it is not open yet (retrying with backoff), then publish at
        `rate_hz` until cancelled (missed periods are skipped, not bunched)."""
        if not self.config.enabled:
            return
        retry_s = self.config.retry_min_s
        while not self.is_open:
            if self._open_attempts > 0:  # the last attempt failed: back off first
                await asyncio.sleep(retry_s)
                retry_s = min(2.0 * retry_s, self.config.retry_max_s)
            await self.open()
        period_s = 1.0 / self.config.rate_hz
        next_s = self._clock()
        while True:
            try:
                await self.publish_once()
            except Exception as exc:  # telemetry must never take the daemon down
                self._failed += 1
                self._last_error = f"{type(exc).__name__}: {exc}"
                log.warning("telemetry cycle failed: %s", self._last_error)
            next_s += period_s
            now = self._clock()
            if next_s < now:  # fell behind (slow link or loaded CPU): restart the grid
                next_s = now + period_s
            await asyncio.sleep(next_s - now)


def encode_png(image_u8: NDArray[np.uint8]) -> bytes | None:
    """PNG bytes of a 2-D uint8 image (None if it is not one or OpenCV cannot encode it)."""
    import cv2

    image = np.ascontiguousarray(image_u8)
    if image.dtype != np.uint8 or image.ndim != 2:
        return None
    ok, buffer = cv2.imencode(".png", image)
    return bytes(buffer.tobytes()) if ok else None
