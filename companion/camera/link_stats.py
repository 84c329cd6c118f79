"""What a serial camera link measures about its stream: frame rate, and parser errors per window.

Pure logic, no I/O: times are seconds of the host monotonic clock the link uses, counters are the
parser's cumulative `ParserCounters`. Imports only `companion.camera.protocol`.
"""

from __future__ import annotations

from collections import deque

from companion.camera.protocol import ParserCounters

FPS_WINDOW_S = 2.0  # frame rate over this many seconds
ERROR_WINDOW_S = 1.0  # parser errors are summed over windows of this length
MAX_RATE_HZ = 200.0  # the frame-rate window remembers at most this rate's worth of frames

# (counter, how one of it reads in a sentence): in the order an operator reads them.
_ERRORS = (
    ("corrupted_headers", "bad header"),
    ("corrupted_payloads", "bad payload"),
    ("invalid_messages", "invalid message"),
    ("unsupported_version", "message of another version"),
    ("sequence_gaps", "sequence gap"),
)


class FrameRate:
    """Frames per second over the last `window_s`: frames received in (now - window, now]
    divided by the window. A new stream therefore ramps up over its first `window_s`, and a
    stream that stops reads 0 once `window_s` has passed."""

    def __init__(self, window_s: float = FPS_WINDOW_S) -> None:
        self.window_s = window_s
        self._times_s: deque[float] = deque(maxlen=int(window_s * MAX_RATE_HZ) + 1)

    def add(self, t_s: float) -> None:
        """One frame received at `t_s`."""
        self._times_s.append(t_s)

    def fps(self, now_s: float) -> float:
        """Frames per second over the window ending at `now_s`."""
        start_s = now_s - self.window_s
        count = sum(1 for t_s in self._times_s if start_s < t_s <= now_s)
        return count / self.window_s


def describe_errors(before: ParserCounters, after: ParserCounters, span_s: float) -> str | None:
    """One line naming the parser errors between two counter snapshots, e.g.
    "bad header x12, 5320 bytes dropped in the last 1.0 s"; None if there were none."""
    parts = []
    for name, text in _ERRORS:
        count = getattr(after, name) - getattr(before, name)
        if count > 0:
            parts.append(f"{text} x{count}")
    dropped = after.dropped_bytes - before.dropped_bytes
    if dropped > 0:
        parts.append(f"{dropped} bytes dropped")
    if not parts:
        return None
    return f"{', '.join(parts)} in the last {span_s:.1f} s"


class ErrorWindow:
    """Sums the parser's errors over consecutive windows of `window_s`.

    `update(counters, now_s)` is called after each read; when it closes a window that held
    errors it returns their description (`describe_errors`), else None.
    """

    def __init__(self, window_s: float = ERROR_WINDOW_S) -> None:
        self.window_s = window_s
        self._start_s: float | None = None
        self._base = ParserCounters()

    def update(self, counters: ParserCounters, now_s: float) -> str | None:
        """The description of the window that `now_s` closes, if it held errors."""
        if self._start_s is None:
            self._start_s = now_s
            return None
        span_s = now_s - self._start_s
        if span_s < self.window_s:
            return None
        text = describe_errors(self._base, counters, span_s)
        self._start_s, self._base = now_s, counters
        return text
