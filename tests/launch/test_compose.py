"""`fleetmpc compose`: the fleet's compose file, generated from the same process list as `up`."""

import json
import re
from pathlib import Path

import pytest

from fleetmpc.cli import main
from fleetmpc.errors import ConfigError
from fleetmpc.launch.compose import ComposeOptions, compose_document, compose_yaml
from fleetmpc.launch.fleet import FleetOptions, fleet_processes
from fleetmpc.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


def _arg(argv: list[str], flag: str) -> str:
    return argv[argv.index(flag) + 1]


def _parse(text: str) -> dict:
    """Read back the YAML subset the generator writes: comments, block mappings by two-space
    indentation, and JSON values (scalars and flow lists). Anything else fails the test."""
    root: dict = {}
    stack: list[tuple[int, dict]] = [(-1, root)]
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = re.fullmatch(r'( *)([A-Za-z0-9_][A-Za-z0-9_.-]*|"[^"]*"):(?: (.+))?', line)
        assert m, f"line {n} is outside the generator's YAML subset: {line!r}"
        indent, key, value = len(m[1]), m[2].strip('"'), m[3]
        assert indent % 2 == 0, f"line {n}: odd indentation"
        while stack[-1][0] >= indent:
            stack.pop()
        parent_indent, parent = stack[-1]
        assert indent == parent_indent + 2 or (parent is root and indent == 0), f"line {n}"
        assert key not in parent, f"line {n}: duplicate key {key}"
        if value is None:
            parent[key] = {}
            stack.append((indent, parent[key]))
        else:
            parent[key] = json.loads(value)
    return root


@pytest.fixture
def in_repo(monkeypatch) -> None:
    monkeypatch.chdir(ROOT)


def test_docker_compose_yaml_is_the_generated_paper_file(in_repo, capsys) -> None:
    committed = (ROOT / "docker" / "compose.yaml").read_text()
    assert compose_yaml("scenarios/paper.toml") == committed, (
        "docker/compose.yaml is stale: run `make compose-file`"
    )
    assert main(["compose", "scenarios/paper.toml"]) == 0
    assert capsys.readouterr().out == committed


def test_the_yaml_reads_back_as_the_document(in_repo) -> None:
    for name in ("paper.toml", "wedge-circle.toml", "mixed-autopilots.toml"):
        path = f"scenarios/{name}"
        doc = compose_document(load_scenario(path), scenario_name=name, options=ComposeOptions())
        assert _parse(compose_yaml(path)) == doc


def test_five_vehicles_get_their_own_services_ids_and_ports(in_repo, tmp_path) -> None:
    out = tmp_path / "five.yaml"
    assert main(["compose", "scenarios/wedge-circle.toml", "--speed", "4", "-o", str(out)]) == 0
    doc = _parse(out.read_text())
    sc = load_scenario("scenarios/wedge-circle.toml")
    ids = sc.vehicle_ids
    assert len(ids) == 5
    services = doc["services"]
    assert list(services) == [
        "zenoh-router",
        "target",
        *(f"sitl-{i}" for i in ids),
        *(f"agent-{i}" for i in ids),
        "gcs",
    ]
    ports = set()
    for i in ids:
        sitl, agent = services[f"sitl-{i}"], services[f"agent-{i}"]
        assert _arg(sitl["command"], "--vehicle") == _arg(agent["command"], "--vehicle") == str(i)
        assert sitl["labels"]["fleetmpc.vehicle"] == str(i)
        assert sitl["labels"]["fleetmpc.mavlink"] == agent["labels"]["fleetmpc.mavlink"]
        ports.add(sitl["labels"]["fleetmpc.mavlink"])
        assert agent["depends_on"][f"sitl-{i}"] == {"condition": "service_started"}
    assert ports == {f"udpin:127.0.0.1:{14540 + i - 1}" for i in ids}
    for name, s in services.items():
        assert s["image"] == "fleetmpc:local" and s["init"] is True, name
        assert s["network_mode"] == "host" and s["pull_policy"] == "never", name
        if name == "zenoh-router":
            assert s["build"]["dockerfile"] == "docker/Dockerfile" and "depends_on" not in s
            assert _arg(s["command"], "--port") == "7447"
            assert "7447" in s["healthcheck"]["test"][-1]
        else:
            assert "build" not in s and _arg(s["command"], "--speed") == "4", name
            assert s["depends_on"]["zenoh-router"] == {"condition": "service_healthy"}, name
    gcs = services["gcs"]
    assert set(gcs["depends_on"]) == set(services) - {"gcs"}
    assert gcs["volumes"] == ["${FLEETMPC_OUT:-../runs/compose}:/out"]
    assert _arg(gcs["command"], "--rrd") == "/out/run.rrd"
    assert _arg(gcs["command"], "--metrics") == "/out/metrics.json"
    assert _arg(gcs["command"], "--gate-formation-m") == "0.1"
    assert _arg(gcs["command"], "--duration") == "60"
    assert "--duration" not in services["target"]["command"]
    assert _arg(services["target"]["command"], "--scenario") == "/app/scenarios/wedge-circle.toml"
    assert doc["name"] == "fleetmpc-wedge-circle"


def test_the_same_processes_and_arguments_as_up(paper) -> None:
    opts = ComposeOptions(speed=2.0, duration_s=12.0)
    doc = compose_document(paper, scenario_name="paper.toml", options=opts)
    specs = fleet_processes(
        paper,
        FleetOptions(
            scenario_path="/app/scenarios/paper.toml",
            speed=2.0,
            duration_s=12.0,
            rrd="/out/run.rrd",
            metrics="/out/metrics.json",
            secrets_dir="/run/secrets",
        ),
    )
    assert list(doc["services"]) == [s.name for s in specs]
    for spec in specs:
        command = doc["services"][spec.name]["command"]
        if spec.role == "target":
            i = spec.argv.index("--duration")
            assert command == [*spec.argv[:i], *spec.argv[i + 2 :]]
        elif spec.role == "gcs":
            assert command == [*spec.argv, "--gate-formation-m", "0.1"]
        else:
            assert command == list(spec.argv)


def test_each_service_gets_only_its_own_secrets_by_file(paper) -> None:
    doc = compose_document(paper, scenario_name="paper.toml", options=ComposeOptions())
    services = doc["services"]
    assert services["sitl-2"]["secrets"] == ["mavlink-2.key"]
    assert services["agent-2"]["secrets"] == ["zenoh-agent-2.json5", "mavlink-2.key"]
    assert services["target"]["secrets"] == ["zenoh-target.json5"]
    assert sorted(services["gcs"]["secrets"]) == [
        "mavlink-1.key", "mavlink-2.key", "mavlink-3.key", "zenoh-gcs.json5",
    ]  # fmt: skip
    assert "zenoh-users.txt" in services["zenoh-router"]["secrets"]
    used = {n for s in services.values() for n in s["secrets"]}
    assert set(doc["secrets"]) == used
    assert doc["secrets"]["mavlink-2.key"] == {
        "file": "${FLEETMPC_SECRETS:-../runs/compose/secrets}/mavlink-2.key"
    }
    for name, service in services.items():
        for arg in service["command"]:
            assert not arg.startswith("/run/secrets/") or arg[13:] in service["secrets"], name
    open_doc = compose_document(
        paper, scenario_name="paper.toml", options=ComposeOptions(insecure=True)
    )
    assert "secrets" not in open_doc
    assert not any("/run/secrets" in " ".join(s["command"]) for s in open_doc["services"].values())


def test_options_reach_the_file(paper) -> None:
    opts = ComposeOptions(
        scenario_in_image="/data/$fleet.toml",
        image="registry.example/fleetmpc:1.0",
        out_dir_var="RUN_OUT",
        out_dir="/srv/runs",
        gate_formation_m=None,
    )
    services = compose_document(paper, scenario_name="x.toml", options=opts)["services"]
    gcs = services["gcs"]
    assert gcs["volumes"] == ["${RUN_OUT:-/srv/runs}:/out"]
    assert "--gate-formation-m" not in gcs["command"]
    # A `$` in an argument is escaped so compose passes it on unchanged.
    assert _arg(gcs["command"], "--scenario") == "/data/$$fleet.toml"
    assert {s["image"] for s in services.values()} == {"registry.example/fleetmpc:1.0"}


@pytest.mark.parametrize(
    ("field", "kwargs", "shown"),
    [
        ("--speed", {"speed": 0.0}, "got 0"),
        ("--speed", {"speed": 5000.0}, "got 5000"),
        ("--duration", {"duration_s": -1.0}, "got -1"),
        ("--scenario-in-image", {"scenario_in_image": "scenarios/p.toml"}, "'scenarios/p.toml'"),
        ("--image", {"image": "Fleet MPC"}, "'Fleet MPC'"),
        ("--out-dir-var", {"out_dir_var": "1OUT"}, "'1OUT'"),
        ("--out-dir", {"out_dir": "runs:/x"}, "'runs:/x'"),
        ("--out-dir", {"out_dir": ""}, "''"),
        ("--gate-formation-m", {"gate_formation_m": 0.0}, "got 0"),
    ],
)
def test_bad_options_are_named(field, kwargs, shown) -> None:
    with pytest.raises(ConfigError) as e:
        ComposeOptions(**kwargs)
    assert e.value.field == field
    assert str(e.value).startswith(f"{field}: ") and str(e.value).endswith(shown)


def test_cli_errors_name_the_bad_value(in_repo, capsys, tmp_path) -> None:
    assert main(["compose", "scenarios/paper.toml", "--gate-formation-m", "tight"]) == 2
    assert "--gate-formation-m" in capsys.readouterr().err
    assert main(["compose", str(tmp_path / "missing.toml")]) == 2
    assert "missing.toml" in capsys.readouterr().err
    assert main(["compose", "scenarios/paper.toml", "--out-dir-var", "A-B"]) == 2
    assert "'A-B'" in capsys.readouterr().err


def test_one_file_per_machine_of_a_fleet_across_machines(tmp_path) -> None:
    """Router and ground station on 10.0.0.1, each vehicle on its own companion computer: each
    machine's file holds exactly its processes, their secrets, and dependencies among them."""
    text = (ROOT / "scenarios" / "paper.toml").read_text()
    for vid in (1, 2, 3):
        text = text.replace(
            f"[[vehicles]]\nid = {vid}\n", f'[[vehicles]]\nid = {vid}\nhost = "10.0.0.1{vid}"\n'
        )
    text += '\n[network]\nrouter_host = "10.0.0.1"\nground_station_host = "10.0.0.1"\n'
    path = tmp_path / "across.toml"
    path.write_text(text)
    sc = load_scenario(path)

    def document(host: str) -> dict:
        options = ComposeOptions(host=host)
        return _parse(compose_yaml(str(path), options))

    ground = document("10.0.0.1")
    assert list(ground["services"]) == ["zenoh-router", "target", "gcs"]
    assert set(ground["services"]["gcs"]["depends_on"]) == {"zenoh-router", "target"}
    assert "build" in ground["services"]["zenoh-router"]
    every = set(ground["services"])
    for v in sc.vehicles:
        doc = document(f"10.0.0.1{v.id}")
        services = doc["services"]
        assert list(services) == [f"sitl-{v.id}", f"agent-{v.id}"]
        assert "build" in services[f"sitl-{v.id}"] and "depends_on" not in services[f"sitl-{v.id}"]
        assert services[f"agent-{v.id}"]["depends_on"] == {
            f"sitl-{v.id}": {"condition": "service_started"}
        }
        assert set(doc["secrets"]) == {f"mavlink-{v.id}.key", f"zenoh-agent-{v.id}.json5"}
        assert doc["name"] == f"fleetmpc-paper-10-0-0-1{v.id}"
        every |= set(services)
    assert every == {s.name for s in fleet_processes(sc, FleetOptions(scenario_path="x"))}
    with pytest.raises(ConfigError, match=r"--host: no process of the fleet runs on 10\.9\.9\.9"):
        document("10.9.9.9")
