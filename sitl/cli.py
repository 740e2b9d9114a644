"""`fleetmpc sitl`: simulated vehicles behind PX4 (default) or ArduPilot MAVLink interfaces.

One vehicle per ``--vehicle``; several in one process serve each its own endpoints, system id and
ports, as a multi-instance SITL does (`fleetmpc.sitl.vehicle_group`).

PX4 ports (vehicle I): streams to the offboard-API port 14540 + I - 1 and to the ground-station
port 14550, as PX4 SITL instance I - 1 does, from ports it binds 10000 above PX4's (24580 + I - 1
and 28570 + I - 1), so it never takes one a real PX4 SITL binds. ArduPilot: TCP server on
15760 + 10 (I - 1) (ArduPilot SITL's 5760 + 10000: a real ArduCopter SITL keeps its own), plus
the same ground-station UDP stream (as ArduPilot SITL's ``--out udp:HOST:14550``; ``--gcs-port 0``
turns it off) (`fleetmpc.network`). The profile is the vehicle's
``autopilot`` in the scenario unless --autopilot says otherwise. Base ports come from the
scenario's [network] table (the agent's default URL uses the same arithmetic,
`fleetmpc.network.mavlink_url`); the bound ports keep their distance to the ports streamed
to, so a [network] table that moves the offboard or ground-station port moves them too and two
fleets with different tables share no port. --port-offset shifts all of them, and each can be
set explicitly (with one --vehicle only). SIGINT/SIGTERM stop the vehicles (exit code 0).

The wind (the scenario's [truth.wind], one field seeded by the scenario's seed) is read on one
clock for the whole fleet: ``--wind-epoch-ns`` is the host's ``time.time_ns()`` at which it reads
0 (`fleetmpc up` gives every SITL process its own launch time), default this process's start.
"""

import argparse
import dataclasses
import math
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.clock import RealTimeClock
from fleetmpc.errors import ConfigError
from fleetmpc.network import vehicle_host
from fleetmpc.scenario import Scenario, VehicleSpec, load_scenario
from fleetmpc.security.mavlink_signing import read_key_file
from fleetmpc.sitl.autopilot import AutopilotConfig, Profile
from fleetmpc.sitl.telemetry import HEARTBEAT_ID, PX4_GCS_RATES_HZ, PX4_ONBOARD_RATES_HZ
from fleetmpc.sitl.vehicle_group import serve_vehicles
from fleetmpc.sitl.vehicle_server import ServerConfig, UdpEndpoint, VehicleServer

__all__ = ["add_arguments", "build_configs", "run"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    parser.add_argument(
        "--vehicle",
        required=True,
        type=int,
        action="append",
        help="vehicle id (MAVLink system id); repeat it to serve several vehicles in one process",
    )
    parser.add_argument(
        "--autopilot",
        choices=[p.value for p in Profile],
        help="autopilot profile (default: the vehicle's autopilot in the scenario, else px4)",
    )
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument(
        "--host",
        help="address to bind and stream to (default: the vehicle's host in the scenario, else"
        " network.host)",
    )
    parser.add_argument(
        "--gcs-host",
        help="address to stream ground-station telemetry to (default: --host if given, else the"
        " scenario's network.ground_station_host, else network.host)",
    )
    parser.add_argument("--port-offset", type=int, default=0, help="added to every default port")
    parser.add_argument(
        "--mavlink-key",
        type=Path,
        action="append",
        metavar="FILE",
        help="MAVLink 2 signing key file (a passphrase, mode 0600; see `fleetmpc keys`): sign"
        " every frame and act only on frames signed with it (default: signing off); with several"
        " --vehicle, one each, in the same order",
    )
    parser.add_argument(
        "--wind-epoch-ns",
        type=int,
        metavar="NS",
        help="host time.time_ns() at which the fleet's wind clock reads 0, so that every SITL"
        " process of a fleet flies one wind (default: this process's start)",
    )
    parser.add_argument(
        "--boot-origin",
        metavar="NORTH,EAST",
        help="where the autopilot booted (its local frame's origin, as a real autopilot's EKF"
        " origin), in metres from the scenario's origin (default: the vehicle's start)",
    )
    ports = parser.add_argument_group("explicit ports (override the defaults)")
    ports.add_argument("--offboard-port", type=int, help="PX4: port streamed to (offboard API)")
    ports.add_argument(
        "--offboard-local-port", type=int, help="PX4: port bound for the offboard link (0: any)"
    )
    ports.add_argument(
        "--gcs-port", type=int, help="ground-station port streamed to (0: no GCS link)"
    )
    ports.add_argument("--gcs-local-port", type=int, help="port bound for the GCS link (0: any)")
    ports.add_argument("--tcp-port", type=int, help="ArduPilot: TCP server port (0: any)")
    timing = parser.add_argument_group("autopilot timing (simulated seconds)")
    timing.add_argument(
        "--com-of-loss-t", type=float, default=1.0, metavar="S", help="PX4 offboard loss timeout"
    )
    timing.add_argument(
        "--guided-timeout", type=float, default=3.0, metavar="S", help="ArduPilot velocity timeout"
    )
    timing.add_argument(
        "--position-ready",
        type=float,
        default=4.0,
        metavar="S",
        help="ArduPilot: position estimate ready after boot",
    )
    timing.add_argument(
        "--heading-ready",
        type=float,
        default=0.0,
        metavar="S",
        help="PX4: arming refused until S after boot, as a real PX4 SITL refuses it while its"
        " heading estimate settles (4.5-13 s; default 0)",
    )
    timing.add_argument(
        "--com-disarm-prflt",
        type=float,
        default=0.0,
        metavar="S",
        help="PX4 COM_DISARM_PRFLT: armed and never off the ground for S, the vehicle disarms"
        " itself (PX4's default 10; default here 0: never, as offboard flies on the ground)",
    )
    timing.add_argument(
        "--takeoff-stall",
        type=float,
        default=0.0,
        metavar="S",
        help="PX4: a takeoff commanded within S of boot is accepted but never climbs (default 0)",
    )


def _ns(option: str, seconds: float, *, lo: float, hi: float) -> int:
    if not lo <= seconds <= hi:  # also rejects NaN
        raise ConfigError(option, f"must be in [{lo}, {hi}] s, got {seconds}")
    return round(seconds * 1e9)


def _boot_origin(text: str | None, spec: VehicleSpec) -> tuple[float, float]:
    """--boot-origin NORTH,EAST [m], else where the vehicle starts."""
    if text is None:
        return (spec.initial[0], spec.initial[1])
    parts = text.split(",")
    try:
        north, east = (float(p) for p in parts)
    except ValueError:
        raise ConfigError("--boot-origin", f"must be NORTH,EAST in metres, got {text!r}") from None
    if not (math.isfinite(north) and math.isfinite(east)):
        raise ConfigError("--boot-origin", f"must be finite, got {text!r}")
    return (north, east)


def _port(option: str, value: int, *, allow_zero: bool) -> int:
    if not (0 if allow_zero else 1) <= value <= 65535:
        raise ConfigError(option, f"must be a port number, got {value}")
    return value


def _with_heartbeat(rates_hz) -> tuple[tuple[int, float], ...]:
    return ((HEARTBEAT_ID, 1.0), *rates_hz.items())


@dataclass(frozen=True)
class _Defaults:
    offboard_port: int
    offboard_local_port: int
    gcs_port: int
    gcs_local_port: int
    tcp_port: int


def _default_ports(scenario: Scenario, vehicle_id: int, offset: int) -> _Defaults:
    n = scenario.network
    return _Defaults(
        offboard_port=n.offboard_port(vehicle_id) + offset,
        offboard_local_port=n.offboard_local_port(vehicle_id) + offset,
        gcs_port=n.gcs_port + offset,
        gcs_local_port=n.gcs_local_port(vehicle_id) + offset,
        tcp_port=n.ardupilot_tcp_port(vehicle_id) + offset,
    )


_ONE_VEHICLE_OPTIONS = (
    "boot_origin",
    "offboard_port",
    "offboard_local_port",
    "gcs_local_port",
    "tcp_port",
)
"""Options that set one vehicle's value: refused with several --vehicle."""


def build_configs(args: argparse.Namespace) -> list[ServerConfig]:
    """Validate the command line against the scenario, one config per --vehicle; errors name the
    option."""
    scenario = load_scenario(args.scenario, live=True)
    ids = list(args.vehicle)
    if len(set(ids)) != len(ids):
        raise ConfigError("--vehicle", f"each vehicle once, got {ids}")
    if len(ids) > 1:
        for name in _ONE_VEHICLE_OPTIONS:
            if getattr(args, name) is not None:
                option = "--" + name.replace("_", "-")
                raise ConfigError(option, "sets one vehicle's value: give it with one --vehicle")
    keys = args.mavlink_key or []
    if keys and len(keys) != len(ids):
        raise ConfigError("--mavlink-key", f"one per --vehicle ({len(ids)}), got {len(keys)}")
    return [
        _build_config(args, scenario, scenario.vehicle(vid), keys[i] if keys else None)
        for i, vid in enumerate(ids)
    ]


def _build_config(
    args: argparse.Namespace, scenario: Scenario, spec: VehicleSpec, key_file: Path | None
) -> ServerConfig:
    profile = Profile(args.autopilot or spec.autopilot)
    d = _default_ports(scenario, spec.id, args.port_offset)

    def pick(option: str, value: int | None, default: int, *, allow_zero: bool) -> int:
        return _port(option, default if value is None else value, allow_zero=allow_zero)

    autopilot = AutopilotConfig(
        profile=profile,
        speed_limit_m_s=spec.truth.speed_limit_m_s,
        yaw_rate_limit_rad_s=spec.truth.yaw_rate_limit_rad_s,
        takeoff_altitude_m=scenario.site.altitude_m,
        offboard_loss_timeout_ns=_ns("--com-of-loss-t", args.com_of_loss_t, lo=0.05, hi=60.0),
        guided_timeout_ns=_ns("--guided-timeout", args.guided_timeout, lo=0.05, hi=60.0),
        position_ready_ns=_ns("--position-ready", args.position_ready, lo=0.0, hi=600.0),
        heading_ready_ns=_ns("--heading-ready", args.heading_ready, lo=0.0, hi=600.0),
        preflight_disarm_ns=_ns("--com-disarm-prflt", args.com_disarm_prflt, lo=0.0, hi=600.0),
        takeoff_stall_ns=_ns("--takeoff-stall", args.takeoff_stall, lo=0.0, hi=600.0),
        local_origin_m=_boot_origin(args.boot_origin, spec),
    )
    common = dict(
        vehicle=spec,
        site=scenario.site,
        tick_ns=scenario.tick_ns,
        autopilot=autopilot,
        seed=scenario.seed,
        host=args.host or vehicle_host(scenario.network, spec),
        signing_key=None if key_file is None else read_key_file(key_file),
    )
    gcs_port = pick("--gcs-port", args.gcs_port, d.gcs_port, allow_zero=True)
    gcs_link = ()
    if gcs_port:
        gcs_local = pick("--gcs-local-port", args.gcs_local_port, d.gcs_local_port, allow_zero=True)
        # PX4 streams to a ground station by default; ArduPilot only what it is asked for.
        rates = PX4_GCS_RATES_HZ if profile == Profile.PX4 else {}
        gcs_host = args.gcs_host or args.host or scenario.network.ground_station_address
        gcs_link = (
            UdpEndpoint("gcs", gcs_local, gcs_port, _with_heartbeat(rates), remote_host=gcs_host),
        )
    if profile == Profile.ARDUPILOT:
        return ServerConfig(
            **common,
            tcp_port=pick("--tcp-port", args.tcp_port, d.tcp_port, allow_zero=True),
            udp=gcs_link,
        )
    udp = [
        UdpEndpoint(
            "offboard",
            pick(
                "--offboard-local-port",
                args.offboard_local_port,
                d.offboard_local_port,
                allow_zero=True,
            ),
            pick("--offboard-port", args.offboard_port, d.offboard_port, allow_zero=False),
            _with_heartbeat(PX4_ONBOARD_RATES_HZ),
        )
    ]
    return ServerConfig(**common, udp=(*udp, *gcs_link))


@dataclass
class _StopFlag:
    requested: bool = False

    def __call__(self) -> bool:
        return self.requested

    def request(self, signum: int, frame: object) -> None:
        self.requested = True


def run(args: argparse.Namespace) -> int:
    configs = build_configs(args)
    clock = RealTimeClock(speed=args.speed)
    booted_ns = time.time_ns()
    if args.wind_epoch_ns is not None:
        offset = round((booted_ns - args.wind_epoch_ns) * clock.speed)
        configs = [dataclasses.replace(c, wind_clock_offset_ns=offset) for c in configs]
    stop = _StopFlag()
    previous = {s: signal.signal(s, stop.request) for s in (signal.SIGINT, signal.SIGTERM)}
    servers: list[VehicleServer] = []
    try:
        for config in configs:
            servers.append(VehicleServer(config, clock=clock))
        for server in servers:
            config = server.config
            endpoints = ", ".join(f"{k} {v}" for k, v in server.addresses.items())
            signed = ", signed" if config.signing_key is not None else ""
            who = (
                f"vehicle {config.vehicle.id} ({config.autopilot.profile.value}, x{clock.speed:g}"
                f"{signed})"
            )
            print(f"fleetmpc sitl: {who} ready: {endpoints}", flush=True)
        serve_vehicles(servers, clock, stop)
    finally:
        for server in servers:
            server.close()
        for s, handler in previous.items():
            signal.signal(s, handler)
        for server in servers:
            print(f"fleetmpc sitl: stopped {server.summary()}", file=sys.stderr, flush=True)
    return 0
