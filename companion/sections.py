"""Building frozen config-section dataclasses from parsed TOML/JSON tables, refusing unknown keys.

Each section dataclass validates its values in `__post_init__` (messages name `section.field` and
the allowed range); this module adds what is common to all of them: the table must be a mapping,
every key must be a field, required fields must be present, and every problem is reported at
once, not only the first.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from typing import Any, ClassVar, Protocol, TypeVar

from companion.errors import ConfigError, problems_error, problems_of


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


def _required(f: dataclasses.Field[Any]) -> bool:
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _field_named(section: str, message: str) -> str | None:
    """The field a `section.field...: ...` message names, if it names one of `section`."""
    match = re.match(rf"{re.escape(section)}\.([A-Za-z_][A-Za-z0-9_]*)", message)
    return match.group(1) if match else None


def build_collecting(
    cls: type[T], section: str, kwargs: Mapping[str, Any], problems: list[str]
) -> T | None:
    """`cls(**kwargs)`, or None after appending every field's problem to `problems`.

    A section validates in `__post_init__` and stops at its first bad field. To report them all,
    the field a problem names gets its default and the section is built again, until it builds
    or a problem names no field that has a default.
    """
    table = dict(kwargs)
    defaults = {f.name for f in dataclasses.fields(cls) if f.init and not _required(f)}
    found: list[str] = []
    while True:
        try:
            built = cls(**table)
        except ConfigError as exc:
            found.extend(problems_of(exc))
            name = _field_named(section, str(exc))
            if name is None or name not in defaults or name not in table:
                break
            del table[name]  # checked with its default from now on
            continue
        if not found:
            return built
        break
    problems.extend(found)
    return None


def section_from_dict(cls: type[T], section: str, data: object, **overrides: Any) -> T:
    """`cls(**data)` after checking the table's keys against `cls`'s init fields.

    `overrides` replace (already converted) values, e.g. a tuple built from a TOML list. Every
    problem of the section is reported at once (`ConfigErrors` when there are several).
    """
    table = dict(require_table(section, data))
    fields = dataclasses.fields(cls)
    allowed = tuple(f.name for f in fields if f.init)
    problems: list[str] = []
    try:
        check_keys(section, table, allowed)
    except ConfigError as exc:
        problems.append(str(exc))
        table = {k: v for k, v in table.items() if k in allowed}
    missing = [
        f.name
        for f in fields
        if f.init and _required(f) and f.name not in table and f.name not in overrides
    ]
    problems += [f"{section}.{name}: missing (required)" for name in missing]
    if not missing:
        table.update(overrides)
        built = build_collecting(cls, section, table, problems)
        if built is not None and not problems:
            return built
    raise problems_error(problems)


def require_bool(field: str, value: object) -> bool:
    """Return `value` if it is a bool (not an int), else raise naming the field."""
    if not isinstance(value, bool):
        raise ConfigError(f"{field}: expected true or false, got {value!r}")
    return value
