"""Frame rate and parser-error windows of a serial camera link (pure logic, explicit times)."""

from __future__ import annotations

from companion.camera.link_stats import ErrorWindow, FrameRate, describe_errors
from companion.camera.protocol import ParserCounters


def test_frame_rate_counts_the_last_two_seconds_edges_included_as_stated() -> None:
    rate = FrameRate(window_s=2.0)
    for k in range(24):  # 8 Hz from t=0 to t=2.875 (binary-exact times)
        rate.add(k * 0.125)
    assert rate.fps(2.875) == 16 / 2.0  # (0.875, 2.875]: k = 8 .. 23
    assert rate.fps(3.0) == 15 / 2.0  # t = 1.0 lies exactly on the edge: out
    assert rate.fps(4.875) == 0.0  # the last frame, 2 s ago, is on the edge: out
    assert rate.fps(4.75) == 1 / 2.0


def test_describe_errors_names_each_counter_that_moved() -> None:
    before = ParserCounters(corrupted_headers=3, dropped_bytes=100)
    after = ParserCounters(
        corrupted_headers=15, corrupted_payloads=1, sequence_gaps=2, dropped_bytes=700
    )
    text = describe_errors(before, after, 1.04)
    assert (
        text == "bad header x12, bad payload x1, sequence gap x2, 600 bytes dropped "
        "in the last 1.0 s"
    )
    assert describe_errors(after, after, 1.0) is None


def test_error_window_reports_once_per_window_that_held_errors() -> None:
    window = ErrorWindow(window_s=1.0)
    clean = ParserCounters(frames_ok=5)
    dirty = ParserCounters(frames_ok=9, corrupted_headers=4, dropped_bytes=168)
    assert window.update(clean, 10.0) is None  # opens the first window
    assert window.update(dirty, 10.5) is None  # still inside it
    assert window.update(dirty, 11.0) == "bad header x4, 168 bytes dropped in the last 1.0 s"
    assert window.update(dirty, 12.2) is None  # nothing new in the next window
