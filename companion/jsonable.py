"""Turning log and telemetry payloads into strict JSON (no NaN literals, no numpy types).

NaN and infinities become `null` (strict JSON has no NaN), numpy arrays become nested lists,
numpy scalars Python numbers, paths strings, tuples lists; mapping keys must be strings.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any

import numpy as np


def to_jsonable(value: Any) -> Any:
    """A JSON-serializable copy of `value` (see the module docstring); TypeError if impossible."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        if value.dtype.kind == "f":
            return to_jsonable(value.tolist())
        return value.tolist()
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise TypeError(f"JSON object keys must be strings, got {key!r}")
            out[key] = to_jsonable(item)
        return out
    if isinstance(value, list | tuple):
        return [to_jsonable(item) for item in value]
    if isinstance(value, PurePath):
        return str(value)
    raise TypeError(f"cannot encode {type(value).__name__} as JSON")


def dumps(value: Any) -> bytes:
    """Compact strict-JSON UTF-8 bytes of `value` after `to_jsonable`."""
    text = json.dumps(to_jsonable(value), separators=(",", ":"), allow_nan=False)
    return text.encode("utf-8")
