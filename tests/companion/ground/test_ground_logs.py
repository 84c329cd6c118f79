"""`companion ground logs pull` over a real sshd: real recorders' MCAP files, the drone's real
tar, flock and od, only new closed files, and nothing half-written under a final name."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

from companion import cli
from companion.flight_log import TOPIC_SETPOINT, recover_log
from companion.recorder import FlightRecorder, RecorderConfig, summarize_log

from .conftest import Sshd

T0_NS = 1_700_000_000_000_000_000


def record(directory: Path, drone_id: str, start_ns: int, messages: int = 50) -> FlightRecorder:
    """A started recorder that has queued `messages` setpoints (the caller closes it)."""
    clock = iter(range(start_ns, start_ns + 10**15, 10_000_000))
    lock = threading.Lock()

    def clock_ns() -> int:
        with lock:
            return next(clock)

    recorder = FlightRecorder(
        RecorderConfig(directory=directory), drone_id=drone_id, clock_ns=clock_ns
    )
    recorder.start()
    for i in range(messages):
        recorder.record(TOPIC_SETPOINT, {"tick": i, "vel_ned": [0.1 * i, 0.0, 0.0]})
    return recorder


def pull(
    sshd: Sshd, remote: Path, dest: Path, capsys: pytest.CaptureFixture[str]
) -> tuple[int, str]:
    argv = ["ground", "logs", "pull", "--hosts", "127.0.0.1", "--dest", str(dest)]
    status = cli.main([*argv, "--remote-dir", str(remote), *sshd.cli_args()])
    return status, capsys.readouterr().out


def test_pull_fetches_closed_logs_once_and_never_the_one_being_written(
    sshd: Sshd, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    remote, dest = tmp_path / "drone" / "flights", tmp_path / "ground"
    closed = record(remote, "d1", T0_NS)
    closed.close()
    (closed_file,) = closed.files
    # A log whose daemon was killed: no footer, and no recorder holds it any more.
    crashed_file = remote / "flight_d1_20200101T000000Z_000.mcap"
    crashed_file.write_bytes(closed_file.read_bytes()[:-200])
    writing = record(remote, "d1", T0_NS + 3600 * 10**9)
    (writing_file,) = writing.files
    try:
        status, out = pull(sshd, remote, dest, capsys)
        assert status == 0, out
        here = dest / "127.0.0.1"
        assert sorted(p.name for p in here.iterdir()) == sorted(
            [closed_file.name, crashed_file.name]
        )
        assert (here / closed_file.name).read_bytes() == closed_file.read_bytes()
        assert (here / crashed_file.name).read_bytes() == crashed_file.read_bytes()
        assert f"skipped {writing_file.name}: being written" in out
        assert f"INCOMPLETE {crashed_file.name}" in out and "companion log recover" in out
        assert "2 pulled" in out and "1/1 hosts ok" in out
        summary = summarize_log(here / closed_file.name)
        assert summary["complete"] and summary["channels"][TOPIC_SETPOINT]["count"] == 50
        assert recover_log(here / crashed_file.name, tmp_path / "recovered.mcap") > 0

        status, out = pull(sshd, remote, dest, capsys)  # nothing new
        assert status == 0 and "0 pulled (0.0 MB), 2 already here, 1 skipped" in out
    finally:
        writing.close()
    status, out = pull(sshd, remote, dest, capsys)  # the flight is over: now it comes
    assert status == 0 and "1 pulled" in out and "2 already here, 0 skipped" in out
    assert (dest / "127.0.0.1" / writing_file.name).read_bytes() == writing_file.read_bytes()
    assert not list((dest / "127.0.0.1").glob(".*.part"))


def test_pull_from_a_drone_without_that_folder_fails_with_the_reason(
    sshd: Sshd, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, out = pull(sshd, tmp_path / "nowhere", tmp_path / "ground", capsys)
    assert status == 1
    assert f"FAILED: 0 pulled (0.0 MB), 0 already here, 0 skipped; cannot list {tmp_path}" in out
    assert "0/1 hosts ok" in out


@pytest.mark.parametrize("remote_dir", ["relative/flights", "/tmp/x y", "/a/../etc", "/$(reboot)"])
def test_pull_refuses_a_remote_folder_that_is_not_a_plain_absolute_path(
    remote_dir: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["ground", "logs", "pull", "--hosts", "d1", "--dest", str(tmp_path)]
    assert cli.main([*argv, "--remote-dir", remote_dir]) == 2
    assert "ground.remote_dir" in capsys.readouterr().err
