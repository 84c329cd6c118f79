"""An output folder is checked before the work: writable or one clear error, nothing left."""

from pathlib import Path

import pytest

from sim_harness.errors import ConfigError
from sim_harness.sim.out_dir import require_writable_dir


def test_a_new_nested_folder_passes_and_is_not_left_behind(tmp_path) -> None:
    out = tmp_path / "a" / "b" / "c"
    assert require_writable_dir(out) == out
    assert list(tmp_path.iterdir()) == []


def test_an_existing_folder_keeps_its_files_and_gets_no_probe(tmp_path) -> None:
    (tmp_path / "kept.txt").write_text("x")
    require_writable_dir(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["kept.txt"]


def test_a_folder_that_cannot_be_created_names_the_option_and_the_path() -> None:
    with pytest.raises(ConfigError, match=r"^out: cannot write to the folder /proc/forbidden \("):
        require_writable_dir(Path("/proc/forbidden"))


def test_a_file_is_not_a_folder(tmp_path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(ConfigError, match=r"eval-out: .*/f is a file, not a folder"):
        require_writable_dir(tmp_path / "f", "eval-out")
