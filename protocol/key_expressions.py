"""Zenoh key expressions of a fleet, and their parser.

Every key lives under ``fleetmpc/<fleet>/``:

- ``fleetmpc/<fleet>/uav/<id>/plan``: a vehicle's assumed trajectory (PlanMessage);
- ``fleetmpc/<fleet>/uav/<id>/status``: a vehicle's status (StatusMessage);
- ``fleetmpc/<fleet>/target/observation``: an observation of the target (TargetObservation);
- ``fleetmpc/<fleet>/epoch``: when fleet time 0 is, announced by the ground station (FleetEpoch).

``<fleet>`` is 1..64 characters of ``[A-Za-z0-9_-]`` (no key-expression wildcards or separators);
``<id>`` is the vehicle's MAVLink system id 1..250, in decimal without leading zeros.
"""

import re
from dataclasses import dataclass

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.protocol.messages import MAX_SENDER_ID, MIN_SENDER_ID, MessageKind

__all__ = [
    "KeyFormatError",
    "ParsedKey",
    "all_plans_key",
    "all_statuses_key",
    "epoch_key",
    "fleet_key",
    "parse_key",
    "plan_key",
    "status_key",
    "target_observation_key",
    "validate_fleet",
]

ROOT = "fleetmpc"
_FLEET_RE = re.compile(r"[A-Za-z0-9_-]{1,64}")
_ID_RE = re.compile(r"[1-9][0-9]{0,2}")


class KeyFormatError(FleetMpcError, ValueError):
    """A key expression is not one of the fleet's keys."""


@dataclass(frozen=True)
class ParsedKey:
    """What a fleet key names."""

    fleet: str
    """Fleet name."""
    kind: MessageKind
    """The message kind the key carries."""
    vehicle_id: int | None
    """Vehicle system id for per-vehicle keys; None for the fleet-wide keys."""


def validate_fleet(fleet: str, *, field: str = "fleet") -> str:
    """Return `fleet` if it is a valid fleet name, else raise ConfigError naming `field`."""
    if not isinstance(fleet, str) or not _FLEET_RE.fullmatch(fleet):
        raise ConfigError(field, f"must be 1..64 characters of [A-Za-z0-9_-], got {fleet!r}")
    return fleet


def _vehicle(vehicle_id: int) -> int:
    if (
        isinstance(vehicle_id, bool)
        or not isinstance(vehicle_id, int)
        or not MIN_SENDER_ID <= vehicle_id <= MAX_SENDER_ID
    ):
        raise ConfigError(
            "vehicle_id",
            f"must be an integer in [{MIN_SENDER_ID}, {MAX_SENDER_ID}], got {vehicle_id!r}",
        )
    return vehicle_id


def fleet_key(fleet: str) -> str:
    """Every key of the fleet: ``fleetmpc/<fleet>/**``."""
    return f"{ROOT}/{validate_fleet(fleet)}/**"


def plan_key(fleet: str, vehicle_id: int) -> str:
    """Key of a vehicle's plans: ``fleetmpc/<fleet>/uav/<id>/plan``."""
    return f"{ROOT}/{validate_fleet(fleet)}/uav/{_vehicle(vehicle_id)}/plan"


def status_key(fleet: str, vehicle_id: int) -> str:
    """Key of a vehicle's status: ``fleetmpc/<fleet>/uav/<id>/status``."""
    return f"{ROOT}/{validate_fleet(fleet)}/uav/{_vehicle(vehicle_id)}/status"


def target_observation_key(fleet: str) -> str:
    """Key of target observations: ``fleetmpc/<fleet>/target/observation``."""
    return f"{ROOT}/{validate_fleet(fleet)}/target/observation"


def epoch_key(fleet: str) -> str:
    """Key of the fleet's epoch announcements: ``fleetmpc/<fleet>/epoch``."""
    return f"{ROOT}/{validate_fleet(fleet)}/epoch"


def all_plans_key(fleet: str) -> str:
    """Subscription to every vehicle's plans: ``fleetmpc/<fleet>/uav/*/plan``."""
    return f"{ROOT}/{validate_fleet(fleet)}/uav/*/plan"


def all_statuses_key(fleet: str) -> str:
    """Subscription to every vehicle's status: ``fleetmpc/<fleet>/uav/*/status``."""
    return f"{ROOT}/{validate_fleet(fleet)}/uav/*/status"


def parse_key(key: str) -> ParsedKey:
    """Parse a concrete (wildcard-free) fleet key; raise KeyFormatError if it is not one."""
    if not isinstance(key, str):
        raise KeyFormatError(f"key must be a string, got {type(key).__name__}")
    parts = key.split("/")
    if len(parts) < 2 or parts[0] != ROOT or not _FLEET_RE.fullmatch(parts[1]):
        raise KeyFormatError(f"not a fleetmpc key: {key!r}")
    fleet, rest = parts[1], parts[2:]
    if rest == ["target", "observation"]:
        return ParsedKey(fleet, MessageKind.TARGET_OBSERVATION, None)
    if rest == ["epoch"]:
        return ParsedKey(fleet, MessageKind.FLEET_EPOCH, None)
    if len(rest) == 3 and rest[0] == "uav" and rest[2] in ("plan", "status"):
        if not _ID_RE.fullmatch(rest[1]) or not MIN_SENDER_ID <= int(rest[1]) <= MAX_SENDER_ID:
            raise KeyFormatError(f"bad vehicle id {rest[1]!r} in key {key!r}")
        kind = MessageKind.PLAN if rest[2] == "plan" else MessageKind.STATUS
        return ParsedKey(fleet, kind, int(rest[1]))
    raise KeyFormatError(f"unknown fleetmpc key: {key!r}")
