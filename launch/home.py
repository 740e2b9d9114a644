"""Where to boot a real autopilot's SITL so it starts where its vehicle starts: `fleetmpc home`.

    fleetmpc home scenarios/paper.toml --vehicle 2

A vehicle's start is the scenario's `[site]` home moved by the vehicle's `initial` North and East
metres (the same projection PX4 uses, `fleetmpc.protocol.local_frame`). For each vehicle this
prints its latitude, longitude, altitude and heading, and the same as the two SITLs take them:
PX4's environment (``PX4_HOME_LAT``, ``PX4_HOME_LON``, ``PX4_HOME_ALT``; PX4 stores them as
float32, about 0.4 m steps at mid latitudes) and ArduCopter's ``--home LAT,LON,ALT,HEADING``
(heading in degrees). See docs/real-autopilots.md.
"""

import argparse
import math
from dataclasses import dataclass

from fleetmpc.protocol.local_frame import geodetic_from_ned
from fleetmpc.scenario import Scenario, load_scenario

__all__ = ["VehicleHome", "add_arguments", "run", "vehicle_home"]


@dataclass(frozen=True)
class VehicleHome:
    """Where and which way a vehicle starts, on the globe."""

    vehicle_id: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    """Altitude above mean sea level [m] (the site's home altitude)."""
    heading_deg: float
    """Heading, clockwise from North, in [0, 360) [deg]."""

    def px4_environment(self) -> str:
        """The variables a PX4 SITL instance reads its home from."""
        return (
            f"PX4_HOME_LAT={self.lat_deg:.7f} PX4_HOME_LON={self.lon_deg:.7f}"
            f" PX4_HOME_ALT={self.alt_m:g}"
        )

    def ardupilot_home(self) -> str:
        """ArduPilot SITL's ``--home`` value."""
        return f"{self.lat_deg:.7f},{self.lon_deg:.7f},{self.alt_m:g},{self.heading_deg:.0f}"


def vehicle_home(scenario: Scenario, vehicle_id: int) -> VehicleHome:
    """Where vehicle `vehicle_id` of `scenario` starts; ConfigError naming the id if none."""
    v = scenario.vehicle(vehicle_id)
    site = scenario.site
    north, east, yaw = v.initial
    lat, lon = geodetic_from_ned(
        north, east, home_lat_deg=site.home_lat_deg, home_lon_deg=site.home_lon_deg
    )
    return VehicleHome(v.id, lat, lon, site.home_alt_m, math.degrees(yaw) % 360.0)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario TOML file")
    parser.add_argument(
        "--vehicle",
        type=int,
        action="append",
        metavar="ID",
        help="only this vehicle (repeatable; default: every vehicle)",
    )


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    for vid in args.vehicle or scenario.vehicle_ids:
        home = vehicle_home(scenario, vid)
        print(
            f"vehicle {vid}: {home.lat_deg:.7f} deg N, {home.lon_deg:.7f} deg E,"
            f" {home.alt_m:g} m, heading {home.heading_deg:.0f} deg"
        )
        print(f"  PX4:       {home.px4_environment()}")
        print(f"  ArduPilot: --home {home.ardupilot_home()}")
    return 0
