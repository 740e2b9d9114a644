"""Reading a recorded track: a CSV of time, latitude, longitude (optionally altitude and velocity)
or a MAVLink telemetry log (.tlog) of one system's GLOBAL_POSITION_INT or FOLLOW_TARGET.

CSV: one fix per line, ``time_s,lat_deg,lon_deg[,alt_m[,vn_m_s,ve_m_s]]``, an optional header
line naming them, ``#`` comments; the time in seconds on any origin (the track starts at its
first fix). A tlog holds many systems: the one followed is given by its system id (an error lists
those the log holds otherwise).
"""

import csv
import math
from pathlib import Path

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.local_frame import ned_from_geodetic
from fleetmpc.targets.fix import Fix
from fleetmpc.targets.track import RecordedTrack, noise_estimate

__all__ = ["load_track", "read_fixes"]

_MIN_NOISE_M = 0.05
"""An estimated noise is never taken below this [m] (a smooth, synthetic track)."""


def read_fixes(path: Path, *, system_id: int | None = None) -> list[Fix]:
    """The fixes of a CSV or .tlog file, in file order, unchecked."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError("target.file", f"no such file: {path}")
    if path.suffix.lower() == ".tlog":
        return _tlog_fixes(path, system_id)
    return _csv_fixes(path)


def _csv_fixes(path: Path) -> list[Fix]:
    fixes = []
    with path.open(newline="") as f:
        for line, row in enumerate(csv.reader(f), start=1):
            if not row or row[0].lstrip().startswith("#"):
                continue
            try:
                values = [float(x) for x in row]
            except ValueError:
                if line == 1:
                    continue  # (the header)
                raise ConfigError("target.file", f"{path}:{line}: not numbers: {row}") from None
            if len(values) not in (3, 4, 6):
                raise ConfigError(
                    "target.file",
                    f"{path}:{line}: expected time,lat,lon[,alt[,vn,ve]], got {len(values)} fields",
                )
            velocity = (values[4], values[5]) if len(values) == 6 else None
            fixes.append(Fix(0, values[0], values[1], values[2], velocity, "csv"))
    return fixes


def _tlog_fixes(path: Path, system_id: int | None) -> list[Fix]:
    from pymavlink import mavutil

    from fleetmpc.targets.mavlink_source import fix_of_message

    log = mavutil.mavlink_connection(str(path), robust_parsing=True)
    fixes, systems = [], set()
    try:
        while (msg := log.recv_match(type=["GLOBAL_POSITION_INT", "FOLLOW_TARGET"])) is not None:
            systems.add(msg.get_srcSystem())
            if system_id is None or msg.get_srcSystem() == system_id:
                fixes.append(fix_of_message(msg))
    finally:
        log.close()
    if system_id is None and len(systems) > 1:
        raise ConfigError(
            "target.system_id", f"{path} holds systems {sorted(systems)}: give the one to follow"
        )
    if not fixes:
        raise ConfigError(
            "target.system_id",
            f"{path}: no positions of system {system_id} (holds {sorted(systems)})",
        )
    return fixes


def load_track(
    path: Path,
    *,
    home_lat_deg: float,
    home_lon_deg: float,
    system_id: int | None = None,
    noise_m: float | None = None,
) -> RecordedTrack:
    """A recorded track about home: its fixes in the local frame; fixes that are not numbers,
    or that repeat or go back in time, are an error naming their line."""
    fixes = read_fixes(path, system_id=system_id)
    for k, f in enumerate(fixes):
        if not all(map(math.isfinite, (f.source_s, f.lat_deg, f.lon_deg))):
            raise ConfigError("target.file", f"{path}: fix {k} is not a number: {f}")
    ne = np.array(
        [
            ned_from_geodetic(
                f.lat_deg, f.lon_deg, home_lat_deg=home_lat_deg, home_lon_deg=home_lon_deg
            )
            for f in fixes
        ]
    )
    velocities = None
    if fixes and all(f.velocity_ne_m_s is not None for f in fixes):
        velocities = np.array([f.velocity_ne_m_s for f in fixes])
    noise = max(noise_estimate(ne), _MIN_NOISE_M) if noise_m is None else noise_m
    return RecordedTrack(
        times_s=np.array([f.source_s for f in fixes]),
        positions_m=ne,
        velocities_m_s=velocities,
        observation_noise_m=noise,
        file=str(path),
    )
