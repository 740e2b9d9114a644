"""`fleetmpc real-autopilots`: how it starts each autopilot and how it judges a run (the
autopilots themselves are built by their own projects, so no test here starts one)."""

import argparse
from pathlib import Path

import pytest

from fleetmpc.cli import main
from fleetmpc.launch.home import vehicle_home
from fleetmpc.launch.real_autopilots import Autopilot, judge, measurements
from fleetmpc.scenario import load_scenario

PAPER = load_scenario("scenarios/paper.toml")


def test_a_px4_instance_serves_its_vehicle_where_the_vehicle_starts(tmp_path):
    home = vehicle_home(PAPER, 2)
    ap = Autopilot("px4", home)
    argv, env = ap.command(argparse.Namespace(px4=str(tmp_path / "build")), tmp_path)
    assert argv[1:3] == ["-i", "1"] and argv[0].endswith("build/bin/px4")
    assert argv[3:] == ["-d", str(tmp_path / "build" / "etc")]
    assert env["PX4_SIM_MODEL"] == "sihsim_quadx"
    assert env["PX4_HOME_LON"] == f"{home.lon_deg:.7f}"
    assert ap.url == "udpin:127.0.0.1:14541"  # PX4 instance 1's offboard link


def test_an_arducopter_instance_takes_its_system_id_from_a_second_defaults_file(tmp_path):
    home = vehicle_home(PAPER, 2)
    paths = argparse.Namespace(arducopter="arducopter", arducopter_defaults="copter.parm")
    argv, _ = Autopilot("arducopter", home).command(paths, tmp_path)
    assert argv[argv.index("-I") + 1] == "1"
    assert argv[argv.index("--home") + 1] == home.ardupilot_home()
    assert argv[argv.index("--defaults") + 1].endswith(f"copter.parm,{tmp_path}/sysid.parm")
    assert (tmp_path / "sysid.parm").read_text() == "MAV_SYSID 2\n"
    assert Autopilot("arducopter", home).url == "tcp:127.0.0.1:5770"


def test_the_mixed_fleet_is_flown_only_with_an_arducopter():
    names = [m.name for m in measurements(Path("scenarios"), arducopter=False)]
    assert names == ["vehicle 2 on PX4", "all on PX4", "agent 2 frozen 3 s, PX4"]
    with_copter = measurements(Path("scenarios"), arducopter=True)
    assert with_copter[2].autopilots == {1: "px4", 2: "arducopter"}


def test_a_run_is_judged_on_every_pair_the_centre_and_d_safe():
    metrics = {
        "separation_pairs": [[1, 2], [1, 3], [2, 3]],
        "separation_error_m": [0.14, 0.02, 0.31],
        "centre_distance_error_m": 0.12,
        "min_separation_m": 9.1,
    }
    assert judge(metrics, 2.0) == ["pair 2-3 0.310 m", "centre 0.120 m"]
    metrics.update(separation_error_m=[0.1, 0.1, 0.1], centre_distance_error_m=0.05)
    assert judge(metrics, 2.0) == []
    assert judge(metrics, 9.5) == ["min separation 9.10 m < d_safe"]


def test_missing_builds_are_named(capsys, tmp_path):
    assert main(["real-autopilots", "--px4", str(tmp_path)]) == 2
    assert "--px4" in capsys.readouterr().err
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "px4").write_text("")
    assert main(["real-autopilots", "--px4", str(tmp_path), "--arducopter", "x"]) == 2
    assert "--arducopter-defaults" in capsys.readouterr().err


@pytest.mark.parametrize("runs", ["0"])
def test_runs_must_be_positive(capsys, tmp_path, runs):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "px4").write_text("")
    assert main(["real-autopilots", "--px4", str(tmp_path), "--runs", runs]) == 2
    assert "--runs" in capsys.readouterr().err
