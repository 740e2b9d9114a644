"""One position fix of a target as its source gives it: the source's own time, geodetic."""

from dataclasses import dataclass

__all__ = ["Fix"]


@dataclass(frozen=True)
class Fix:
    """A target's position fix as a source sent it, before any check."""

    system_id: int
    """MAVLink system id of the sender (0 for a file without one)."""
    source_s: float
    """The source's own time of the fix (time since boot, a GPS or a file's time) [s]."""
    lat_deg: float
    """Latitude [deg]."""
    lon_deg: float
    """Longitude [deg]."""
    velocity_ne_m_s: tuple[float, float] | None = None
    """Velocity (North, East) if the source sends one [m/s]."""
    message: str = ""
    """What carried it: "GLOBAL_POSITION_INT", "FOLLOW_TARGET", "csv", ..."""
