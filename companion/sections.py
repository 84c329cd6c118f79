"""Building frozen config-section dataclasses from parsed TOML/JSON tables, refusing unknown keys.

Each section dataclass validates its values in `__post_init__` (messages name `section.field` and
the allowed range); this module adds what is common to all of them: the table must be a mapping,
every key must be a field, and required fields must be present.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Protocol, TypeVar

from companion.errors import ConfigError


class _Dataclass(Protocol):
    __dataclass_fields__: ClassVar[dict[str, Any]]


T = TypeVar("T", bound=_Dataclass)


def require_table(section: str, data: object) -> Mapping[str, Any]:
    """Return `data` if it is a mapping with string keys, else raise naming the section."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{section}: expected a table, got {type(data).__name__}")
    for key in data:
        if not isinstance(key, str):
            raise ConfigError(f"{section}: keys must be strings, got {key!r}")
    return data


def check_keys(section: str, data: Mapping[str, Any], allowed: tuple[str, ...]) -> None:
    """Raise `ConfigError` naming every key of `data` that is not in `allowed`."""
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ConfigError(
            f"{section}: unknown key(s) {', '.join(repr(k) for k in unknown)}; "
            f"allowed keys: {', '.join(allowed)}"
        )


def section_from_dict(cls: type[T], section: str, data: object, **overrides: Any) -> T:
    """`cls(**data)` after checking the table's keys against `cls`'s init fields.

    `overrides` replace (already converted) values, e.g. a tuple built from a TOML list.
    """
    table = dict(require_table(section, data))
    fields = dataclasses.fields(cls)
    allowed = tuple(f.name for f in fields if f.init)
    check_keys(section, table, allowed)
    for f in fields:
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        if f.init and required and f.name not in table and f.name not in overrides:
            raise ConfigError(f"{section}.{f.name}: missing (required)")
    table.update(overrides)
    return cls(**table)


def require_bool(field: str, value: object) -> bool:
    """Return `value` if it is a bool (not an int), else raise naming the field."""
    if not isinstance(value, bool):
        raise ConfigError(f"{field}: expected true or false, got {value!r}")
    return value
