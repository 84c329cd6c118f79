"""Progress bars for every long job of `swarm-sim`: a tqdm bar on a terminal, plain lines elsewhere.

A bar redrawn with carriage returns fills a log file (stderr redirected, a CI job, `nohup`) with
thousands of overwritten copies. When the stream is not a terminal, `progress_bar` returns a
`LineProgress` instead: the same tqdm object and API, but it writes one plain line at the start,
each time another `LINE_EVERY_FRACTION` of the total is done or `LINE_EVERY_S` have passed, and
at the end.
"""

from __future__ import annotations

import sys
import time
from typing import IO, Any

from tqdm import tqdm

ProgressBar = tqdm  # what `progress_bar` returns, for annotations
LINE_EVERY_FRACTION = 0.1
LINE_EVERY_S = 10.0
LINE_FORMAT = (
    "{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]"
)
LINE_FORMAT_NO_TOTAL = "{desc}: {n_fmt} [{elapsed}, {rate_fmt}{postfix}]"


def is_terminal(stream: IO[str]) -> bool:
    """Whether `stream` is an interactive terminal (a bar can be redrawn in place)."""
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty()) if callable(isatty) else False
    except ValueError:  # a closed stream
        return False


class LineProgress(tqdm):  # type: ignore[type-arg]
    """A tqdm bar that prints plain, newline-terminated lines, a few per job (for log files)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._last_line_s = -float("inf")
        self._last_bucket = -1
        self._last_line_n: float | None = None
        self._last_postfix: str | None = None
        kwargs["leave"] = False  # the closing line is written by `display` itself
        kwargs.setdefault("mininterval", 0.5)
        if "bar_format" not in kwargs:
            kwargs["bar_format"] = (
                LINE_FORMAT if kwargs.get("total") is not None else LINE_FORMAT_NO_TOTAL
            )
        super().__init__(*args, **kwargs)

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:
        closing = bool(self.disable)  # `close` disables the bar before its last display
        now = time.monotonic()
        bucket = -1
        if self.total:
            bucket = int(min(self.n / self.total, 1.0) / LINE_EVERY_FRACTION + 1e-9)
        due = bucket > self._last_bucket or now - self._last_line_s >= LINE_EVERY_S
        if closing:  # a last line unless the previous one said it all
            due = (self.n, self.postfix) != (self._last_line_n, self._last_postfix)
        if due:
            self.fp.write(str(self) + "\n")
            self.fp.flush()
            self._last_line_s, self._last_bucket = now, bucket
            self._last_line_n, self._last_postfix = self.n, self.postfix
        return False  # nothing to clear with a carriage return


def progress_bar(
    *,
    total: float | None,
    desc: str,
    enabled: bool = True,
    lines: bool | None = None,
    file: IO[str] | None = None,
    **kwargs: Any,
) -> ProgressBar[Any]:
    """A progress bar writing to `file` (default stderr), or a disabled one when not `enabled`.

    `lines`: None picks by the stream (a redrawn bar on a terminal, plain lines otherwise); True
    forces plain lines (e.g. in pool workers, whose bars would overwrite each other). Other
    keyword arguments go to tqdm (`unit`, `initial`, `leave`, `unit_scale`, `smoothing`).
    """
    stream = file if file is not None else sys.stderr
    if not enabled:
        return tqdm(total=total, desc=desc, disable=True, file=stream, **kwargs)
    if lines is None:
        lines = not is_terminal(stream)
    if lines:
        return LineProgress(total=total, desc=desc, file=stream, **kwargs)
    return tqdm(total=total, desc=desc, file=stream, **kwargs)
