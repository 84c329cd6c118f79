"""What build this is (`companion --version`): package version, source commit, and the model.

The commit comes from the git checkout the package runs from (an editable install), else from
`companion/_build_info.py`, which `python -m companion.version --record [--repo CHECKOUT]` writes
into the sources before a non-editable `pip install` (systemd/install.sh), else it is "unknown".
The model is the one a config flies (its SHA-256, and whether it matches the config's pin); with
no config given, the installed config's, else the model shipped in the checkout.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from companion import __version__
from companion.errors import CompanionError

PACKAGE_DIR = Path(__file__).resolve().parent
DEFAULT_CONFIG = Path("/etc/vision-swarm/companion.toml")
SHIPPED_MODEL = PACKAGE_DIR.parent / "models" / "swarm_cnn.pt"  # present in a checkout only
BUILD_INFO = PACKAGE_DIR / "_build_info.py"
_SHA_RE = re.compile(r"^[0-9a-f]{40}([0-9a-f]{24})?$")


def _git_dir(repo: Path) -> Path | None:
    dot_git = repo / ".git"
    if dot_git.is_file():  # a worktree or submodule: "gitdir: PATH"
        text = dot_git.read_text().strip()
        if text.startswith("gitdir: "):
            path = Path(text.removeprefix("gitdir: "))
            return path if path.is_absolute() else (repo / path).resolve()
        return None
    return dot_git if dot_git.is_dir() else None


def git_commit(repo: Path = PACKAGE_DIR.parent) -> str | None:
    """HEAD's commit of the git checkout at `repo` (read from .git, no git program needed)."""
    git = _git_dir(repo)
    if git is None or not (git / "HEAD").is_file():
        return None
    head = (git / "HEAD").read_text().strip()
    if not head.startswith("ref: "):
        return head if _SHA_RE.match(head) else None
    ref = head.removeprefix("ref: ")
    common = git
    if (git / "commondir").is_file():
        common = (git / (git / "commondir").read_text().strip()).resolve()
    for base in (git, common):
        if (base / ref).is_file():
            sha = (base / ref).read_text().strip()
            return sha if _SHA_RE.match(sha) else None
    packed = common / "packed-refs"
    if packed.is_file():
        for line in packed.read_text().splitlines():
            sha, _, name = line.partition(" ")
            if name == ref and _SHA_RE.match(sha):
                return sha
    return None


def recorded_commit() -> str | None:
    """The commit `--record` wrote at install time, if any."""
    if not BUILD_INFO.is_file():
        return None
    match = re.search(r'^COMMIT = "([0-9a-f]{40,64})"$', BUILD_INFO.read_text(), re.MULTILINE)
    return match.group(1) if match else None


def commit_line() -> str:
    live = git_commit()
    if live is not None:
        return f"commit {live} (git checkout {PACKAGE_DIR.parent})"
    recorded = recorded_commit()
    if recorded is not None:
        return f"commit {recorded} (recorded at install)"
    return "commit unknown (not a git checkout, none recorded at install)"


def model_line(config_path: str | None) -> str:
    """The model's path and SHA-256, against the config's pin. An explicit config that cannot be
    read raises; the default one (or none) only makes the line say so."""
    from companion.model_file import sha256_file

    pinned: str | None = None
    source = "shipped model"
    if config_path is not None or DEFAULT_CONFIG.is_file():
        from companion.config import load_config

        path = config_path if config_path is not None else str(DEFAULT_CONFIG)
        try:
            policy = load_config(path).policy
        except CompanionError as exc:
            if config_path is not None:
                raise
            return f"model unknown: {exc}"
        model, pinned, source = policy.model_path, policy.sha256, f"config {path}"
    elif SHIPPED_MODEL.is_file():
        model = SHIPPED_MODEL
    else:
        return "model unknown (give --config FILE)"
    if not model.is_file():
        return f"model {model}: missing ({source})"
    digest = sha256_file(model)
    if pinned is None:
        suffix = "" if config_path is None and source == "shipped model" else ", not pinned"
        return f"model {model} sha256 {digest} ({source}{suffix})"
    verdict = "matches the pin" if pinned == digest else f"DIFFERS from the pin {pinned}"
    return f"model {model} sha256 {digest} ({source}: {verdict})"


def version_text(config_path: str | None = None) -> str:
    return "\n".join((f"companion {__version__}", commit_line(), model_line(config_path)))


def record_build_info(repo: Path = PACKAGE_DIR.parent) -> Path:
    """Write `repo`'s commit into this package's folder (before a non-editable install; `repo`
    differs when the package is built from a copy of the checkout)."""
    commit = git_commit(repo)
    if commit is None:
        raise CompanionError(f"{repo} is not a git checkout: no commit to record")
    BUILD_INFO.write_text(
        f'"""Written by python -m companion.version --record."""\n\nCOMMIT = "{commit}"\n'
    )
    return BUILD_INFO


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m companion.version", description=__doc__)
    parser.add_argument("--record", action="store_true", help="write companion/_build_info.py")
    parser.add_argument("--repo", default=str(PACKAGE_DIR.parent), help="the git checkout")
    args = parser.parse_args()
    if args.record:
        path = record_build_info(Path(args.repo))
        print(f"recorded {git_commit(Path(args.repo))} in {path}")
    else:
        print(version_text())


if __name__ == "__main__":
    main()
