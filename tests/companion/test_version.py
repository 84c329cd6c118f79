"""`companion --version`: the package version, the source commit and the model's hash."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

import pytest

from companion import __version__, cli, version
from companion.camera.layout import FACE_NAMES

REPO = Path(__file__).resolve().parents[2]


def write_config(tmp_path: Path, model_bytes: bytes, pin: str | None) -> Path:
    (tmp_path / "policy.pt").write_bytes(model_bytes)
    faces = "".join(
        f'[cameras.faces.{face}]\ndevice = "/dev/openmv-{face}"\ncamera_id = "{i + 1:024x}"\n'
        for i, face in enumerate(FACE_NAMES)
    )
    pinned = "" if pin is None else f'sha256 = "{pin}"\n'
    path = tmp_path / "companion.toml"
    path.write_text(f'[policy]\nmodel_path = "policy.pt"\n{pinned}[cameras]\n{faces}')
    return path


def test_version_names_the_package_the_commit_and_the_shipped_model(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(version, "DEFAULT_CONFIG", tmp_path / "absent.toml")
    assert cli.main(["--version"]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = subprocess.run(
        ["git", "-c", f"safe.directory={REPO}", "-C", str(REPO), "rev-parse", "HEAD"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    shipped = REPO / "models" / "swarm_cnn.pt"
    digest = hashlib.sha256(shipped.read_bytes()).hexdigest()
    assert lines == [
        f"companion {__version__}",
        f"commit {head} (git checkout {REPO})",
        f"model {shipped} sha256 {digest} (shipped model)",
    ]


def test_version_with_a_config_hashes_its_model_against_the_pin(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = b"not really a model"
    digest = hashlib.sha256(model).hexdigest()
    config = write_config(tmp_path, model, digest)
    assert cli.main(["--version", "--config", str(config)]) == 0
    line = capsys.readouterr().out.splitlines()[2]
    assert (
        line == f"model {tmp_path / 'policy.pt'} sha256 {digest} (config {config}: matches the pin)"
    )
    config = write_config(tmp_path, model, "0" * 64)
    assert cli.main(["--version", "--config", str(config)]) == 0
    assert f"DIFFERS from the pin {'0' * 64}" in capsys.readouterr().out
    assert cli.main(["--version", "--config", str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml" in capsys.readouterr().err


def test_an_install_without_git_reports_the_commit_recorded_at_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    commit = "0123456789abcdef0123456789abcdef01234567"
    monkeypatch.setattr(version, "git_commit", lambda repo=None: None)
    monkeypatch.setattr(version, "BUILD_INFO", tmp_path / "_build_info.py")
    assert version.commit_line() == "commit unknown (not a git checkout, none recorded at install)"
    (tmp_path / "_build_info.py").write_text(f'COMMIT = "{commit}"\n')
    assert version.commit_line() == f"commit {commit} (recorded at install)"


def test_the_commit_is_read_from_loose_and_packed_refs(tmp_path: Path) -> None:
    def git(*args: str) -> str:
        env = ["-c", "user.name=t", "-c", "user.email=t@t", "-c", f"safe.directory={tmp_path}"]
        done = subprocess.run(
            ["git", *env, "-C", str(tmp_path), *args], capture_output=True, text=True, check=True
        )
        return done.stdout.strip()

    git("init", "-q")
    git("commit", "-q", "--allow-empty", "-m", "one")
    head = git("rev-parse", "HEAD")
    assert version.git_commit(tmp_path) == head
    git("pack-refs", "--all")
    assert not any((tmp_path / ".git" / "refs" / "heads").iterdir())
    assert version.git_commit(tmp_path) == head
    assert version.git_commit(tmp_path / "absent") is None
