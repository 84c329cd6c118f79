"""The policy a pool worker flies: loaded once per process, from the driver's file or its bytes.

A local pool's workers read the policy file the driver names (same machine). A cluster's workers
may not see that file: the driver ships the file and its sidecar (`PolicySource.read(path,
embed=True)`, about 1.3 MB, shared once through the pool), and each worker writes them to a
private temporary folder and loads them from there, checking the SHA-256 the driver read. Either
way the policy is loaded as `load_policy` does (one torch thread, unfused): a seed gives the same
flight in any worker, on any machine.
"""

from __future__ import annotations

import atexit
import hashlib
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from companion.model_file import sidecar_path
from companion.policy import Policy
from sim_harness.experiments.vision_controller import load_policy

_LOADED: dict[str, Policy] = {}  # by SHA-256: the policies this process has loaded


@dataclass(frozen=True)
class PolicySource:
    """Where a worker finds the policy: `path` on this machine, or the files' bytes by name."""

    path: Path
    sha256: str
    files: tuple[tuple[str, bytes], ...] = ()  # (file name, bytes): the .pt and its sidecar

    @classmethod
    def read(cls, path: Path, embed: bool) -> PolicySource:
        """The source of the policy at `path`; `embed` carries its files' bytes along."""
        data = Path(path).read_bytes()
        sha = hashlib.sha256(data).hexdigest()
        if not embed:
            return cls(Path(path), sha)
        sidecar = sidecar_path(path)
        files = [(Path(path).name, data)]
        if sidecar.exists():
            files.append((sidecar.name, sidecar.read_bytes()))
        return cls(Path(path), sha, tuple(files))


def adopt(policy: Policy) -> None:
    """Let tasks run in this process use a policy it has already loaded (the one-worker pool)."""
    _LOADED[policy.sha256] = policy


def release(policy: Policy) -> None:
    """Forget an adopted policy (its owner closes it)."""
    if _LOADED.get(policy.sha256) is policy:
        del _LOADED[policy.sha256]


def worker_policy(source: PolicySource) -> Policy:
    """This process's policy for `source`, loaded on first use and kept for later tasks."""
    policy = _LOADED.get(source.sha256)
    if policy is not None:
        return policy
    path = source.path
    if source.files:
        folder = Path(tempfile.mkdtemp(prefix=f"policy-{source.sha256[:12]}-"))
        atexit.register(shutil.rmtree, folder, True)
        for name, data in source.files:
            (folder / name).write_bytes(data)
        path = folder / source.files[0][0]
    policy = load_policy(path, threads=1, sha256=source.sha256)
    _LOADED[source.sha256] = policy
    return policy
