"""Exception hierarchy of the simulation harness; the CLI turns these into one clear line."""

from companion.errors import CompanionError, ConfigError


class SimError(CompanionError):
    """Base class of every error raised on purpose by `sim_harness`."""


class ControllerError(SimError):
    """A controller returned commands of the wrong shape or non-finite values."""


class DatasetError(SimError):
    """A dataset on disk is missing, incomplete, corrupted or was made with other parameters."""


__all__ = ["ConfigError", "ControllerError", "DatasetError", "SimError"]
