"""`swarm-sim fly | view`: refuse what cannot be shown, say how far a flight has come."""

import pytest

from sim_harness.cli import main

SHORT = ["--agents", "3", "--goal-distance", "3"]  # the flock arrives at step 23 (seed 0)


def test_view_refuses_a_step_past_the_end_of_the_flight_naming_the_last_one(
    tmp_path, capsys
) -> None:
    out = tmp_path / "view"
    assert main(["view", *SHORT, "--step", "5000", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "swarm-sim: error: step: 5000 is past the end of the flight: the flock arrived at step "
        "23 (t = 2.3 s); the last step available is 23"
    )
    assert not out.exists()  # nothing rendered for another step


@pytest.mark.slow
def test_view_renders_the_last_step_available(tmp_path, capsys) -> None:
    out = tmp_path / "view"
    assert main(["view", *SHORT, "--step", "23", "--out", str(out)]) == 0
    assert (out / "common-s0-step23-agent0-strip.png").stat().st_size > 0


def test_fly_progress_in_a_log_is_plain_lines(tmp_path, capsys) -> None:
    out = tmp_path / "fly"
    assert main(["fly", *SHORT, "--out", str(out)]) == 0
    err = capsys.readouterr().err  # not a terminal here, as when redirected to a file
    assert "\r" not in err
    lines = [line for line in err.splitlines() if line.startswith("common / teacher:")]
    assert lines[0].startswith("common / teacher:   0% 0/900")  # 90 s at 10 Hz at most
    assert lines[-1].startswith("common / teacher:   3% 23/900") and "arrived]" in lines[-1]
