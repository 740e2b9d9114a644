"""The processes of a fleet, derived from its scenario: what `fleetmpc up` starts and
`fleetmpc compose` writes.

One list for both, so a compose file and a native launch can never disagree about a port, a
system id or an argument. Every process is a `fleetmpc` subcommand; the order is the start order:
the Zenoh router, the target, the SITL vehicles, their agents, and the ground station last.

Ports and system ids come from the scenario (`[network]` and the vehicles' ids). Every Zenoh
member is a client of the one router (peers do not relay for each other with gossip off). No
process is given an epoch: the ground station announces it on the bus once every vehicle is
engaged, and the target and the agents wait for it (`--wait-epoch`).

Secrets (`FleetOptions.secrets_dir`, made by `fleetmpc.security.secrets`): the router gets the
folder (its users, access list and TLS certificate), every bus member its own Zenoh client config
(``--zenoh-config``: its user, password and the run's CA) instead of ``--zenoh-connect``; each
simulated vehicle's SITL and agent get that vehicle's MAVLink signing key file, the ground
station each of them (``--mavlink-key ID=FILE``); a vehicle flown on an external autopilot
keeps an unsigned link (its key is the user's to set up on the autopilot). Only file paths are
passed, never a secret.
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import PurePath

from fleetmpc.errors import ConfigError
from fleetmpc.network import vehicle_host
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.scenario import Scenario, VehicleSpec
from fleetmpc.security.mavlink_signing import key_file_name
from fleetmpc.security.zenoh_access import zenoh_user
from fleetmpc.security.zenoh_security import ZenohSecurity

__all__ = ["FleetOptions", "ProcessSpec", "auto_vehicles_per_sitl", "fleet_processes"]


@dataclass(frozen=True)
class ProcessSpec:
    """One OS process (or container) of a fleet."""

    name: str
    """Unique name: ``zenoh-router``, ``target``, ``sitl-<id>`` (``sitl-<first id>..<last id>``
    for a process that serves several vehicles), ``agent-<id>`` or ``gcs``."""
    argv: tuple[str, ...]
    """Arguments after ``fleetmpc``."""
    role: str
    """``router``, ``target``, ``sitl``, ``agent`` or ``gcs``."""
    host: str = "127.0.0.1"
    """The address of the machine it runs on: the router's for the router, the ground
    station's for the target and the ground station, a vehicle's (its companion computer's) for
    its SITL and agent."""


@dataclass(frozen=True)
class FleetOptions:
    """What a launch chooses beyond the scenario (paths as the processes will see them)."""

    scenario_path: str
    """The scenario file, as the processes open it."""
    speed: float = 1.0
    """Simulated seconds per wall-clock second."""
    duration_s: float | None = None
    """Flight time; None: the scenario's."""
    fleet: str | None = None
    """Zenoh fleet name; None: the scenario's name."""
    rrd: str | None = None
    """Recording the ground station writes."""
    metrics: str | None = None
    """Metrics JSON the ground station writes."""
    status_file: str | None = None
    """Live status snapshot the ground station rewrites (for a launcher's table)."""
    viewer: str = "none"
    """Ground station's Rerun viewer: ``spawn``, ``connect=URL`` or ``none``."""
    agent_records_dir: str | None = None
    """If set, each agent writes one JSON line per step to ``<dir>/agent-<id>.jsonl``."""
    external_autopilots: Mapping[int, str] = field(default_factory=dict)
    """Vehicle id -> MAVLink URL of an autopilot outside the fleet (a real PX4 or ArduPilot, or
    their SITL): that vehicle's agent flies it, and no simulated vehicle is started for it."""
    secrets_dir: str | None = None
    """The folder of the run's secrets (`fleetmpc.security.secrets`) as the processes see it; None:
    an insecure fleet (unsigned MAVLink)."""
    connect_timeout_s: float | None = None
    """Wall seconds each agent waits for its autopilot's HEARTBEAT and first pose (``fleetmpc
    agent --connect-timeout``); None: the agent's default."""
    engage_timeout_s: float | None = None
    """Wall seconds each agent keeps trying to engage its vehicle (``fleetmpc agent
    --engage-timeout``); None: the agent's default."""
    wind_epoch_ns: int | None = None
    """Host time.time_ns() at which the fleet's wind clock reads 0, given to every SITL process
    (``fleetmpc sitl --wind-epoch-ns``) so that they fly one wind; None: each its own start."""
    target_source: str = "script"
    """The target process's source (``fleetmpc target --source``: ``script``,
    ``mavlink:CONNECTION``, ``track:FILE``)."""
    target_sysid: int | None = None
    """The MAVLink system the target process follows (``--sysid``)."""
    vehicles_per_sitl: int = 1
    """Simulated vehicles one SITL process serves at most (vehicles next to each other in the
    scenario, on one host): fewer processes wake the host less often
    (`fleetmpc.sitl.vehicle_group`), but a stalled process stalls all of its vehicles."""

    def __post_init__(self) -> None:
        if self.vehicles_per_sitl < 1:
            raise ConfigError(
                "vehicles_per_sitl", f"must be at least 1, got {self.vehicles_per_sitl}"
            )


SEPARATE_SITL_LOAD = 12.0
"""Simulated vehicle-seconds per wall-clock second (vehicles x speed) up to which a launch gives
each vehicle a SITL process of its own by default: ten vehicles at x1, the paper's three at x4.
A one-vehicle SITL process takes about 2.6 % of a core per unit of speed (twenty-five of them
took 64 % at x1), so up to here they take about a third of a core (`auto_vehicles_per_sitl`)."""
SITL_GROUP = 25
"""Vehicles one SITL process serves by default beyond that: about a quarter of a core at x1."""


def auto_vehicles_per_sitl(vehicles: int, speed: float = 1.0) -> int:
    """`FleetOptions.vehicles_per_sitl` for a launch that does not choose: a process per vehicle
    up to `SEPARATE_SITL_LOAD` (a fault can then stop one vehicle's SITL alone), else
    `SITL_GROUP` vehicles a process (on a few cores, waking fewer processes is what lets the
    fleet keep up: ten vehicles at x4 on two cores held their formation in one SITL process and
    lost it in ten; docs/design.md, "Waking")."""
    return 1 if vehicles * speed <= SEPARATE_SITL_LOAD else SITL_GROUP


def _num(x: float) -> str:
    return f"{x:g}"


def fleet_processes(scenario: Scenario, options: FleetOptions) -> list[ProcessSpec]:
    """The fleet's processes in start order: router, target, SITLs, agents, ground station."""
    fleet = _FleetArgs(scenario, options)
    return [
        fleet.router(),
        fleet.target(),
        *fleet.sitls(),
        *(fleet.agent(v) for v in scenario.vehicles),
        fleet.gcs(),
    ]


class _FleetArgs:
    """Each process's argument list, from the scenario and the options of one fleet."""

    def __init__(self, scenario: Scenario, options: FleetOptions) -> None:
        self.scenario, self.options, self.net = scenario, options, scenario.network
        self.fleet = options.fleet or scenario.name
        self.duration_s = scenario.duration_s if options.duration_s is None else options.duration_s
        self.common = ("--scenario", options.scenario_path)
        self.speed = ("--speed", _num(options.speed))
        self.secrets = None if options.secrets_dir is None else PurePath(options.secrets_dir)

    def bus_of(self, sender_id: int) -> tuple[str, ...]:
        """How the process of `sender_id` joins the fleet's Zenoh bus."""
        if self.secrets is None:
            connect = ("--zenoh-connect", f"{self.net.router_address}:{self.net.zenoh_port}")
        else:
            config = ZenohSecurity.client_config_name(zenoh_user(sender_id))
            connect = ("--zenoh-config", str(self.secrets / config))
        return (*connect, "--fleet", self.fleet)

    def key_path(self, vid: int) -> PurePath | None:
        """Vehicle `vid`'s signing key file; None for an insecure fleet or an external autopilot."""
        external = self.options.external_autopilots
        return (
            None if self.secrets is None or vid in external else self.secrets / key_file_name(vid)
        )

    def key(self, vid: int) -> tuple[str, ...]:
        path = self.key_path(vid)
        return () if path is None else ("--mavlink-key", str(path))

    def router(self) -> ProcessSpec:
        net = self.net
        argv = ("zenoh-router", "--host", net.router_address, "--port", str(net.zenoh_port))
        if self.secrets is not None:
            argv += ("--security", str(self.secrets))
        return ProcessSpec("zenoh-router", argv, "router", net.router_address)

    def target(self) -> ProcessSpec:
        o = self.options
        argv = ("target", *self.common, *self.bus_of(TARGET_ID), *self.speed, "--wait-epoch")
        if o.target_source != "script":
            argv += ("--source", o.target_source)
        if o.target_sysid is not None:
            argv += ("--sysid", str(o.target_sysid))
        argv += ("--duration", _num(self.duration_s + 1.0))
        return ProcessSpec("target", argv, "target", self.net.ground_station_address)

    def sitls(self) -> list[ProcessSpec]:
        """One SITL process per run of up to `vehicles_per_sitl` simulated vehicles in a row
        on one host."""
        groups: list[tuple[str, list[int]]] = []  # (host, vehicle ids)
        for v in self.scenario.vehicles:
            if v.id in self.options.external_autopilots:
                continue
            host = vehicle_host(self.net, v)
            last = groups[-1] if groups else None
            if last and last[0] == host and len(last[1]) < self.options.vehicles_per_sitl:
                last[1].append(v.id)
            else:
                groups.append((host, [v.id]))
        return [self._sitl(host, ids) for host, ids in groups]

    def _sitl(self, host: str, ids: list[int]) -> ProcessSpec:
        argv = ["sitl", *self.common]
        for vid in ids:
            argv += ["--vehicle", str(vid)]
        argv += self.speed
        if self.options.wind_epoch_ns is not None:
            argv += ["--wind-epoch-ns", str(self.options.wind_epoch_ns)]
        for vid in ids:  # (paired with the vehicles in order)
            argv += self.key(vid)
        name = f"sitl-{ids[0]}" if len(ids) == 1 else f"sitl-{ids[0]}..{ids[-1]}"
        return ProcessSpec(name, tuple(argv), "sitl", host)

    def agent(self, v: VehicleSpec) -> ProcessSpec:
        o = self.options
        argv = ["agent", *self.common, "--vehicle", str(v.id), *self.bus_of(v.id), *self.speed]
        argv += ["--wait-epoch", *self.key(v.id)]
        for flag, seconds in (
            ("--connect-timeout", o.connect_timeout_s),
            ("--engage-timeout", o.engage_timeout_s),
        ):
            if seconds is not None:
                argv += [flag, _num(seconds)]
        if v.id in o.external_autopilots:
            argv += ["--mavlink", o.external_autopilots[v.id]]
        if o.agent_records_dir is not None:
            argv += ["--record", str(PurePath(o.agent_records_dir) / f"agent-{v.id}.jsonl")]
        return ProcessSpec(f"agent-{v.id}", tuple(argv), "agent", vehicle_host(self.net, v))

    def gcs(self) -> ProcessSpec:
        o = self.options
        argv = ["gcs", *self.common, *self.bus_of(GROUND_STATION_ID), *self.speed]
        argv += ["--duration", _num(self.duration_s), "--viewer", o.viewer]
        if o.target_source != "script":
            argv += ["--target-source", o.target_source]
        for v in self.scenario.vehicles:
            if self.key_path(v.id) is not None:
                argv += ["--mavlink-key", f"{v.id}={self.key_path(v.id)}"]
        for flag, value in (
            ("--rrd", o.rrd),
            ("--metrics", o.metrics),
            ("--status-file", o.status_file),
        ):
            if value is not None:
                argv += [flag, value]
        return ProcessSpec("gcs", tuple(argv), "gcs", self.net.ground_station_address)
