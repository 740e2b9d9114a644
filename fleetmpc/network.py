"""The fleet's network: which host and port each process binds to or sends to.

Vehicle (system id) i uses each base port plus i - 1 (ArduPilot's TCP ports: plus 10 (i - 1)),
as PX4's and ArduPilot's multi-vehicle SITLs number theirs. The ports a vehicle streams to are
PX4's (the offboard API's 14540 + i - 1, the ground station's 14550), so a real PX4 SITL
instance i - 1 flown as vehicle i streams where that vehicle's agent listens; the ports our
simulated vehicles bind or serve are PX4's and ArduPilot's plus 10000 (UDP 24580 + i - 1 and
28570 + i - 1, TCP 15760 + 10 (i - 1)), so they never take one a real SITL binds (PX4 instance
n: 14580 + n and 18570 + n; ArduCopter instance n: TCP 5760 + 10 n to 5763 + 10 n) and a fleet
that mixes both starts with the defaults. `check_ports` refuses a fleet two of whose processes
would share a port, naming the field the clash derives from.
"""

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from fleetmpc.errors import ConfigError

if TYPE_CHECKING:
    from fleetmpc.scenario import VehicleSpec

__all__ = [
    "ARDUCOPTER_TCP_BASE_PORT",
    "Network",
    "PX4_GCS_LOCAL_BASE_PORT",
    "PX4_OFFBOARD_LOCAL_BASE_PORT",
    "PX4_OFFBOARD_REMOTE_BASE_PORT",
    "SITL_GCS_LOCAL_BASE_PORT",
    "SITL_OFFBOARD_LOCAL_BASE_PORT",
    "check_ports",
    "mavlink_url",
    "vehicle_host",
]


@dataclass(frozen=True)
class Network:
    """Loopback ports of a fleet; vehicle (system id) i uses the base ports plus (i - 1)."""

    host: str = "127.0.0.1"
    """Address every process binds to or sends to, unless the fields below (and a vehicle's
    `host`) place some of them on other machines."""
    router_host: str | None = None
    """Address of the Zenoh router (it binds there; every fleet process connects there);
    None: `host`."""
    ground_station_host: str | None = None
    """Address of the ground station (every vehicle streams its telemetry there); None:
    `host`."""
    offboard_base_port: int = 14540
    """PX4 offboard-API UDP port of vehicle 1 (vehicle i: + i - 1)."""
    gcs_port: int = 14550
    """UDP port every vehicle streams to for ground stations."""
    ardupilot_tcp_base_port: int = 15760
    """TCP port our ArduPilot-profile vehicle 1 serves (vehicle i: + 10 * (i - 1)): ArduPilot
    SITL's 5760 + 10000, clear of a real ArduCopter SITL's."""
    zenoh_port: int = 7447
    """TCP port of the Zenoh router or first peer."""
    offboard_local_base_port: int | None = None
    """PX4: the UDP port vehicle 1's SITL binds its offboard link to (vehicle i: + i - 1);
    None: 24580 (PX4's 14580 + 10000, clear of a real PX4 SITL's), moved with
    `offboard_base_port`."""
    gcs_local_base_port: int | None = None
    """The UDP port vehicle 1's SITL binds its ground-station link to (vehicle i: + i - 1);
    None: 28570 (PX4's 18570 + 10000), moved with `gcs_port`."""

    def __post_init__(self) -> None:
        for name in ("host", "router_host", "ground_station_host"):
            value = getattr(self, name)
            if value is None and name != "host":
                continue
            if not isinstance(value, str) or not value:
                raise ConfigError(
                    f"network.{name}", f"must be a host name or address, got {value!r}"
                )
        for name in (
            "offboard_base_port",
            "gcs_port",
            "ardupilot_tcp_base_port",
            "zenoh_port",
            "offboard_local_base_port",
            "gcs_local_base_port",
        ):
            port = getattr(self, name)
            if port is None and name.endswith("_local_base_port"):
                continue
            if not isinstance(port, int) or not 1 <= port <= 65535:
                raise ConfigError(f"network.{name}", f"must be a port number, got {port!r}")

    @property
    def router_address(self) -> str:
        """Where the Zenoh router is."""
        return self.router_host or self.host

    @property
    def ground_station_address(self) -> str:
        """Where the ground station listens for the vehicles' telemetry."""
        return self.ground_station_host or self.host

    def offboard_port(self, vehicle_id: int) -> int:
        """PX4: the offboard-API UDP port vehicle `vehicle_id` streams to (agents listen here)."""
        return _derived_port("network.offboard_base_port", self.offboard_base_port, vehicle_id - 1)

    def offboard_local_port(self, vehicle_id: int) -> int:
        """PX4: the UDP port vehicle `vehicle_id`'s SITL binds its offboard link to (24580 +
        i - 1 on the default network, moved with `offboard_base_port`)."""
        base = self.offboard_local_base_port
        if base is None:
            base = (
                SITL_OFFBOARD_LOCAL_BASE_PORT + self.offboard_base_port - Network.offboard_base_port
            )
        return _derived_port("network.offboard_local_base_port", base, vehicle_id - 1)

    def gcs_local_port(self, vehicle_id: int) -> int:
        """The UDP port vehicle `vehicle_id`'s SITL binds its ground-station link to (28570 +
        i - 1 on the default network, moved with `gcs_port`)."""
        base = self.gcs_local_base_port
        if base is None:
            base = SITL_GCS_LOCAL_BASE_PORT + self.gcs_port - Network.gcs_port
        return _derived_port("network.gcs_local_base_port", base, vehicle_id - 1)

    def ports(self, vehicles: "tuple[VehicleSpec, ...]") -> list[tuple[str, int, str, str]]:
        """Every port a fleet of `vehicles` binds or streams to on `host`, as (protocol, port,
        whose, the field it derives from)."""
        out = [
            ("udp", self.gcs_port, "the ground station", "network.gcs_port"),
            ("tcp", self.zenoh_port, "the Zenoh router", "network.zenoh_port"),
        ]
        for v in vehicles:
            if v.autopilot == "ardupilot":
                out.append(
                    (
                        "tcp",
                        self.ardupilot_tcp_port(v.id),
                        f"vehicle {v.id}'s ArduPilot link",
                        "network.ardupilot_tcp_base_port",
                    )
                )
            else:
                out.append(
                    (
                        "udp",
                        self.offboard_port(v.id),
                        f"vehicle {v.id}'s offboard link",
                        "network.offboard_base_port",
                    )
                )
                out.append(
                    (
                        "udp",
                        self.offboard_local_port(v.id),
                        f"vehicle {v.id}'s SITL offboard port",
                        "network.offboard_local_base_port",
                    )
                )
            out.append(
                (
                    "udp",
                    self.gcs_local_port(v.id),
                    f"vehicle {v.id}'s SITL ground-station port",
                    "network.gcs_local_base_port",
                )
            )
        return out

    def ardupilot_tcp_port(self, vehicle_id: int) -> int:
        """ArduPilot: the TCP port vehicle `vehicle_id`'s SITL serves (agents connect here)."""
        return _derived_port(
            "network.ardupilot_tcp_base_port", self.ardupilot_tcp_base_port, 10 * (vehicle_id - 1)
        )


SUGGEST_WITHIN = 1000
"""How far above a clashing field's value `check_ports` looks for one that clears every clash."""
PX4_OFFBOARD_REMOTE_BASE_PORT = 14540
"""A real PX4 SITL sends its offboard-API link here (instance n: + n), where an agent listens."""
PX4_OFFBOARD_LOCAL_BASE_PORT = 14580
"""A real PX4 SITL binds its offboard-API link here (instance n: + n)."""
ARDUCOPTER_TCP_BASE_PORT = 5760
"""A real ArduCopter SITL serves MAVLink on this TCP port (instance n: + 10 n)."""
PX4_GCS_LOCAL_BASE_PORT = 18570
"""A real PX4 SITL binds its ground-station link here (instance n: + n)."""
SITL_OFFBOARD_LOCAL_BASE_PORT = PX4_OFFBOARD_LOCAL_BASE_PORT + 10_000
"""Our PX4-profile vehicle 1 binds its offboard link here by default (vehicle i: + i - 1)."""
SITL_GCS_LOCAL_BASE_PORT = PX4_GCS_LOCAL_BASE_PORT + 10_000
"""Our vehicle 1 binds its ground-station link here by default (vehicle i: + i - 1)."""


def check_ports(network: Network, vehicles: "tuple[VehicleSpec, ...]") -> None:
    """Refuse a fleet two of whose processes would use the same port, naming the field and,
    when there is one, the nearest value above it that clears every clash."""
    clash = _first_clash(network, vehicles)
    if clash is None:
        return
    field, message = clash
    name = field.removeprefix("network.")
    start = getattr(network, name)
    if start is None:  # a local base that follows another field's: name the field only
        raise ConfigError(field, message)
    for value in range(start + 1, min(start + SUGGEST_WITHIN, 65535) + 1):
        try:
            moved = replace(network, **{name: value})
            free = _first_clash(moved, vehicles) is None
        except ConfigError:  # (a derived port past 65535)
            break
        if free:
            raise ConfigError(field, f"{message} ({name} = {value} in [network] clears it)")
    raise ConfigError(field, message)


def _first_clash(network: Network, vehicles: "tuple[VehicleSpec, ...]") -> tuple[str, str] | None:
    """The field and the message of the first port two processes of the fleet would share."""
    seen: dict[tuple[str, int], str] = {}
    for proto, port, whose, field in network.ports(vehicles):
        other = seen.get((proto, port))
        if other is not None:
            return field, f"{proto.upper()} port {port} of {whose} is already {other}'s"
        seen[(proto, port)] = whose
    return None


def _derived_port(field: str, base: int, step: int) -> int:
    port = base + step
    if not 1 <= port <= 65535:
        raise ConfigError(field, f"{base} + {step} is not a port number")
    return port


def mavlink_url(network: Network, vehicle: "VehicleSpec") -> str:
    """The pymavlink URL of a vehicle's autopilot as its SITL serves it by default.

    PX4: ``udpin:HOST:offboard_base_port + i - 1`` (the SITL streams there, the agent listens);
    ArduPilot: ``tcp:HOST:ardupilot_tcp_base_port + 10 (i - 1)``; i is the vehicle's system id.
    """
    host = vehicle_host(network, vehicle)
    if vehicle.autopilot == "ardupilot":
        return f"tcp:{host}:{network.ardupilot_tcp_port(vehicle.id)}"
    return f"udpin:{host}:{network.offboard_port(vehicle.id)}"


def vehicle_host(network: Network, vehicle: "VehicleSpec") -> str:
    """The address of a vehicle's companion computer (its agent and autopilot link)."""
    return vehicle.host or network.host
