"""The README's commands work as written, in order, in a fresh shell after the set-up commands."""

import re
from pathlib import Path

import pytest

from sim_harness.cli import main
from sim_harness.experiments.cli import DEMO_DURATION

README = Path(__file__).resolve().parents[1] / "README.md"
ACTIVATE = re.compile(r"^(source|\.) \.venv/bin/activate\b")
BARE = re.compile(r"^(swarm-sim|companion)\b")  # a console script called through PATH


def bash_lines() -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", README.read_text(), flags=re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def test_console_scripts_are_called_only_once_the_environment_is_active() -> None:
    lines = bash_lines()
    bare = [k for k, line in enumerate(lines) if BARE.match(line)]
    activated = [k for k, line in enumerate(lines) if ACTIVATE.match(line)]
    assert bare, "the README shows no swarm-sim or companion command"
    assert activated and activated[0] < bare[0], (
        f"{lines[bare[0]]!r} runs before the README activates .venv (the set-up commands call "
        ".venv/bin/... and leave the shell outside the environment)"
    )


def test_the_readme_and_the_demos_help_state_the_same_duration(capsys) -> None:
    text = " ".join(README.read_text().split())
    assert f"The demo ({DEMO_DURATION};" in text
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    assert DEMO_DURATION in " ".join(capsys.readouterr().out.split())
