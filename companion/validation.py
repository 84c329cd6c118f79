"""Small validators that turn bad configuration values into a `ConfigError` naming the field."""

from __future__ import annotations

import math
from collections.abc import Sequence

from companion.errors import ConfigError


def require_finite(field: str, value: float) -> float:
    """Return `value` as float, or raise if it is not a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{field}: expected a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ConfigError(f"{field}: must be finite, got {value!r}")
    return number


def require_range(
    field: str,
    value: float,
    low: float | None = None,
    high: float | None = None,
    *,
    low_inclusive: bool = True,
    high_inclusive: bool = True,
) -> float:
    """Return `value` if `low <= value <= high` (bounds optional, inclusivity per side)."""
    number = require_finite(field, value)
    too_low = low is not None and (number < low if low_inclusive else number <= low)
    too_high = high is not None and (number > high if high_inclusive else number >= high)
    if too_low or too_high:
        left = "-inf" if low is None else f"{low:g}"
        right = "inf" if high is None else f"{high:g}"
        lb = "[" if low_inclusive and low is not None else "("
        rb = "]" if high_inclusive and high is not None else ")"
        raise ConfigError(
            f"{field}: {number:g} is outside the allowed range {lb}{left}, {right}{rb}"
        )
    return number


def require_positive(field: str, value: float) -> float:
    """Return `value` if it is a finite number > 0."""
    return require_range(field, value, 0.0, None, low_inclusive=False)


def require_non_negative(field: str, value: float) -> float:
    """Return `value` if it is a finite number >= 0."""
    return require_range(field, value, 0.0, None)


def require_int_range(field: str, value: int, low: int, high: int | None = None) -> int:
    """Return `value` if it is an integer (not a bool) with `low <= value <= high`."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{field}: expected an integer, got {value!r}")
    if value < low or (high is not None and value > high):
        right = "inf" if high is None else str(high)
        raise ConfigError(f"{field}: {value} is outside the allowed range [{low}, {right}]")
    return value


def require_vector3(field: str, value: Sequence[float]) -> tuple[float, float, float]:
    """Return a 3-vector of finite floats, or raise naming the field."""
    try:
        items = list(value)
    except TypeError:
        raise ConfigError(f"{field}: expected 3 numbers, got {value!r}") from None
    if len(items) != 3:
        raise ConfigError(f"{field}: expected 3 numbers, got {len(items)}")
    x, y, z = (require_finite(f"{field}[{k}]", v) for k, v in enumerate(items))
    return (x, y, z)
