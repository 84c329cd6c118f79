"""Telemetry: a real Zenoh subscriber session on loopback receives what the drone publishes."""

from __future__ import annotations

import asyncio
import json
import socket
import statistics
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np
import pytest
import zenoh

from companion.errors import ConfigError
from companion.telemetry import TelemetryConfig, TelemetryPublisher, zenoh_config


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Received:
    """Samples collected by a subscriber callback (Zenoh calls it from its own threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.samples: list[tuple[str, bytes, str]] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.samples.append(
                (str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding))
            )

    def on(self, suffix: str) -> list[bytes]:
        with self._lock:
            return [data for key, data, _ in self.samples if key.endswith(suffix)]

    def json_on(self, suffix: str) -> list[dict]:
        return [json.loads(data) for data in self.on(suffix)]


@contextmanager
def ground_session(
    *, connect: list[str] | None = None, listen: list[str] | None = None
) -> Iterator[tuple[zenoh.Session, Received]]:
    """A monitor: a peer session with multicast scouting off, subscribed to `swarm/**`."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    conf.insert_json5("listen/endpoints", json.dumps(listen or []))
    session = zenoh.open(conf)
    received = Received()
    subscriber = session.declare_subscriber("swarm/**", received)
    try:
        yield session, received
    finally:
        subscriber.undeclare()
        session.close()


async def publish_until_received(
    pub: TelemetryPublisher, received: Received, suffix: str = ""
) -> int:
    """Publish until the monitor's link is up and it got a first message (links take ms);
    the number of publish cycles it took."""
    deadline = time.monotonic() + 10.0
    cycles = 0
    while not received.on(suffix):
        assert time.monotonic() < deadline, "the monitor never received anything"
        await pub.publish_once()
        cycles += 1
        await asyncio.sleep(0.02)
    return cycles


async def until_state_seq(received: Received, seq: int) -> None:
    """Wait until the state of publish cycle `seq` arrived (a hang guard, not a timing check).

    One session, one link, one priority: messages arrive in the order they were put, so by then
    everything put in the cycles up to `seq` has arrived too.
    """
    deadline = time.monotonic() + 10.0
    while all(state["seq"] < seq for state in received.json_on("/state")):
        assert time.monotonic() < deadline, f"the state of cycle {seq} never arrived"
        await asyncio.sleep(0.01)


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_monitor_receives_state_health_setpoint_at_about_5_hz() -> None:
    port = free_port()
    cfg = TelemetryConfig(drone_id="d1", listen_endpoints=(f"tcp/127.0.0.1:{port}",))
    assert cfg.rate_hz == 5.0 and cfg.multicast_scouting is False

    async def main(received: Received) -> None:
        async with TelemetryPublisher(cfg) as pub:
            pub.update_state({"pos_enu": np.array([1.0, 2.0, np.nan]), "mode": "offboard"})
            pub.update_health({"ok": True, "events": []})
            pub.update_setpoint({"vel_ned": [0.5, 0.0, 0.0], "yaw_ned_rad": 0.1})
            await publish_until_received(pub, received)
            start = len(received.on("/state"))
            task = asyncio.create_task(pub.run())
            try:
                deadline = time.monotonic() + 15.0
                while len(received.on("/state")) < start + 11:
                    assert time.monotonic() < deadline
                    await asyncio.sleep(0.02)
            finally:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            assert pub.stats().failed == 0

    with ground_session(connect=[f"tcp/127.0.0.1:{port}"]) as (_, received):
        asyncio.run(main(received))

    states = received.json_on("/state")
    assert states[0]["drone_id"] == "d1"
    assert states[0]["data"] == {"pos_enu": [1.0, 2.0, None], "mode": "offboard"}
    seqs = [s["seq"] for s in states]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    # ~5 Hz, from the publisher's own stamps of the cycles `run()` made. `run()` keeps a fixed
    # grid, so a cycle a loaded machine delays moves one or two periods, not the median of ten.
    periods_s = np.diff([s["stamp_ns"] for s in states[-11:]]) / 1e9
    assert 0.12 < statistics.median(periods_s) < 0.35
    assert received.json_on("/health")[-1]["data"] == {"ok": True, "events": []}
    assert received.json_on("/setpoint")[-1]["data"]["vel_ned"] == [0.5, 0.0, 0.0]
    assert all("application/json" in enc for _, _, enc in received.samples)
    assert received.on("/preview") == []  # preview is off by default


def test_preview_png_and_age_of_values() -> None:
    port = free_port()
    clock = FakeClock()
    cfg = TelemetryConfig(
        drone_id="d2", listen_endpoints=(f"tcp/127.0.0.1:{port}",), preview_every_s=1.0
    )
    first = np.zeros((64, 384), dtype=np.uint8)
    image = (np.arange(64 * 384) % 251).astype(np.uint8).reshape(64, 384)

    async def main(received: Received) -> None:
        async with TelemetryPublisher(cfg, clock=clock) as pub:
            pub.update_state({"armed": True})
            pub.update_preview(first)
            cycles = await publish_until_received(pub, received, "/state")
            # One state per cycle; the fake clock stood still, so only the first cycle was due a
            # preview (counted where they are put: no fixed sleep a loaded machine could outlast).
            assert pub.stats().published == cycles + 1
            clock.now += 2.0  # the state was last updated 2 s ago; a preview is due again
            pub.update_preview(image)
            sent = [await pub.publish_once() for _ in range(3)]
            assert sent == [2, 1, 1]  # then no preview: less than 1 s since the last one
            await until_state_seq(received, cycles + 3)

    with ground_session(connect=[f"tcp/127.0.0.1:{port}"]) as (_, received):
        asyncio.run(main(received))
    previews = [
        cv2.imdecode(np.frombuffer(png, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        for png in received.on("/preview")
    ]
    assert 1 <= len(previews) <= 2  # the first cycle's is lost if it beat the link
    assert all(np.array_equal(p, first) for p in previews[:-1])
    np.testing.assert_array_equal(previews[-1], image)  # the one due after 2 s, exactly once
    assert received.json_on("/state")[-1]["age_s"] == pytest.approx(2.0)


def test_drone_accepts_no_queries_or_commands() -> None:
    port = free_port()
    cfg = TelemetryConfig(drone_id="d3", listen_endpoints=(f"tcp/127.0.0.1:{port}",))

    async def main(session: zenoh.Session, received: Received) -> None:
        async with TelemetryPublisher(cfg) as pub:
            pub.update_state({"x": 1})
            await publish_until_received(pub, received)
            session.put("swarm/d3/command", b'{"land": true}')  # nobody listens to this
            replies = await asyncio.to_thread(lambda: list(session.get("swarm/d3/**", timeout=0.5)))
            assert replies == []
            assert pub.stats().published >= 1

    with ground_session(connect=[f"tcp/127.0.0.1:{port}"]) as (session, received):
        asyncio.run(main(session, received))


def test_drone_can_connect_to_a_listening_ground_station() -> None:
    port = free_port()
    cfg = TelemetryConfig(
        drone_id="d4", listen_endpoints=(), connect_endpoints=(f"tcp/127.0.0.1:{port}",)
    )

    async def main(received: Received) -> None:
        async with TelemetryPublisher(cfg) as pub:
            pub.update_setpoint({"vel_ned": [0.0, 1.0, 0.0]})
            await publish_until_received(pub, received)

    with ground_session(listen=[f"tcp/127.0.0.1:{port}"]) as (_, received):
        asyncio.run(main(received))
    assert received.json_on("/setpoint")[0]["data"] == {"vel_ned": [0.0, 1.0, 0.0]}


def test_taken_port_is_not_fatal_run_retries_until_it_is_free() -> None:
    """Another process holds the listen port (or the Wi-Fi address is not up yet): open() says
    so once and returns; run() keeps retrying and telemetry flows once the port is free."""
    port = free_port()
    cfg = TelemetryConfig(
        drone_id="d5",
        listen_endpoints=(f"tcp/127.0.0.1:{port}",),
        retry_min_s=0.05,
        retry_max_s=0.2,
    )
    holder = socket.socket()
    holder.bind(("127.0.0.1", port))
    holder.listen()
    events: list[tuple[str, str, object]] = []

    async def main() -> None:
        pub = TelemetryPublisher(cfg)
        pub.on_event = lambda event, level, detail: events.append((event, level, detail))
        assert await pub.open() is False  # no exception: the drone flies on without telemetry
        assert not pub.is_open and "cannot open" in (pub.stats().last_error or "")
        assert [e[:2] for e in events] == [("telemetry unavailable", "warning")]
        pub.update_state({"x": 1})
        task = asyncio.create_task(pub.run())
        try:
            deadline = time.monotonic() + 10.0
            while pub._open_attempts < 4:  # retrying in the background, still not open
                assert time.monotonic() < deadline and not task.done()
                await asyncio.sleep(0.02)
            assert not pub.is_open and len(events) == 1  # one warning, not one per attempt
            holder.close()  # the port is free now
            with ground_session(connect=[f"tcp/127.0.0.1:{port}"]) as (_, received):
                while not received.json_on("/state"):
                    assert time.monotonic() < deadline + 10.0, "telemetry never came up"
                    await asyncio.sleep(0.02)
            assert received.json_on("/state")[-1]["data"] == {"x": 1}
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await pub.close()
        assert events[-1][:2] == ("telemetry up", "info")
        detail = events[-1][2]
        # The count rises as an attempt starts: the 4th may still have been binding (in its
        # thread) when the port was freed, and succeed; a loaded machine showed exactly that.
        assert isinstance(detail, dict) and detail["attempts"] >= 4

    try:
        asyncio.run(main())
    finally:
        holder.close()


def test_close_frees_the_port() -> None:
    port = free_port()
    cfg = TelemetryConfig(drone_id="d5", listen_endpoints=(f"tcp/127.0.0.1:{port}",))

    async def main() -> None:
        first = TelemetryPublisher(cfg)
        assert await first.open() and first.is_open
        assert await TelemetryPublisher(cfg).open() is False  # taken by the first
        await first.close()
        await first.close()  # idempotent
        assert not first.is_open
        async with TelemetryPublisher(cfg) as again:  # the port was released
            assert again.is_open

    asyncio.run(main())


def test_disabled_publisher_does_nothing() -> None:
    async def main() -> None:
        async with TelemetryPublisher(TelemetryConfig(enabled=False)) as pub:
            pub.update_state({"a": 1})
            assert await pub.publish_once() == 0
            await asyncio.wait_for(pub.run(), 1.0)  # returns at once
            assert not pub.is_open

    asyncio.run(main())


def test_config_defaults_validation_and_from_dict() -> None:
    cfg = TelemetryConfig()
    assert cfg.listen_endpoints == ("tcp/127.0.0.1:7447",) and cfg.connect_endpoints == ()
    assert cfg.key("state") == "swarm/drone0/state"
    zconf = zenoh_config(cfg)
    assert json.loads(zconf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(zconf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    parsed = TelemetryConfig.from_dict(
        {"drone_id": "alpha-1", "connect_endpoints": ["tcp/10.0.0.2:7447"], "mode": "client"}
    )
    assert parsed.connect_endpoints == ("tcp/10.0.0.2:7447",) and parsed.mode == "client"
    with pytest.raises(ConfigError, match="telemetry.drone_id"):
        TelemetryConfig(drone_id="a/b")
    with pytest.raises(ConfigError, match="telemetry.listen_endpoints: 'tcp/127.0.0.1' is not"):
        TelemetryConfig(listen_endpoints=("tcp/127.0.0.1",))
    with pytest.raises(ConfigError, match="telemetry.connect_endpoints: client mode"):
        TelemetryConfig(mode="client")
    with pytest.raises(ConfigError, match="telemetry.mode"):
        TelemetryConfig(mode="router")
    with pytest.raises(ConfigError, match="nobody could receive"):
        TelemetryConfig(listen_endpoints=())
    with pytest.raises(ConfigError, match=r"unknown key\(s\) 'endpoints'"):
        TelemetryConfig.from_dict({"endpoints": []})
    with pytest.raises(ConfigError, match="telemetry.rate_hz"):
        TelemetryConfig(rate_hz=0)
    assert (TelemetryConfig().retry_min_s, TelemetryConfig().retry_max_s) == (1.0, 30.0)
    assert TelemetryConfig(retry_min_s=2.0, retry_max_s=2.0).retry_max_s == 2.0  # the boundary
    with pytest.raises(ConfigError, match=r"telemetry\.retry_max_s: 1\.9"):
        TelemetryConfig(retry_min_s=2.0, retry_max_s=1.9)
    with pytest.raises(ConfigError, match=r"telemetry\.retry_min_s"):
        TelemetryConfig(retry_min_s=0.0)
