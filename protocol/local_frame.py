"""The local NED frame's geometry: headings, and where a local point is on the Earth.

Headings are wrapped to (-pi, pi]; a local North/East point maps to latitude/longitude about the
home position by the azimuthal equidistant projection PX4 uses, and back.
"""

import math

__all__ = [
    "EARTH_RADIUS_M",
    "geodetic_from_ned",
    "ned_from_geodetic",
    "quaternion_yaw",
    "wrap_pi",
    "yaw_quaternion",
]


def wrap_pi(angle_rad: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


def yaw_quaternion(yaw_rad: float) -> list[float]:
    """The attitude quaternion (w, x, y, z) of a level vehicle heading `yaw_rad`."""
    half = 0.5 * yaw_rad
    return [math.cos(half), 0.0, 0.0, math.sin(half)]


def quaternion_yaw(w: float, x: float, y: float, z: float) -> float:
    """The heading (yaw, ZYX Euler angles) of the attitude quaternion (w, x, y, z)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


EARTH_RADIUS_M = 6_371_000.0
"""Mean Earth radius used by PX4's map projection [m]."""


def geodetic_from_ned(
    north_m: float, east_m: float, *, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """(lat_deg, lon_deg) of a local NED point: azimuthal equidistant projection, as PX4 does."""
    x, y = north_m / EARTH_RADIUS_M, east_m / EARTH_RADIUS_M
    lat0, lon0 = math.radians(home_lat_deg), math.radians(home_lon_deg)
    c = math.hypot(x, y)
    if c == 0.0:
        return home_lat_deg, home_lon_deg
    sin_c, cos_c = math.sin(c), math.cos(c)
    lat = math.asin(cos_c * math.sin(lat0) + x * sin_c * math.cos(lat0) / c)
    lon = lon0 + math.atan2(y * sin_c, c * math.cos(lat0) * cos_c - x * math.sin(lat0) * sin_c)
    return math.degrees(lat), math.degrees(wrap_pi(lon))


def ned_from_geodetic(
    lat_deg: float, lon_deg: float, *, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """(north_m, east_m) of a geodetic point: inverse of `geodetic_from_ned`."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    lat0, lon0 = math.radians(home_lat_deg), math.radians(home_lon_deg)
    cos_dlon = math.cos(lon - lon0)
    arg = min(
        max(math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * cos_dlon, -1), 1
    )
    c = math.acos(arg)
    k = 1.0 if abs(c) < 1e-12 else c / math.sin(c)
    north = k * (math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * cos_dlon)
    east = k * math.cos(lat) * math.sin(lon - lon0)
    return north * EARTH_RADIUS_M, east * EARTH_RADIUS_M
