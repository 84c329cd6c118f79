"""Progress bars: redrawn on a terminal, a few plain lines in a log file; one helper for all."""

import io
import re
from pathlib import Path

from sim_harness.sim.progress import progress_bar

ROOT = Path(__file__).resolve().parents[3]


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def run_bar(stream: io.StringIO, steps: int = 1000) -> str:
    with progress_bar(total=steps, desc="train", file=stream, unit="img", mininterval=0) as bar:
        for _ in range(steps):
            bar.update()
    return stream.getvalue()


def test_off_a_terminal_the_bar_writes_a_plain_line_every_tenth_without_carriage_returns() -> None:
    text = run_bar(io.StringIO())
    assert "\r" not in text
    lines = text.splitlines()
    percents = [int(m.group(1)) for m in (re.search(r"train:\s+(\d+)%", ln) for ln in lines) if m]
    assert len(percents) == len(lines)  # every line is a progress line
    assert percents == [0, 10, 20, 30, 40, 50, 60, 70, 80, 90, 100]
    assert lines[-1].startswith("train: 100% 1000/1000")


def test_on_a_terminal_it_is_tqdms_bar_redrawn_in_place() -> None:
    assert "\r" in run_bar(Terminal(), steps=50)


def test_a_disabled_bar_writes_nothing() -> None:
    stream = io.StringIO()
    with progress_bar(total=10, desc="x", file=stream, enabled=False) as bar:
        bar.update(10)
    assert stream.getvalue() == ""


def test_a_total_raised_while_running_ends_on_the_count_reached() -> None:
    stream = io.StringIO()
    with progress_bar(total=300, desc="train", file=stream, mininterval=0) as bar:
        for _ in range(36):
            bar.total = max(bar.total, bar.n + 10)
            bar.update(10)
    assert stream.getvalue().splitlines()[-1].startswith("train: 100% 360/360")


def test_every_progress_bar_of_the_package_goes_through_the_helper() -> None:
    users = [
        path.relative_to(ROOT).as_posix()
        for path in (ROOT / "sim_harness").rglob("*.py")
        if re.search(r"^\s*(from tqdm|import tqdm)", path.read_text(), flags=re.M)
    ]
    assert users == ["sim_harness/sim/progress.py"]
