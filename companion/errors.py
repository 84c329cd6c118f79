"""Exception hierarchy of the companion package: library code raises these, CLIs print them."""

from collections.abc import Sequence


class CompanionError(Exception):
    """Base class of every error raised on purpose by `companion`."""


class ConfigError(CompanionError, ValueError):
    """A configuration value is missing, of the wrong type or out of range.

    The message always names the field and the allowed range.
    """


class ConfigErrors(ConfigError):
    """Several configuration problems found at once; `problems` holds each one's message.

    Raised so that a user fixes a config in one pass: each message names its field and range.
    """

    def __init__(self, problems: Sequence[str], where: str | None = None) -> None:
        prefix = "" if where is None else f"{where}: "
        self.problems = tuple(prefix + p for p in problems)  # each a complete message
        super().__init__(f"{prefix}{len(problems)} problems: " + "; ".join(problems))


def problems_of(exc: ConfigError) -> tuple[str, ...]:
    """The messages of a `ConfigErrors`, or the one message of any other `ConfigError`."""
    return exc.problems if isinstance(exc, ConfigErrors) else (str(exc),)


def problems_error(problems: Sequence[str], where: str | None = None) -> ConfigError:
    """The error to raise for these problems: `ConfigError` for one, `ConfigErrors` for more.

    `where` (e.g. the config file) prefixes each message."""
    if len(problems) == 1:
        return ConfigError(problems[0] if where is None else f"{where}: {problems[0]}")
    return ConfigErrors(problems, where)


class ModelError(CompanionError):
    """A model file is missing, corrupted, does not match its recorded hash or its metadata."""


class AutopilotError(CompanionError):
    """The autopilot link failed, timed out, or refused a command (the message says which)."""


class OffboardLostError(AutopilotError):
    """The vehicle left OFFBOARD while we were commanding it (pilot switch or PX4 failsafe)."""


class RecorderError(CompanionError):
    """The flight recorder cannot write its files."""


class TelemetryError(CompanionError):
    """The telemetry session cannot be opened (e.g. an endpoint's port is taken)."""
