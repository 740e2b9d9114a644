import math
import tomllib
from pathlib import Path

import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.network import Network, mavlink_url
from fleetmpc.scenario import load_scenario, parse_scenario

ROOT = Path(__file__).resolve().parents[1]

BASE = {
    "name": "t",
    "vehicles": [
        {"id": 1, "initial": [0.0, 0.0, 0.0], "slot_m": [0.0, 0.0]},
        {"id": 2, "initial": [0.0, 10.0, 0.0], "slot_m": [0.0, 10.0]},
    ],
}


def _with(**changes):
    doc = {**BASE, **changes}
    return parse_scenario(doc)


def test_repository_scenarios_load():
    for name in ("paper", "paper-strict", "wedge-circle", "mixed-autopilots"):
        sc = load_scenario(f"scenarios/{name}.toml")
        assert sc.name == name
        assert sc.controller.period_ns % sc.plant_steps_per_period == 0


def test_paper_scenario_holds_the_issue_truth(paper):
    assert [v.truth.speed_effectiveness for v in paper.vehicles] == [0.85, 0.90, 1.10]
    assert [v.truth.yaw_rate_effectiveness for v in paper.vehicles] == [0.90, 1.10, 0.95]
    assert all(
        v.truth.actuator_lag_s == 0.1 and v.truth.wind.mean_m_s == (0.3, -0.2)
        for v in paper.vehicles
    )
    c = paper.controller
    assert (c.speed_max_m_s, c.yaw_rate_max_rad_s, c.horizon, c.period_s, c.d_safe_m) == (
        2.0,
        0.5,
        5,
        0.2,
        2.0,
    )


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"controller": {"horizon": 0}}, "controller.horizon"),
        ({"controller": {"speed_max_m_s": -1}}, "controller.speed_max_m_s"),
        ({"controller": {"horizonn": 5}}, "controller.horizonn"),
        ({"target": {"kind": "spiral"}}, "target.kind"),
        ({"formation": {"frame": "body"}}, "formation.frame"),
        ({"truth": {"speed_effectiveness": 0.0}}, "vehicles[0].truth.speed_effectiveness"),
        ({"truth": {"wind": {"mean_m_s": [1.0]}}}, "truth.wind.mean_m_s"),
        ({"plant_steps_per_period": 7}, "plant_steps_per_period"),
        ({"seed": -1}, "seed"),
        ({"colour": "red"}, "colour"),
        ({"vehicles": []}, "vehicles"),
        (
            {
                "vehicles": [
                    BASE["vehicles"][0],
                    {**BASE["vehicles"][1], "initial": [0.0, 1.0, 0.0]},
                ]
            },
            "vehicles[1].initial",
        ),
        ({"vehicles": [BASE["vehicles"][0], {**BASE["vehicles"][1], "id": 1}]}, "vehicles"),
        (
            {"vehicles": [BASE["vehicles"][0], {**BASE["vehicles"][1], "autopilot": "apm"}]},
            "vehicles[1].autopilot",
        ),
        ({"network": {"gcs_port": 0}}, "network.gcs_port"),
        ({"network": {"offboard_base_port": 65535}}, "network.offboard_base_port"),
        ({"network": {"ardupilot_tcp_base_port": 65530}}, "network.ardupilot_tcp_base_port"),
        ({"network": {"router_host": ""}}, "network.router_host"),
        ({"network": {"ground_station_host": 7}}, "network.ground_station_host"),
        (
            {"vehicles": [BASE["vehicles"][0], {**BASE["vehicles"][1], "host": ""}]},
            "vehicles[1].host",
        ),
    ],
)
def test_errors_name_the_field(changes, field):
    with pytest.raises(ConfigError) as err:
        _with(**changes)
    assert str(err.value).startswith(field + ":"), str(err.value)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_scenario(tmp_path / "nope.toml")


def test_autopilot_error_quotes_the_value():
    doc = {**BASE, "vehicles": [BASE["vehicles"][0], {**BASE["vehicles"][1], "autopilot": "apm"}]}
    with pytest.raises(ConfigError) as err:
        parse_scenario(doc)
    assert str(err.value) == 'vehicles[1].autopilot: must be "px4" or "ardupilot", got "apm"'


def test_each_vehicle_gets_the_url_of_its_autopilot():
    network = {"host": "127.0.0.2", "offboard_base_port": 24540, "ardupilot_tcp_base_port": 25760}
    vehicles = [
        BASE["vehicles"][0],
        {**BASE["vehicles"][1], "autopilot": "ardupilot"},
        {"id": 3, "initial": [0.0, -10.0, 0.0], "slot_m": [0.0, -10.0], "autopilot": "px4"},
    ]
    sc = _with(vehicles=vehicles, network=network)
    assert [v.autopilot for v in sc.vehicles] == ["px4", "ardupilot", "px4"]
    assert [mavlink_url(sc.network, v) for v in sc.vehicles] == [
        "udpin:127.0.0.2:24540",
        "tcp:127.0.0.2:25770",
        "udpin:127.0.0.2:24542",
    ]
    # On the default network: PX4's offboard ports, our ArduPilot profile's TCP ports clear of
    # ArduCopter SITL's.
    default = Network()
    assert [mavlink_url(default, v) for v in sc.vehicles] == [
        "udpin:127.0.0.1:14540",
        "tcp:127.0.0.1:15770",
        "udpin:127.0.0.1:14542",
    ]


def test_the_default_ports_of_simulated_vehicles_are_clear_of_real_sitls():
    """A fleet that mixes our vehicles with real SITLs starts on the defaults: no port our
    vehicles bind or serve is one a PX4 SITL instance binds (offboard 14580 + n, ground station
    18570 + n, payload 14280 + n, gimbal 13030 + n, simulator 4560 + n) or an ArduCopter SITL
    instance serves (TCP 5760 + 10 n to 5763 + 10 n), for 50 vehicles and 50 instances. The
    ports they stream to stay PX4's: instance n streams where vehicle n + 1's agent listens."""
    from fleetmpc.launch.fleet import FleetOptions, fleet_processes

    n = 50
    pattern = {"kind": "grid", "count": n, "spacing_m": 5.0, "columns": 10}
    px4 = parse_scenario({"name": "px4", "formation": {"pattern": pattern}})
    net = px4.network
    real_px4 = {p + i for p in (14580, 18570, 14280, 13030, 4560) for i in range(n)}
    real_ardupilot = {p + 10 * i for p in (5760, 5762, 5763) for i in range(n)}
    ours_udp = {net.offboard_local_port(v) for v in range(1, n + 1)}
    ours_udp |= {net.gcs_local_port(v) for v in range(1, n + 1)}
    ours_tcp = {net.ardupilot_tcp_port(v) for v in range(1, n + 1)}
    assert len(ours_udp) == 2 * n and not ours_udp & real_px4
    assert not ours_tcp & real_ardupilot
    assert min(ours_udp | ours_tcp) >= 15760 and max(ours_udp | ours_tcp) < 32768  # (ephemeral)
    assert [net.offboard_port(v) for v in (1, 2)] == [14540, 14541]  # (PX4 instance 0, 1)
    # What `up` starts: the issue's fleet, vehicle 2 on PX4 instance 1, binds none of its ports.
    paper = load_scenario(ROOT / "scenarios" / "paper.toml", live=True)
    specs = fleet_processes(
        paper, FleetOptions("s.toml", external_autopilots={2: "udpin:127.0.0.1:14541"})
    )
    assert [p.name for p in specs if p.role == "sitl"] == ["sitl-1", "sitl-3"]
    bound = {paper.network.offboard_local_port(v) for v in (1, 3)}
    bound |= {paper.network.gcs_local_port(v) for v in (1, 3)}
    assert bound == {24580, 24582, 28570, 28572}
    assert not bound & {14581, 18571}


def test_hosts_place_the_router_the_ground_station_and_each_vehicle():
    from fleetmpc.launch.fleet import FleetOptions, fleet_processes

    network = {"router_host": "10.0.0.1", "ground_station_host": "10.0.0.2"}
    vehicles = [{**BASE["vehicles"][0], "host": "10.0.0.11"}, BASE["vehicles"][1]]
    sc = _with(vehicles=vehicles, network=network)
    assert [mavlink_url(sc.network, v) for v in sc.vehicles] == [
        "udpin:10.0.0.11:14540",
        "udpin:127.0.0.1:14541",  # (no host of its own: network.host)
    ]
    specs = fleet_processes(sc, FleetOptions("s.toml"))
    assert {p.name: p.host for p in specs} == {
        "zenoh-router": "10.0.0.1",
        "target": "10.0.0.2",
        "sitl-1": "10.0.0.11",
        "sitl-2": "127.0.0.1",
        "agent-1": "10.0.0.11",
        "agent-2": "127.0.0.1",
        "gcs": "10.0.0.2",
    }
    argv = {p.name: p.argv for p in specs}
    assert argv["zenoh-router"][1:3] == ("--host", "10.0.0.1")
    for name in ("target", "agent-1", "agent-2", "gcs"):
        assert "10.0.0.1:7447" in argv[name], name
    assert sc.network.ground_station_address == "10.0.0.2"


def test_mixed_autopilots_is_the_paper_fleet_with_an_ardupilot_vehicle(paper):
    mixed = load_scenario("scenarios/mixed-autopilots.toml")
    assert [v.autopilot for v in mixed.vehicles] == ["px4", "ardupilot", "px4"]
    assert [v.autopilot for v in paper.vehicles] == ["px4", "px4", "px4"]
    for a, b in zip(mixed.vehicles, paper.vehicles, strict=True):
        assert (a.id, a.initial, a.slot_m, a.truth) == (b.id, b.initial, b.slot_m, b.truth)
    for field in ("seed", "duration_s", "controller", "learning", "formation", "target"):
        assert getattr(mixed, field) == getattr(paper, field), field


def test_a_live_fleet_whose_ports_collide_is_refused_naming_the_field():
    vehicles = [
        {"id": i, "initial": [0.0, 5.0 * i, 0.0], "slot_m": [0.0, 5.0 * i]} for i in range(1, 12)
    ]
    doc = {"name": "eleven", "vehicles": vehicles}
    with pytest.raises(ConfigError) as e:
        parse_scenario(doc, live=True)  # vehicle 11's offboard port would be 14540 + 10 = 14550
    assert e.value.field == "network.offboard_base_port"
    assert "UDP port 14550 of vehicle 11's offboard link is already the ground station's" in str(
        e.value
    )
    assert "(offboard_base_port = 14551 in [network] clears it)" in str(e.value)
    hinted = {**doc, "network": {"offboard_base_port": 14551}}
    assert len(parse_scenario(hinted, live=True).vehicles) == 11
    moved = {**doc, "network": {"gcs_port": 14650}}
    assert len(parse_scenario(moved, live=True).vehicles) == 11
    ardupilot = [{**v, "autopilot": "ardupilot"} for v in vehicles[:2]]
    clash = {"name": "clash", "vehicles": ardupilot, "network": {"zenoh_port": 15770}}
    with pytest.raises(ConfigError) as e:
        parse_scenario(clash, live=True)
    assert e.value.field == "network.ardupilot_tcp_base_port"


def test_a_simulation_opens_no_port_and_is_not_refused_over_one(tmp_path, capsys):
    """sim and check fly a fleet whose live ports would clash; up refuses it before starting
    anything."""
    from fleetmpc.cli import main

    text = (ROOT / "scenarios" / "scale" / "grid50.toml").read_text()
    text = text[: text.index("[network]")]  # the default ports: vehicle 11's is the GCS's 14550
    path = tmp_path / "fifty.toml"
    path.write_text(text)
    assert main(["check", str(path)]) == 0
    assert main(["sim", str(path), "--duration", "2", "--quiet"]) == 0
    with pytest.raises(ConfigError, match="network.offboard_base_port"):
        load_scenario(path, live=True)


def test_pattern_slots_are_spaced_as_asked():
    import math

    from fleetmpc.scenario import pattern_slots

    grid = pattern_slots("grid", 6, 5.0, 3)
    assert grid[:3] == [(2.5, -5.0), (2.5, 0.0), (2.5, 5.0)] and grid[3] == (-2.5, -5.0)
    line = pattern_slots("line", 3, 4.0, 1)
    assert line == [(0.0, -4.0), (0.0, 0.0), (0.0, 4.0)]
    ring = pattern_slots("ring", 8, 5.0, 1)
    assert math.dist(ring[0], ring[1]) == pytest.approx(5.0)
    wedge = pattern_slots("wedge", 5, 5.0, 1)
    assert math.dist(wedge[0], wedge[1]) == pytest.approx(5.0)
    assert wedge[1][1] == -wedge[2][1] and wedge[1][0] == wedge[2][0] < wedge[0][0]


def test_a_pattern_makes_the_vehicles_and_starts_them_at_their_slots():
    from fleetmpc.scenario import parse_scenario

    doc = {
        "name": "p",
        "formation": {
            "frame": "course",
            "trail_m": 10.0,
            "pattern": {"kind": "line", "count": 4, "spacing_m": 5.0},
        },
        "target": {"kind": "line", "start_m": [0.0, 0.0], "velocity_m_s": [0.0, 1.0]},
    }
    sc = parse_scenario(doc)
    assert sc.vehicle_ids == (1, 2, 3, 4)
    assert [v.slot_m for v in sc.vehicles] == [(0.0, -7.5), (0.0, -2.5), (0.0, 2.5), (0.0, 7.5)]
    # The target flies East: the centre trails it 10 m West, "right" of East is South.
    first = sc.vehicles[0].initial
    assert first == (pytest.approx(7.5), pytest.approx(-10.0), pytest.approx(math.pi / 2))
    for bad, field in (
        ({"kind": "star", "count": 3}, "formation.pattern.kind"),
        ({"kind": "grid", "count": 0}, "formation.pattern.count"),
        ({"kind": "grid", "count": 4, "spacing_m": -1.0}, "formation.pattern.spacing_m"),
        ({"kind": "grid", "count": 4, "rows": 2}, "formation.pattern.rows"),
    ):
        with pytest.raises(ConfigError) as e:
            parse_scenario({**doc, "formation": {"pattern": bad}})
        assert e.value.field == field
    with pytest.raises(ConfigError) as e:
        parse_scenario({**doc, "vehicles": [{"id": 1}]})
    assert e.value.field == "formation.pattern"
    with pytest.raises(ConfigError) as e:  # 1 m apart: closer than d_safe
        parse_scenario(
            {**doc, "formation": {"pattern": {"kind": "line", "count": 3, "spacing_m": 1.0}}}
        )
    assert e.value.field.startswith("vehicles[1]")


def test_a_vehicle_may_name_its_autopilots_system_id_and_system_ids_stay_unique():
    doc = tomllib.loads(Path("scenarios/mixed-autopilots.toml").read_text())
    doc["vehicles"][1]["system_id"] = 1
    with pytest.raises(ConfigError, match="system ids .* must be unique"):
        parse_scenario(doc)
    doc["vehicles"][0]["system_id"] = 11
    sc = parse_scenario(doc)
    assert [v.mavlink_system_id for v in sc.vehicles] == [11, 1, 3]
    doc["vehicles"][0]["system_id"] = 0
    with pytest.raises(ConfigError, match=r"vehicles\[0\]\.system_id: must be an integer"):
        parse_scenario(doc)
