"""Exception hierarchy of the companion package: library code raises these, CLIs print them."""


class CompanionError(Exception):
    """Base class of every error raised on purpose by `companion`."""


class ConfigError(CompanionError, ValueError):
    """A configuration value is missing, of the wrong type or out of range.

    The message always names the field and the allowed range.
    """


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
