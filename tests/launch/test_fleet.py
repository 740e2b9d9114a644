"""The fleet's process list: derived from the scenario, the same for `up` and compose."""

import argparse
from pathlib import Path

import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.gcs import ground_station
from fleetmpc.gcs.ground_station import SERIES_FLUSH_S, series_every
from fleetmpc.gcs.telemetry import FLUSH_S
from fleetmpc.launch import up
from fleetmpc.launch.fleet import FleetOptions, auto_vehicles_per_sitl, fleet_processes
from fleetmpc.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


def _arg(argv: tuple[str, ...], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def test_every_process_of_a_five_vehicle_fleet() -> None:
    sc = load_scenario(ROOT / "scenarios" / "wedge-circle.toml")
    procs = fleet_processes(sc, FleetOptions(scenario_path="s.toml", speed=4.0, rrd="r.rrd"))
    names = [p.name for p in procs]
    ids = sc.vehicle_ids
    assert names == [
        "zenoh-router",
        "target",
        *(f"sitl-{i}" for i in ids),
        *(f"agent-{i}" for i in ids),
        "gcs",
    ]
    by_name = {p.name: p for p in procs}
    router = f"{sc.network.host}:{sc.network.zenoh_port}"
    assert _arg(by_name["zenoh-router"].argv, "--port") == str(sc.network.zenoh_port)
    for p in procs[1:]:
        assert p.argv[0] == p.role and _arg(p.argv, "--scenario") == "s.toml"
        assert _arg(p.argv, "--speed") == "4"
        if p.role != "sitl":
            assert _arg(p.argv, "--zenoh-connect") == router
            assert _arg(p.argv, "--fleet") == sc.name
    for i in ids:
        assert _arg(by_name[f"sitl-{i}"].argv, "--vehicle") == str(i)
        agent = by_name[f"agent-{i}"].argv
        assert _arg(agent, "--vehicle") == str(i) and "--wait-epoch" in agent
        assert "--epoch-ns" not in agent
    gcs = by_name["gcs"].argv
    assert _arg(gcs, "--duration") == f"{sc.duration_s:g}" and _arg(gcs, "--rrd") == "r.rrd"
    assert "--metrics" not in gcs and _arg(gcs, "--viewer") == "none"


def test_options_reach_the_processes(paper) -> None:
    opts = FleetOptions(
        scenario_path="/app/paper.toml",
        duration_s=12.5,
        fleet="blue",
        metrics="/out/m.json",
        status_file="/out/s.json",
        agent_records_dir="/out",
    )
    by_name = {p.name: p.argv for p in fleet_processes(paper, opts)}
    assert _arg(by_name["gcs"], "--duration") == "12.5"
    assert _arg(by_name["gcs"], "--metrics") == "/out/m.json"
    assert _arg(by_name["gcs"], "--status-file") == "/out/s.json"
    assert _arg(by_name["target"], "--duration") == "13.5"
    assert _arg(by_name["agent-2"], "--record") == "/out/agent-2.jsonl"
    assert all(
        _arg(argv, "--fleet") == "blue"
        for name, argv in by_name.items()
        if name not in ("zenoh-router",) and not name.startswith("sitl")
    )


def _up_args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    up.add_arguments(parser)
    return parser.parse_args(["paper.toml", *argv])


def _gcs_args(options: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    ground_station.add_arguments(parser)
    return parser.parse_args(["--scenario", "paper.toml", *options])


def test_up_hands_its_flush_intervals_to_the_ground_station() -> None:
    default = _gcs_args(up._gcs_options(_up_args()))
    assert (default.flush_s, default.series_flush_s) == (FLUSH_S, SERIES_FLUSH_S) == (4.0, 4.0)
    given = _gcs_args(up._gcs_options(_up_args("--flush-s", "0.7", "--series-flush-s", "2.8")))
    assert (given.flush_s, given.series_flush_s) == (0.7, 2.8)
    assert series_every(flush_s=given.flush_s, series_flush_s=given.series_flush_s) == 4
    for bad in ("0", "-1", "nan", "inf"):
        with pytest.raises(ConfigError, match="--series-flush-s"):
            up._gcs_options(_up_args("--series-flush-s", bad))


def test_an_external_autopilot_replaces_its_vehicles_sitl():
    sc = load_scenario(ROOT / "scenarios" / "paper.toml")
    opts = FleetOptions(scenario_path="s.toml", external_autopilots={2: "tcp:127.0.0.1:5770"})
    procs = {p.name: p for p in fleet_processes(sc, opts)}
    assert "sitl-2" not in procs and {"sitl-1", "sitl-3"} <= set(procs)
    argv = procs["agent-2"].argv
    assert argv[argv.index("--mavlink") + 1] == "tcp:127.0.0.1:5770"
    assert "--mavlink" not in procs["agent-1"].argv


def test_secrets_reach_each_process_by_path_and_an_external_autopilot_stays_unsigned():
    sc = load_scenario(ROOT / "scenarios" / "paper.toml")
    opts = FleetOptions(
        scenario_path="s.toml", external_autopilots={2: "tcp:127.0.0.1:5770"}, secrets_dir="/s"
    )
    procs = {p.name: p for p in fleet_processes(sc, opts)}

    def arg(name: str, flag: str) -> list[str]:
        argv = procs[name].argv
        return [argv[i + 1] for i, a in enumerate(argv) if a == flag]

    assert arg("zenoh-router", "--security") == ["/s"]
    assert arg("agent-1", "--zenoh-config") == ["/s/zenoh-agent-1.json5"]
    assert arg("target", "--zenoh-config") == ["/s/zenoh-target.json5"]
    assert arg("agent-1", "--mavlink-key") == arg("sitl-1", "--mavlink-key") == ["/s/mavlink-1.key"]
    assert arg("agent-2", "--mavlink-key") == [], "the external autopilot's link is its owner's"
    assert arg("gcs", "--mavlink-key") == ["1=/s/mavlink-1.key", "3=/s/mavlink-3.key"]
    assert not any("--zenoh-connect" in p.argv for p in procs.values() if p.role != "router")


def test_vehicles_share_sitl_processes_of_at_most_k_each_with_its_own_key():
    sc = load_scenario(ROOT / "scenarios" / "wedge-circle.toml")  # five vehicles, one host
    opts = FleetOptions(scenario_path="s.toml", secrets_dir="/s", vehicles_per_sitl=2)
    sitls = [p for p in fleet_processes(sc, opts) if p.role == "sitl"]
    ids = sc.vehicle_ids
    assert [p.name for p in sitls] == [
        f"sitl-{ids[0]}..{ids[1]}",
        f"sitl-{ids[2]}..{ids[3]}",
        f"sitl-{ids[4]}",
    ]
    argv = sitls[0].argv
    vehicles = [argv[i + 1] for i, a in enumerate(argv) if a == "--vehicle"]
    keys = [argv[i + 1] for i, a in enumerate(argv) if a == "--mavlink-key"]
    assert vehicles == [str(ids[0]), str(ids[1])]
    assert keys == [f"/s/mavlink-{ids[0]}.key", f"/s/mavlink-{ids[1]}.key"]
    with pytest.raises(ConfigError, match="vehicles_per_sitl"):
        FleetOptions(scenario_path="s.toml", vehicles_per_sitl=0)


@pytest.mark.parametrize(
    ("vehicles", "speed", "per_sitl"),
    [(3, 1.0, 1), (12, 1.0, 1), (3, 4.0, 1), (13, 1.0, 25), (10, 4.0, 25), (4, 4.0, 25)],
)
def test_a_launch_groups_sitls_once_vehicles_times_speed_exceeds_twelve(vehicles, speed, per_sitl):
    assert auto_vehicles_per_sitl(vehicles, speed) == per_sitl


def test_up_refuses_another_fleets_secrets_naming_the_option(tmp_path):
    from fleetmpc.security.secrets import check_keys, make_keys

    paper = load_scenario(ROOT / "scenarios" / "paper.toml")
    wedge = load_scenario(ROOT / "scenarios" / "wedge-circle.toml")
    ours = make_keys(paper, tmp_path / "ours")
    assert check_keys(paper, ours) == ours
    with pytest.raises(ConfigError, match="--keys: .* made for fleet wedge-circle"):
        check_keys(paper, make_keys(wedge, tmp_path / "theirs"))
    (ours / "mavlink-2.key").unlink()
    with pytest.raises(ConfigError, match=r"--keys: .* no MAVLink key for vehicles \[2\]"):
        check_keys(paper, ours)
    with pytest.raises(ConfigError, match="--keys: cannot read"):
        check_keys(paper, tmp_path / "none")


def test_up_gives_each_agent_its_connect_and_engage_timeouts():
    """`up --connect-timeout` and `--engage-timeout` mean what they mean to `fleetmpc agent`
    (each agent's own waits); the ground station waits for the fleet that long and more."""
    from fleetmpc.onboard import cli as agent_cli

    args = _up_args("--connect-timeout", "90", "--engage-timeout", "45")
    gcs = _gcs_args(up._gcs_options(args))
    assert gcs.engage_timeout == 90 + 45 + up._ENGAGE_SLACK_S
    sc = load_scenario(ROOT / "scenarios" / "paper.toml")
    opts = FleetOptions(scenario_path="s.toml", connect_timeout_s=90.0, engage_timeout_s=45.0)
    agent = {p.name: p for p in fleet_processes(sc, opts)}["agent-2"]
    parser = argparse.ArgumentParser()
    agent_cli.add_arguments(parser)
    parsed = parser.parse_args(list(agent.argv[1:]))
    assert (parsed.connect_timeout, parsed.engage_timeout) == (90.0, 45.0)
    for bad in ("0", "nan"):
        with pytest.raises(ConfigError, match="--engage-timeout"):
            up._gcs_options(_up_args("--engage-timeout", bad))


def test_the_real_autopilot_docs_name_only_flags_the_commands_have():
    """Every `--flag` docs/real-autopilots.md names is one of `fleetmpc up`'s, `agent`'s,
    `sitl`'s, `home`'s or `real-autopilots`'s (or of the autopilots' own tools, listed)."""
    import re

    from fleetmpc.launch import home, real_autopilots
    from fleetmpc.onboard import cli as agent_cli
    from fleetmpc.sitl import cli as sitl_cli

    known: set[str] = set()
    commands = (up, agent_cli, sitl_cli, home, real_autopilots)
    for add in (command.add_arguments for command in commands):
        parser = argparse.ArgumentParser()
        add(parser)
        known |= {s for a in parser._actions for s in a.option_strings}
    theirs = {"--model", "--speedup", "--home", "--defaults", "--serial1", "--out", "--board"}
    text = (ROOT / "docs" / "real-autopilots.md").read_text()
    named = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text))
    assert named - theirs <= known, sorted(named - theirs - known)
    assert {"--connect-timeout", "--engage-timeout", "--mavlink", "--target-system"} <= named
