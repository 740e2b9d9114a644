"""The paper fleet across machines: every vehicle's SITL and agent in a network namespace of its
own, with its own address, the router, the target and the ground station in another, joined by
a bridge this test creates (and removes). Each process is started as `fleetmpc up` would start it
(`fleetmpc.launch.fleet.fleet_processes`), inside its host's namespace; the scenario's
`[network]` and the vehicles' `host` say which address is whose. The fleet is secured as `up`
secures it (signed MAVLink, Zenoh users and TLS to the router's own address). The run must pass
the gates of the same fleet on loopback.

Needs root and iproute2 (`ip netns`); no traffic leaves the namespaces.
"""

import json
import os
import secrets
import shutil
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from fleetmpc.launch.fleet import FleetOptions, fleet_processes
from fleetmpc.scenario import load_scenario
from fleetmpc.security.secrets import make_keys

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper.toml"
SUBNET = "10.77.{}.{}"
DURATION_S = 30.0

pytestmark = pytest.mark.skipif(
    os.geteuid() != 0 or shutil.which("ip") is None, reason="needs root and iproute2"
)


class NamespaceRefused(RuntimeError):
    """The kernel (or the container this runs in) does not let this process make a namespace."""


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)
    if done.returncode != 0:
        message = f"ip {' '.join(args)}: {done.stderr.strip() or f'exit status {done.returncode}'}"
        refused = ("Operation not permitted", "Permission denied")
        if args[:2] == ("netns", "add") and any(word in done.stderr for word in refused):
            raise NamespaceRefused(message)
        raise RuntimeError(message)


class Hosts:
    """Network namespaces joined by a bridge (in a namespace of its own): one per host name,
    each with one address on a /24 and its loopback up. The names carry a random tag, so a run
    never meets the namespaces of another run (or of one that was killed before it cleaned up);
    whatever was made is removed again if making the rest fails."""

    def __init__(self, names: list[str]) -> None:
        tag = secrets.token_hex(3)
        self.bridge_ns = f"fm{tag}-br"
        self.ns = {name: f"fm{tag}-{name}" for name in names}
        subnet = int(tag, 16) % 250
        self.address = {name: SUBNET.format(subnet, 10 + i) for i, name in enumerate(names)}
        self.made: list[str] = []
        try:
            self._make(names)
        except BaseException:
            self.remove()
            raise

    def _add(self, ns: str) -> None:
        _ip("netns", "add", ns)
        self.made.append(ns)

    def _make(self, names: list[str]) -> None:
        self._add(self.bridge_ns)
        _ip("-n", self.bridge_ns, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.bridge_ns, "link", "set", "br0", "up")
        for i, name in enumerate(names):
            ns = self.ns[name]
            self._add(ns)
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", f"p{i}")
            _ip("-n", ns, "link", "set", f"p{i}", "netns", self.bridge_ns)
            _ip("-n", self.bridge_ns, "link", "set", f"p{i}", "master", "br0", "up")
            _ip("-n", ns, "addr", "add", f"{self.address[name]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def remove(self) -> None:
        for ns in reversed(self.made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
        self.made.clear()


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    try:
        made = Hosts(["ground", "uav1", "uav2", "uav3"])
    except NamespaceRefused as refused:  # a container without CAP_SYS_ADMIN, say
        pytest.skip(f"this host does not allow network namespaces ({refused})")
    try:
        yield made
    finally:
        made.remove()


def _scenario_across(hosts: Hosts, dest: Path) -> Path:
    """paper.toml with its router and ground station on host "ground" and vehicle i on "uav<i>"."""
    text = PAPER.read_text()
    doc = tomllib.loads(text)
    assert "network" not in doc and all("host" not in v for v in doc["vehicles"])
    ground = hosts.address["ground"]
    lines = text.splitlines()
    out = []
    for line in lines:
        out.append(line)
        if line.startswith("id = "):
            out.append(f'host = "{hosts.address["uav" + line.split("=")[1].strip()]}"')
    out += ["", "[network]", f'router_host = "{ground}"', f'ground_station_host = "{ground}"']
    dest.write_text("\n".join(out) + "\n")
    return dest


@pytest.mark.slow  # (44 s of two cores)
def test_the_paper_fleet_across_network_namespaces_passes_the_loopback_gates(
    hosts, processes, tmp_path
):
    copy = _scenario_across(hosts, tmp_path / "paper-across.toml")
    scenario = load_scenario(copy)
    metrics = tmp_path / "metrics.json"
    secrets = make_keys(scenario, tmp_path / "secrets")  # TLS to the router's own address
    options = FleetOptions(
        str(copy), duration_s=DURATION_S, metrics=str(metrics), secrets_dir=str(secrets)
    )
    gcs = None
    by_address = {address: name for name, address in hosts.address.items()}
    for spec in fleet_processes(scenario, options):  # each on the host the deployment names
        ns = hosts.ns[by_address[spec.host]]
        argv = ["ip", "netns", "exec", ns, sys.executable, "-m", "fleetmpc.cli"]
        child = processes.start(spec.name, [*argv, *spec.argv])
        if spec.role == "gcs":
            gcs = child
    assert gcs is not None
    rc = gcs.proc.wait(timeout=120.0 + DURATION_S)
    assert rc == 0, gcs.tail()
    m = json.loads(metrics.read_text())
    assert m["source"] == "live" and m["periods_recorded"] == m["periods_expected"] == 151, m
    assert all(e <= 0.1 for e in m["separation_error_m"]), m["separation_error_m"]
    assert m["centre_distance_error_m"] <= 0.1, m
    assert m["min_separation_m"] >= 2.0, m
