"""What a figure was measured on, for every report and benchmark that saves figures.

The CNN's flights repeat exactly on one machine but not across machines: another CPU's kernels
(or another install's libraries) round differently, about 1e-6 m/s, and a flock amplifies that
(round 45's opposing seed 1012: closest pair 1.37 m in one session, 1.34 m in a later one, the
same file, code and torch). Timings differ more still. So each saved figure says where it was
measured: the CPU model, its core count, the platform and the numeric libraries' versions.
"""

from __future__ import annotations

import contextlib
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), else what `platform` knows."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def machine(**extra: Any) -> dict[str, Any]:
    """The machine and libraries: cpu, cpus, platform, python, numpy, torch (None where not
    installed), plus whatever the caller measured about it (`extra`, e.g. load averages)."""
    return {
        "cpu": cpu_model(),
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": _version("numpy"),
        "torch": _version("torch"),
        **extra,
    }
