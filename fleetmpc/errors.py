"""Exception tree shared by the fleetmpc packages."""

__all__ = ["ConfigError", "FleetMpcError", "InfeasibleError"]


class FleetMpcError(Exception):
    """Base class of every error fleetmpc raises on purpose."""


class ConfigError(FleetMpcError, ValueError):
    """A configuration value is missing, malformed or out of range.

    The message starts with the name of the offending field.
    """

    def __init__(self, field: str, message: str) -> None:
        self.field = field
        super().__init__(f"{field}: {message}")


class InfeasibleError(ConfigError):
    """The configuration leaves the controller no feasible input (e.g. an empty tightened set)."""
