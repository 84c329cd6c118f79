"""Refuse an output folder that cannot be written before the work that will fill it starts.

A flight, a dataset or a training run that ends in a `PermissionError` traceback while saving has
wasted its whole run. Every `swarm-sim` command that flies, generates or trains, then writes,
calls `require_writable_dir` first: it creates the folder (and its parents) and writes a probe
file, then removes the probe and every folder it created, so a refused or later failing command
leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from sim_harness.errors import ConfigError


def require_writable_dir(path: Path, option: str = "out") -> Path:
    """Return `path` if a folder can be created there and written to; else raise `ConfigError`.

    `option` names the command-line option in the message (`out` for `--out`).
    """
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option}: {path} is a file, not a folder; choose a folder")
    created: list[Path] = []
    missing = path
    while not missing.exists() and missing != missing.parent:
        created.append(missing)
        missing = missing.parent
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-probe-", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(
            f"{option}: cannot write to the folder {path} ({reason}); choose a writable folder"
        ) from None
    finally:
        for folder in created:  # deepest first; only folders this check made, if still empty
            with contextlib.suppress(OSError):
                folder.rmdir()
    return path
