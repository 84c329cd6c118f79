"""Flight recorder: MCAP written and read back, rotation, dropping, a killed writer's file."""

from __future__ import annotations

import base64
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from companion.control import ControlConfig, ControlLaw
from companion.errors import ConfigError, RecorderError
from companion.flight_log import (
    TOPIC_FRAME,
    TOPIC_HEALTH,
    TOPIC_POLICY,
    TOPIC_SETPOINT,
    TOPIC_TELEMETRY,
    LogReader,
    recover_log,
)
from companion.recorder import FlightRecorder, RecorderConfig, format_summary, summarize_log

REPO = Path(__file__).resolve().parents[2]
T0_NS = 1_700_000_000_000_000_000  # 2023-11-14T22:13:20Z


class FakeClocks:
    """Deterministic wall (ns) and monotonic (s) clocks, safe to read from the writer thread."""

    def __init__(self, step_ns: int = 10_000_000) -> None:
        self._lock = threading.Lock()
        self.now_ns = T0_NS
        self.step_ns = step_ns
        self.mono_s = 0.0

    def clock_ns(self) -> int:
        with self._lock:
            self.now_ns += self.step_ns
            return self.now_ns

    def monotonic(self) -> float:
        with self._lock:
            return self.mono_s

    def advance(self, seconds: float) -> None:
        with self._lock:
            self.mono_s += seconds


def wait_written(recorder: FlightRecorder, n: int) -> None:
    deadline = time.monotonic() + 10.0
    while recorder.stats().written < n:
        assert time.monotonic() < deadline, "writer thread did not catch up"
        time.sleep(0.005)


def messages(path: Path) -> list:
    return list(LogReader(path).messages())


def test_write_and_read_back_every_topic(tmp_path: Path) -> None:
    clocks = FakeClocks()
    cfg = RecorderConfig(directory=tmp_path, frame_every_n=2)
    law = ControlLaw(ControlConfig())
    images = [np.full((64, 384), 10 * i, dtype=np.uint8) for i in range(10)]
    images[4][3, 5] = 255
    with FlightRecorder(
        cfg, drone_id="d1", metadata={"model_sha256": "ab" * 32}, clock_ns=clocks.clock_ns
    ) as rec:
        for i, image in enumerate(images):
            rec.record_frame(image, publish_time_ns=T0_NS + i)
            rec.record(TOPIC_POLICY, {"vel_body_flu": np.array([0.1, 0.0, np.nan]), "ok": True})
            setpoint = law.step([1.0, 0.0, 0.0], [1.0, 0, 0, 0], [0.0, 0.0, 5.0], 0.0)
            rec.record(TOPIC_SETPOINT, setpoint.as_dict())
        rec.record(TOPIC_TELEMETRY, {"armed": True, "pos_ned": [1.0, 2.0, -5.0]})
        rec.record_health("offboard_started", "info", {"after_s": 1.2})
    [path] = rec.files
    assert re.fullmatch(r"flight_d1_20231114T221320Z_000\.mcap", path.name)
    assert rec.stats().written == 5 + 10 + 10 + 2 and rec.stats().dropped == 0

    reader = LogReader(path)
    got = list(reader.messages())
    assert reader.complete and reader.stopped_at is None
    assert reader.metadata["flight"]["model_sha256"] == "ab" * 32
    by_topic: dict[str, list] = {}
    for m in got:
        by_topic.setdefault(m.topic, []).append(m)
    counts = {topic: len(items) for topic, items in by_topic.items()}
    assert counts == {TOPIC_FRAME: 5, TOPIC_POLICY: 10, TOPIC_SETPOINT: 10, TOPIC_TELEMETRY: 1,
                      TOPIC_HEALTH: 1}  # fmt: skip

    frame = by_topic[TOPIC_FRAME][2].json()  # third recorded frame = image 4
    assert (frame["width"], frame["height"], frame["encoding"], frame["step"]) == (
        384, 64, "mono8", 384)  # fmt: skip
    pixels = np.frombuffer(base64.b64decode(frame["data"]), dtype=np.uint8).reshape(64, 384)
    np.testing.assert_array_equal(pixels, images[4])
    assert by_topic[TOPIC_FRAME][2].publish_time_ns == T0_NS + 4
    assert frame["timestamp"] == {"sec": (T0_NS + 4) // 10**9, "nsec": (T0_NS + 4) % 10**9}
    assert by_topic[TOPIC_POLICY][0].json()["vel_body_flu"] == [0.1, 0.0, None]  # NaN -> null
    assert by_topic[TOPIC_SETPOINT][0].json()["vel_ned"] == pytest.approx([0.0, 1.0, 0.0])
    assert [m.sequence for m in by_topic[TOPIC_POLICY]] == list(range(10))
    assert all(m.log_time_ns > T0_NS for m in got)

    # The standard indexed reader (what tools use) agrees.
    with open(path, "rb") as f:
        reader2 = make_reader(f)
        summary = reader2.get_summary()
        assert summary is not None and summary.statistics.message_count == len(got)
        schemas = {s.name for s in summary.schemas.values()}
        assert "foxglove.RawImage" in schemas


def test_summary_counts_duration_and_health_events(tmp_path: Path) -> None:
    clocks = FakeClocks(step_ns=100_000_000)  # 0.1 s per clock read
    with FlightRecorder(RecorderConfig(directory=tmp_path), clock_ns=clocks.clock_ns) as rec:
        for _ in range(20):
            rec.record(TOPIC_TELEMETRY, {"alt_m": 5.0})
        rec.record_health("images_stale", "warning", "front 0.4 s old")
        rec.record_health("landing", "error", "")
    summary = summarize_log(rec.files[0])
    assert summary["complete"] and summary["message_count"] == 22
    assert summary["duration_s"] == pytest.approx(2.1)
    assert summary["channels"][TOPIC_TELEMETRY]["count"] == 20
    events = summary["health_events"]
    assert [(e["level"], e["event"]) for e in events] == [
        ("warning", "images_stale"),
        ("error", "landing"),
    ]
    text = format_summary(summary)
    assert "complete" in text and "images_stale: front 0.4 s old" in text
    assert re.search(r"/autopilot/telemetry\s+20 msgs\s+10.0 Hz", text)


def test_rotation_by_size_keeps_every_file_readable(tmp_path: Path) -> None:
    cfg = RecorderConfig(directory=tmp_path, max_file_mb=0.08)  # ~2 frames (33 kB JSON each)
    rng = np.random.default_rng(0)
    with FlightRecorder(cfg) as rec:
        for _ in range(7):
            rec.record_frame(rng.integers(0, 255, (64, 384), dtype=np.uint8))
    files = rec.files
    assert len(files) >= 3
    assert [int(p.stem.rsplit("_", 1)[1]) for p in files] == list(range(len(files)))
    total = 0
    for path in files:
        reader = LogReader(path)
        total += len(list(reader.messages()))
        assert reader.complete
        assert path.stat().st_size < 0.08e6 + 40_000
    assert total == 7


def test_rotation_by_duration(tmp_path: Path) -> None:
    clocks = FakeClocks()
    cfg = RecorderConfig(directory=tmp_path, max_file_s=10.0)
    with FlightRecorder(cfg, clock_ns=clocks.clock_ns, monotonic=clocks.monotonic) as rec:
        rec.record(TOPIC_TELEMETRY, {"i": 0})
        rec.record(TOPIC_TELEMETRY, {"i": 1})
        wait_written(rec, 2)
        clocks.advance(10.5)
        rec.record(TOPIC_TELEMETRY, {"i": 2})
        wait_written(rec, 3)
    assert len(rec.files) == 2
    assert [m.json()["i"] for m in messages(rec.files[0])] == [0, 1]
    assert [m.json()["i"] for m in messages(rec.files[1])] == [2]


class StalledRecorder(FlightRecorder):
    """A recorder whose disk hangs on the first message until `release` is set."""

    entered = threading.Event()
    release = threading.Event()

    def _write(self, item, now_s):  # type: ignore[no-untyped-def]
        self.entered.set()
        self.release.wait(10.0)
        super()._write(item, now_s)


def test_full_queue_drops_instead_of_blocking(tmp_path: Path) -> None:
    rec = StalledRecorder(RecorderConfig(directory=tmp_path, queue_size=3))
    rec.start()
    try:
        assert rec.record(TOPIC_TELEMETRY, {"i": 0})
        assert rec.entered.wait(10.0)  # the writer holds message 0, the queue is empty
        accepted = [rec.record(TOPIC_TELEMETRY, {"i": i}) for i in range(1, 6)]
        assert accepted == [True, True, True, False, False]
        assert rec.stats().dropped == 2
    finally:
        rec.release.set()
        rec.close()
    assert [m.json()["i"] for m in messages(rec.files[0])] == [0, 1, 2, 3]


def test_bad_messages_are_dropped_not_raised(tmp_path: Path) -> None:
    with FlightRecorder(RecorderConfig(directory=tmp_path)) as rec:
        assert not rec.record(TOPIC_TELEMETRY, {"obj": object()})
        assert not rec.record("/no/such/topic", {"a": 1})
        assert not rec.record_frame(np.zeros((64, 384, 3), dtype=np.uint8))
        assert rec.record(TOPIC_TELEMETRY, {"a": 1})
    assert rec.stats().dropped == 3
    assert [m.json() for m in messages(rec.files[0])] == [{"a": 1}]


def test_disabled_recorder_writes_nothing(tmp_path: Path) -> None:
    with FlightRecorder(RecorderConfig(directory=tmp_path / "x", enabled=False)) as rec:
        assert not rec.record(TOPIC_TELEMETRY, {"a": 1})
        assert not rec.record_frame(np.zeros((64, 384), dtype=np.uint8))
    assert rec.files == () and not (tmp_path / "x").exists()
    assert rec.stats().dropped == 0


def test_unwritable_directory_is_a_recorder_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(RecorderError, match="cannot start recording"):
        FlightRecorder(RecorderConfig(directory=blocker)).start()


def test_reader_returns_a_prefix_of_a_file_cut_anywhere(tmp_path: Path) -> None:
    clocks = FakeClocks()
    cfg = RecorderConfig(directory=tmp_path / "src", flush_every_s=0.5)
    with FlightRecorder(cfg, clock_ns=clocks.clock_ns, monotonic=clocks.monotonic) as rec:
        for i in range(12):
            rec.record(TOPIC_TELEMETRY, {"i": i})
            wait_written(rec, i + 1)
            clocks.advance(0.6)  # the next message flushes this one: one chunk per message
    data = rec.files[0].read_bytes()
    cut_file = tmp_path / "cut.mcap"
    seen_counts = set()
    for cut in range(0, len(data) + 1, 37):
        cut_file.write_bytes(data[:cut])
        got = [m.json()["i"] for m in messages(cut_file)]
        assert got == list(range(len(got)))  # a prefix, never garbage or an exception
        seen_counts.add(len(got))
    assert len(seen_counts) >= 10  # the prefix grows chunk by chunk


CHILD = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from companion.recorder import FlightRecorder, RecorderConfig, TOPIC_POLICY, TOPIC_TELEMETRY
    cfg = RecorderConfig(directory=Path(sys.argv[1]), flush_every_s=0.2)
    rec = FlightRecorder(cfg, drone_id="killed")
    rec.start()
    for i in range(20):
        rec.record(TOPIC_POLICY, {"i": i})
    print(rec.files[0], flush=True)
    i = 0
    while True:  # keeps flying (and recording) until killed
        rec.record(TOPIC_TELEMETRY, {"i": i})
        i += 1
        time.sleep(0.01)
    """
)


def test_file_of_a_killed_writer_is_readable_and_recoverable(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO,
    )
    try:
        assert child.stdout is not None
        path = Path(child.stdout.readline().strip())
        # Wait until periodic flushes (not close) have put the first messages on disk.
        deadline = time.monotonic() + 20.0
        while summarize_log(path)["channels"].get(TOPIC_TELEMETRY, {}).get("count", 0) < 10:
            assert time.monotonic() < deadline, "nothing flushed while the writer was running"
            time.sleep(0.05)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait(10.0)
    assert child.returncode == -signal.SIGKILL

    reader = LogReader(path)
    got = list(reader.messages())
    assert not reader.complete  # no footer: the process never closed the file
    policy = [m.json()["i"] for m in got if m.topic == TOPIC_POLICY]
    telemetry = [m.json()["i"] for m in got if m.topic == TOPIC_TELEMETRY]
    assert policy == list(range(20))
    assert len(telemetry) >= 10 and telemetry == list(range(len(telemetry)))
    assert summarize_log(path)["complete"] is False

    fixed = tmp_path / "recovered.mcap"
    assert recover_log(path, fixed) == len(got)
    with open(fixed, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count == len(got)
    assert summarize_log(fixed)["metadata"]["flight"]["drone_id"] == "killed"


def test_config_validation_and_from_dict(tmp_path: Path) -> None:
    cfg = RecorderConfig.from_dict({"directory": "logs", "frame_every_n": 5}, base_dir=tmp_path)
    assert cfg.directory == tmp_path / "logs" and cfg.frame_every_n == 5
    assert (cfg.enabled, cfg.flush_every_s, cfg.max_file_mb, cfg.max_file_s) == (
        True, 1.0, 512.0, 900.0)  # fmt: skip
    with pytest.raises(ConfigError, match=r"unknown key\(s\) 'max_mb'"):
        RecorderConfig.from_dict({"max_mb": 3})
    with pytest.raises(ConfigError, match="recorder.frame_every_n: 0 is outside"):
        RecorderConfig(frame_every_n=0)
    with pytest.raises(ConfigError, match="recorder.enabled: expected true or false"):
        RecorderConfig(enabled=1)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="recorder.file_prefix"):
        RecorderConfig(file_prefix="a/b")
