"""The flight-log folder's disk budget (`[recorder] max_total_mb`) and the being-written mark."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.flight_log import TOPIC_HEALTH, LogReader
from companion.log_budget import is_being_written
from companion.recorder import FlightRecorder, RecorderConfig

MB = 1_000_000


def old_log(directory: Path, name: str, size_bytes: int, age_s: float) -> Path:
    """A closed log from an earlier flight (only its size and age matter to the budget)."""
    path = directory / name
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(size_bytes - 8))
    stamp = time.time() - age_s
    os.utime(path, (stamp, stamp))
    return path


def health_events(path: Path) -> list[dict]:
    return [m.json() for m in LogReader(path).messages() if m.topic == TOPIC_HEALTH]


def wait_written(recorder: FlightRecorder, n: int) -> None:
    deadline = time.monotonic() + 30.0
    while recorder.stats().written < n:
        assert time.monotonic() < deadline, "writer thread did not catch up"
        time.sleep(0.005)


def test_a_new_log_first_deletes_the_oldest_closed_logs_until_it_fits(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    a = old_log(tmp_path, "flight_d1_20260101T100000Z_000.mcap", 300_000, age_s=300)
    b = old_log(tmp_path, "flight_d1_20260101T110000Z_000.mcap", 300_000, age_s=200)
    c = old_log(tmp_path, "flight_d1_20260101T120000Z_000.mcap", 300_000, age_s=100)
    config = RecorderConfig(directory=tmp_path, max_file_mb=0.2, max_total_mb=1.0)
    # 0.9 MB + room for one 0.2 MB file > 1.0 MB: the oldest goes (0.6 + 0.2 fits).
    with caplog.at_level(logging.WARNING), FlightRecorder(config, drone_id="d1") as recorder:
        pass
    assert not a.exists() and b.exists() and c.exists()
    [new] = recorder.files
    assert health_events(new) == [
        {"level": "warning", "event": "log deleted",
         "detail": {"file": a.name, "size_mb": 0.3, "reason": "recorder.max_total_mb 1 MB"}}
    ]  # fmt: skip
    assert f"deleted {a}" in caplog.text


def test_rotation_keeps_the_folder_within_the_budget(tmp_path: Path) -> None:
    config = RecorderConfig(directory=tmp_path, max_file_mb=0.1, max_total_mb=0.3)
    rng = np.random.default_rng(0)
    with FlightRecorder(config, drone_id="d1") as recorder:
        for i in range(40):  # ~25 kB each on disk (noise does not compress): ~1 MB in all
            recorder.record_frame(rng.integers(0, 256, (64, 384), dtype=np.uint8))
            wait_written(recorder, i + 1)
            total = sum(p.stat().st_size for p in tmp_path.glob("*.mcap"))
            assert total <= 0.3 * MB
    left = sorted(tmp_path.glob("*.mcap"))
    assert len(recorder.files) >= 8 and len(left) < len(recorder.files)
    assert left[-1] == recorder.files[-1]  # the newest survives, complete
    reader = LogReader(left[-1])
    assert list(reader.messages()) and reader.complete
    deleted = [e["detail"]["file"] for p in left for e in health_events(p)]
    assert deleted and all(not (tmp_path / name).exists() for name in deleted)


def test_a_log_being_written_is_never_deleted_and_an_overflow_is_recorded(
    tmp_path: Path,
) -> None:
    other = FlightRecorder(RecorderConfig(directory=tmp_path), drone_id="d2")
    other.start()  # another recorder writing into the same folder: its file is oldest
    try:
        [busy] = other.files
        assert is_being_written(busy)
        os.utime(busy, (time.time() - 1000, time.time() - 1000))
        old = old_log(tmp_path, "flight_d1_20260101T100000Z_000.mcap", 150_000, age_s=500)
        config = RecorderConfig(directory=tmp_path, max_file_mb=0.1, max_total_mb=0.1)
        with FlightRecorder(config, drone_id="d1") as recorder:
            pass
        assert busy.exists() and not old.exists()
        events = [e["event"] for e in health_events(recorder.files[0])]
        assert events == ["log deleted", "log budget exceeded"]
    finally:
        other.close()
    assert not is_being_written(busy)


def test_the_budget_is_a_validated_option() -> None:
    assert RecorderConfig.from_dict({"max_total_mb": 2048}).max_total_mb == 2048
    assert RecorderConfig().max_total_mb is None  # no budget unless configured
    with pytest.raises(ConfigError, match=r"recorder\.max_total_mb: .*allowed range \(0, 1e\+09\]"):
        RecorderConfig(max_total_mb=0)
    with pytest.raises(
        ConfigError,
        match=r"recorder\.max_total_mb: 100 is below recorder\.max_file_mb \(512\); allowed range",
    ):
        RecorderConfig(max_total_mb=100)
