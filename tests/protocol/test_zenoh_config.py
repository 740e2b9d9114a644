"""Zenoh options: URL parsing, explicit endpoints, scouting always off."""

import json
from pathlib import Path

import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.protocol.zenoh_config import (
    ZenohOptions,
    endpoint,
    options_from_args,
    peer_mesh_index,
)
from fleetmpc.scenario import parse_scenario


def conf_json(options: ZenohOptions, key: str) -> object:
    return json.loads(options.to_config().get_json(key))


def test_default_url_is_a_loopback_peer_of_port_7447() -> None:
    options = ZenohOptions.from_url("zenoh")
    assert options == ZenohOptions(connect=("tcp/127.0.0.1:7447",))
    assert conf_json(options, "mode") == "peer"
    assert conf_json(options, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert conf_json(options, "listen/endpoints") == []  # not zenoh's tcp/[::]:0


@pytest.mark.parametrize(
    "options",
    [
        ZenohOptions(connect=("tcp/127.0.0.1:7447",)),
        ZenohOptions(mode="client", connect=("tcp/127.0.0.1:7447",)),
        ZenohOptions.peer_mesh(index=2, size=3, base_port=7450),
    ],
)
def test_scouting_is_always_off(options: ZenohOptions) -> None:
    assert conf_json(options, "scouting/multicast/enabled") is False
    assert conf_json(options, "scouting/gossip/enabled") is False


def test_url_with_options() -> None:
    url = "zenoh://127.0.0.1:7447,localhost:7448?listen=127.0.0.1:7449&connect=udp/127.0.0.1:7450"
    options = ZenohOptions.from_url(url)
    assert options.mode is None
    assert options.connect == ("tcp/127.0.0.1:7447", "tcp/localhost:7448", "udp/127.0.0.1:7450")
    assert options.listen == ("tcp/127.0.0.1:7449",)
    client = ZenohOptions.from_url("zenoh://[::1]:7447?mode=client")
    assert client.mode == "client" and client.connect == ("tcp/[::1]:7447",)
    assert conf_json(client, "mode") == "client"


@pytest.mark.parametrize(
    ("url", "field"),
    [
        ("zenoh://127.0.0.1:7447?colour=red", "zenoh_url.colour"),
        ("zenoh://127.0.0.1:7447?mode=router", "zenoh.mode"),
        ("zenoh://127.0.0.1?mode=peer", "zenoh_url"),
        ("zenoh://127.0.0.1:99999", "zenoh_url"),
        ("zenoh://127.0.0.1:7447?listen=nowhere", "zenoh_url.listen"),
        ("zenoh://127.0.0.1:7447?mode=client&listen=127.0.0.1:7448", "zenoh.listen"),
        ("zenoh://", "zenoh.connect"),
        ("zenoh:/path", "zenoh_url"),
        ("zenoh://127.0.0.1:7447?config=/no/such/file.json5", "zenoh.config_file"),
    ],
)
def test_bad_urls_name_the_field(url: str, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        ZenohOptions.from_url(url)
    assert info.value.field == field


def test_peer_mesh_links_every_pair_once() -> None:
    members = [ZenohOptions.peer_mesh(index=k, size=3, base_port=9000) for k in range(3)]
    assert [m.listen for m in members] == [(f"tcp/127.0.0.1:{9000 + k}",) for k in range(3)]
    assert [m.connect for m in members] == [
        (),
        ("tcp/127.0.0.1:9000",),
        ("tcp/127.0.0.1:9000", "tcp/127.0.0.1:9001"),
    ]
    with pytest.raises(ConfigError) as info:
        ZenohOptions.peer_mesh(index=3, size=3, base_port=9000)
    assert info.value.field == "index"


def test_config_file_is_the_base_but_scouting_stays_off(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] },'
        " scouting: { multicast: { enabled: true }, gossip: { enabled: true } } }"
    )
    options = ZenohOptions(config_file=str(path))
    assert conf_json(options, "mode") == "client"
    assert conf_json(options, "connect/endpoints") == ["tcp/127.0.0.1:7999"]
    assert conf_json(options, "scouting/multicast/enabled") is False
    assert conf_json(options, "scouting/gossip/enabled") is False
    override = ZenohOptions.from_url(f"zenoh://127.0.0.1:7447?mode=peer&config={path}")
    assert conf_json(override, "mode") == "peer"
    assert conf_json(override, "connect/endpoints") == ["tcp/127.0.0.1:7447"]


def test_malformed_config_file_is_a_config_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.json5"
    path.write_text("{ mode: ")
    with pytest.raises(ConfigError) as info:
        ZenohOptions(config_file=str(path)).to_config()
    assert info.value.field == "zenoh.config_file"


@pytest.mark.parametrize("endpoints", ["tcp/127.0.0.1:7447", ("127.0.0.1:7447",), ("tcp/a b:1",)])
def test_malformed_endpoints_are_refused(endpoints: object) -> None:
    with pytest.raises(ConfigError) as info:
        ZenohOptions(connect=endpoints)  # type: ignore[arg-type]
    assert info.value.field.startswith("zenoh.connect")


def test_endpoint_helper() -> None:
    assert endpoint("127.0.0.1", 7447) == "tcp/127.0.0.1:7447"
    with pytest.raises(ConfigError):
        endpoint("127.0.0.1", 70000)


def _fleet(*ids: int, **network):
    vehicles = [
        {"id": vid, "initial": [0.0, 10.0 * k, 0.0], "slot_m": [0.0, 10.0 * k]}
        for k, vid in enumerate(ids)
    ]
    return parse_scenario({"name": "mesh", "vehicles": vehicles, "network": network})


def _mesh(sc) -> dict:
    """`options_from_args`'s peer-mesh arguments for a scenario's fleet."""
    net = sc.network
    return {"host": net.host, "base_port": net.zenoh_port, "size": len(sc.vehicles) + 2}


def test_peer_mesh_index_is_vehicles_in_scenario_order_then_target_then_ground_station() -> None:
    sc = _fleet(7, 3, 5)
    assert [peer_mesh_index(sc.vehicle_ids, vid) for vid in (7, 3, 5)] == [0, 1, 2]
    assert peer_mesh_index(sc.vehicle_ids, TARGET_ID) == 3
    assert peer_mesh_index(sc.vehicle_ids, GROUND_STATION_ID) == 4
    with pytest.raises(ConfigError) as info:
        peer_mesh_index(sc.vehicle_ids, 4)
    assert info.value.field == "vehicle"


def test_options_from_args_default_to_the_fleets_peer_mesh() -> None:
    sc = _fleet(1, 2, 3, host="127.0.0.3", zenoh_port=17447)
    members = [options_from_args(None, None, member_index=k, **_mesh(sc)) for k in range(5)]
    assert members == [
        ZenohOptions.peer_mesh(index=k, size=5, base_port=17447, host="127.0.0.3") for k in range(5)
    ]
    assert members[4].listen == ("tcp/127.0.0.3:17451",)
    assert members[4].connect == tuple(f"tcp/127.0.0.3:{17447 + j}" for j in range(4))
    assert conf_json(members[0], "mode") == "peer"


def test_options_from_args_connect_makes_a_client_and_a_file_is_a_base() -> None:
    sc = _fleet(1, 2)
    client = options_from_args(
        None, "127.0.0.1:7000, tcp/127.0.0.2:7001", member_index=0, **_mesh(sc)
    )
    assert client == ZenohOptions(
        mode="client", connect=("tcp/127.0.0.1:7000", "tcp/127.0.0.2:7001")
    )
    with pytest.raises(ConfigError) as info:
        options_from_args(None, "nowhere", member_index=0, **_mesh(sc))
    assert info.value.field == "--zenoh-connect"


def test_options_from_args_takes_a_config_file_first(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    options = options_from_args(path, "127.0.0.1:7000", member_index=0, **_mesh(_fleet(1)))
    assert options == ZenohOptions(config_file=str(path))
    assert conf_json(options, "connect/endpoints") == ["tcp/127.0.0.1:7999"]
