"""The ground station over a real sshd on loopback: launch, the journal of a failed start, the
quoting of remote commands, timeouts. systemctl and journalctl on the 'drone' are stand-ins."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from companion import cli
from companion.groundstation import DEFAULT_UNIT, format_launch, launch, run_remote

from .conftest import ALLOWED, Sshd

CAUSE = "companion: error: policy.model_path: /opt/vision-swarm/models/policy.pt: no such file"
FAILED_START = f"""echo "systemctl $*" >> "$(dirname "$0")/../systemctl_calls"
[ "$1" = start ] || exit 0
echo 'Job for {DEFAULT_UNIT} failed because the control process exited with error code.' >&2
echo 'See "systemctl status {DEFAULT_UNIT}" and "journalctl -xeu {DEFAULT_UNIT}" for details.' >&2
exit 1
"""
# 25 lines of the unit's journal; the cause is the last one (journalctl -n 20 shows it).
JOURNAL = f"i=1; while [ $i -le 24 ]; do echo \"old line $i\"; i=$((i+1)); done\necho '{CAUSE}'\n"


def run_launch(sshd: Sshd, action: str, timeout_s: float = 30.0) -> str:
    target = sshd.target()
    results = asyncio.run(
        launch(
            [target.host],
            action,
            user=target.user,
            port=target.port,
            options=target.options,
            timeout_s=timeout_s,
        )
    )
    return format_launch(results, action)


def test_a_failed_start_shows_the_units_journal_not_only_see_systemctl_status(
    sshd: Sshd,
) -> None:
    sshd.fake("systemctl", FAILED_START)
    sshd.fake("journalctl", JOURNAL)
    text = run_launch(sshd, "start")
    assert "FAILED (exit 1)" in text and "0/1 hosts ok" in text
    assert CAUSE in text  # the reason the daemon did not start, from its journal
    assert "Job for" in text  # systemctl's own lines too
    # Over SSH, both commands ran through sudo -n exactly as the sudoers rule allows them.
    assert sshd.sudo_log() == [f"systemctl start {DEFAULT_UNIT}", ALLOWED[-1]]


def test_a_journal_the_sudoers_rule_does_not_allow_is_said_so(sshd: Sshd) -> None:
    sshd.fake("systemctl", FAILED_START)
    sshd.fake("journalctl", JOURNAL)
    allowed = sshd.bin_dir.parent / "allowed"
    allowed.write_text(allowed.read_text().replace(ALLOWED[-1], "journalctl"))
    text = run_launch(sshd, "start")
    assert "journal: not readable: sudo: a password is required" in text
    assert CAUSE not in text


def test_cli_launch_start_and_stop_over_ssh(sshd: Sshd, capsys: pytest.CaptureFixture[str]) -> None:
    sshd.fake("systemctl", FAILED_START)
    base = ["ground", "launch", "--hosts", "127.0.0.1", *sshd.cli_args()]
    assert cli.main([*base, "--action", "stop"]) == 0
    assert "1/1 hosts ok" in capsys.readouterr().out
    assert cli.main(base) == 1
    out = capsys.readouterr().out
    assert "0/1 hosts ok" in out and "Job for" in out and "  journal: " in out
    calls = (sshd.bin_dir.parent / "systemctl_calls").read_text().splitlines()
    assert calls == [f"systemctl stop {DEFAULT_UNIT}", f"systemctl start {DEFAULT_UNIT}"]


def test_remote_argv_arrives_word_for_word_whatever_it_contains(sshd: Sshd, tmp_path: Path) -> None:
    marker = tmp_path / "injected"
    words = ["a b", "it's", '"quoted"', f"$(touch {marker})", "`id`", "x;y", "*", "--flag"]
    argv = sshd.target().argv(["printf", "%s\\n", *words])
    result = asyncio.run(run_remote("127.0.0.1", argv, 30.0, merge_stderr=False))
    assert result.ok, result.stderr
    assert result.output.splitlines() == words
    assert not marker.exists()


def test_a_hung_remote_command_is_cut_at_the_timeout(sshd: Sshd) -> None:
    sshd.fake("systemctl", "sleep 60\n")
    # 8 s: far above an SSH login on a loaded machine (~0.2 s quiet), far below the 60 s hang.
    text = run_launch(sshd, "restart", timeout_s=8.0)
    assert "FAILED: no answer within 8 s" in text


def test_an_unreachable_drone_says_so(sshd: Sshd) -> None:
    target = sshd.target()
    argv = target.argv(["true"])
    argv[argv.index(str(target.port))] = "1"  # nothing listens on port 1
    result = asyncio.run(run_remote("127.0.0.1", argv, 30.0))
    assert result.returncode == 255 and "Connection refused" in result.output
