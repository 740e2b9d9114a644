"""`fleetmpc home`: a real SITL booted where it prints starts at its vehicle's start."""

import math

import pytest

from fleetmpc.cli import main
from fleetmpc.errors import ConfigError
from fleetmpc.launch.home import vehicle_home
from fleetmpc.protocol.local_frame import ned_from_geodetic
from fleetmpc.scenario import load_scenario


def test_each_vehicle_home_projects_back_onto_its_start():
    scenario = load_scenario("scenarios/paper.toml")
    site = scenario.site
    for v in scenario.vehicles:
        home = vehicle_home(scenario, v.id)
        north, east = ned_from_geodetic(
            home.lat_deg,
            home.lon_deg,
            home_lat_deg=site.home_lat_deg,
            home_lon_deg=site.home_lon_deg,
        )
        assert north == pytest.approx(v.initial[0], abs=1e-3)
        assert east == pytest.approx(v.initial[1], abs=1e-3)
        assert home.alt_m == site.home_alt_m
        assert home.heading_deg == pytest.approx(math.degrees(v.initial[2]) % 360.0)


def test_the_printed_values_are_what_each_sitl_takes(capsys):
    assert main(["home", "scenarios/paper.toml", "--vehicle", "2"]) == 0
    out = capsys.readouterr().out
    home = vehicle_home(load_scenario("scenarios/paper.toml"), 2)
    assert f"PX4_HOME_LAT={home.lat_deg:.7f} PX4_HOME_LON={home.lon_deg:.7f}" in out
    assert f"--home {home.lat_deg:.7f},{home.lon_deg:.7f},488,0" in out
    assert "vehicle 1" not in out


def test_an_unknown_vehicle_is_named():
    with pytest.raises(ConfigError, match=r"no vehicle with id 7 .*\(1, 2, 3\)"):
        vehicle_home(load_scenario("scenarios/paper.toml"), 7)
