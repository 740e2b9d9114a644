"""`fleetmpc compose SCENARIO`: the fleet as a docker compose file.

    fleetmpc compose scenarios/paper.toml -o docker/compose.yaml
    docker compose -f docker/compose.yaml up --abort-on-container-exit --exit-code-from gcs

One service per process of `fleetmpc.launch.fleet.fleet_processes`, the list `fleetmpc up` starts,
in the same order and with the same arguments: the Zenoh router, the target, ``sitl-<id>`` and
``agent-<id>`` for every vehicle, and the ground station ``gcs`` last. Every service runs the
image's ``fleetmpc`` entry point with host networking (the scenario's loopback ports, see the
``fleetmpc.*`` labels), ``init: true`` (signals reach the process; no zombie is left), and the one
locally built image with ``pull_policy: never``: the router's service carries the ``build`` section
(context: the repository root, for a file in ``docker/``), so the first ``up`` builds the image and
nothing is ever pulled. The router is healthy once its TCP port accepts; everything else starts
after that, each agent after its SITL, the ground station last.

Differences from `fleetmpc up`, all forced by compose:

- the scenario is opened at its path inside the image (``/app/scenarios/<file>``; the image
  carries ``scenarios/``);
- the ground station writes ``/out/run.rrd`` and ``/out/metrics.json`` to a bind mount
  (``${FLEETMPC_OUT:-../runs/compose}``, a relative path being relative to the compose file's
  directory), has no viewer, and adds the formation gates (``--gate-formation-m``), so its exit
  status is the run's verdict;
- the target gets no ``--duration``: with ``--abort-on-container-exit`` the first container to
  exit stops the fleet, so only the ground station may end the run.
- the run's secrets (`fleetmpc keys`) are made beforehand into a host folder
  (``${FLEETMPC_SECRETS:-../runs/compose/secrets}``) and handed to the services as compose
  secrets: each service gets only its own files, at ``/run/secrets/<file>``, never in the image
  or on a command line (``--insecure`` writes a file without them).

The YAML is written by hand: block mappings, every scalar and flow list JSON-quoted (JSON is
YAML), so no YAML library is needed and the output is byte-for-byte reproducible.
"""

import argparse
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from fleetmpc.errors import ConfigError
from fleetmpc.launch.fleet import FleetOptions, ProcessSpec, fleet_processes
from fleetmpc.network import mavlink_url
from fleetmpc.scenario import Scenario, load_scenario
from fleetmpc.security.zenoh_security import ZenohSecurity

__all__ = [
    "ComposeOptions",
    "add_arguments",
    "compose_document",
    "compose_yaml",
    "render_yaml",
    "run",
]

IMAGE_SCENARIOS_DIR = "/app/scenarios"
"""Where the image (docker/Dockerfile) keeps the repository's scenarios/."""
OUT_IN_CONTAINER = "/out"
"""The ground station's output directory inside its container."""
SECRETS_IN_CONTAINER = "/run/secrets"
"""Where compose mounts a service's secrets."""

_ENV_VAR = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PLAIN_KEY = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
_HEALTH_PROBE = "import socket; socket.create_connection(({host!r}, {port}), 1).close()"


@dataclass(frozen=True)
class ComposeOptions:
    """What a compose file chooses beyond the scenario."""

    speed: float = 1.0
    """Simulated seconds per wall-clock second (`fleetmpc up`'s default)."""
    duration_s: float | None = None
    """Flight time [s] the ground station records; None: the scenario's."""
    scenario_in_image: str | None = None
    """The scenario's path inside the image; None: ``/app/scenarios/<file name>``."""
    image: str = "fleetmpc:local"
    """The image every service runs (built from docker/Dockerfile)."""
    build_context: str = ".."
    """Build context of the image, relative to the compose file (the repository root)."""
    out_dir_var: str = "FLEETMPC_OUT"
    """Environment variable that overrides the host directory mounted at /out."""
    out_dir: str = "../runs/compose"
    """Host directory mounted at /out when the variable is unset (relative: to the file)."""
    gate_formation_m: float | None = 0.1
    """Formation gate of the ground station [m]; None: only its safety gate."""
    secrets_dir_var: str = "FLEETMPC_SECRETS"
    """Environment variable that overrides the host folder of the run's secrets."""
    secrets_dir: str = "../runs/compose/secrets"
    """Host folder of the run's secrets (`fleetmpc keys`) when the variable is unset."""
    insecure: bool = False
    """No secrets: unsigned MAVLink, an open Zenoh bus."""
    host: str | None = None
    """Only the services of the machine with this address (`ProcessSpec.host`: the router's,
    the ground station's or a vehicle's); None: the whole fleet in one file."""

    def __post_init__(self) -> None:
        if not 0.01 <= self.speed <= 1000.0:
            raise ConfigError("--speed", f"must be in [0.01, 1000], got {self.speed:g}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ConfigError("--duration", f"must be > 0, got {self.duration_s:g}")
        if self.scenario_in_image is not None and not self.scenario_in_image.startswith("/"):
            raise ConfigError(
                "--scenario-in-image", f"must be an absolute path, got {self.scenario_in_image!r}"
            )
        if not re.fullmatch(r"[a-z0-9][a-z0-9._/:-]*", self.image):
            raise ConfigError(
                "--image", f"must be a lower-case image reference, got {self.image!r}"
            )
        for flag, var in (
            ("--out-dir-var", self.out_dir_var),
            ("--secrets-dir-var", self.secrets_dir_var),
        ):
            if not _ENV_VAR.fullmatch(var):
                raise ConfigError(flag, f"must be an environment variable name, got {var!r}")
        for flag, path in (("--out-dir", self.out_dir), ("--secrets-dir", self.secrets_dir)):
            if not path or any(c in path for c in ":${}"):
                raise ConfigError(
                    flag, f"must be a directory path without ':', '$' or braces: {path!r}"
                )
        if self.gate_formation_m is not None and not self.gate_formation_m > 0:
            raise ConfigError("--gate-formation-m", f"must be > 0, got {self.gate_formation_m:g}")

    @property
    def out_on_host(self) -> str:
        """The host folder mounted at /out, as the file writes it (the variable, else the
        default)."""
        return f"${{{self.out_dir_var}:-{self.out_dir}}}"

    @property
    def secrets_on_host(self) -> str:
        """The host folder of the run's secrets, as the file writes it."""
        return f"${{{self.secrets_dir_var}:-{self.secrets_dir}}}"


def _escape(arg: str) -> str:
    """An argument as compose passes it on: `$` would start an interpolation."""
    return arg.replace("$", "$$")


def _without_flag(argv: tuple[str, ...], flag: str) -> tuple[str, ...]:
    """`argv` less `flag` and its value."""
    if flag not in argv:
        return argv
    i = argv.index(flag)
    return argv[:i] + argv[i + 2 :]


def _project_name(scenario: Scenario) -> str:
    name = re.sub(r"[^a-z0-9_-]+", "-", scenario.name.lower()).strip("-_")
    return f"fleetmpc-{name}" if name else "fleetmpc"


def _labels(spec: ProcessSpec, scenario: Scenario) -> dict[str, str]:
    """What a container is and which loopback endpoint it serves or listens on."""
    net = scenario.network
    labels = {"fleetmpc.role": spec.role}
    if spec.role == "router":
        labels["fleetmpc.zenoh"] = f"tcp/{net.router_address}:{net.zenoh_port}"
    elif spec.role in ("sitl", "agent"):
        vehicle_id = int(spec.argv[spec.argv.index("--vehicle") + 1])
        vehicle = scenario.vehicle(vehicle_id)
        labels["fleetmpc.vehicle"] = str(vehicle_id)
        labels["fleetmpc.autopilot"] = vehicle.autopilot
        labels["fleetmpc.mavlink"] = mavlink_url(net, vehicle)
    elif spec.role == "gcs":
        labels["fleetmpc.mavlink"] = f"udpin:{net.ground_station_address}:{net.gcs_port}"
    return labels


def _secret_files(spec: ProcessSpec, scenario: Scenario) -> list[str]:
    """The files of the run's secrets a service needs: those its arguments name (a path, or
    the FILE of ``ID=FILE``), and the router's (users, access list, certificate)."""
    inside = SECRETS_IN_CONTAINER + "/"
    paths = [a.partition("=")[2] if a[:1].isdigit() else a for a in spec.argv]  # (ID=FILE)
    files = [PurePosixPath(a).name for a in paths if a.startswith(inside)]
    if spec.role == "router":
        net = scenario.network
        bus = ZenohSecurity(
            Path(SECRETS_IN_CONTAINER),
            fleet=scenario.name,
            vehicle_ids=tuple(scenario.vehicle_ids),
            router_host=net.router_address,
            router_port=net.zenoh_port,
            tls=True,
            mutual_tls=False,
        )
        files += [p.name for p in bus.router_files()]
    return files


def compose_document(scenario: Scenario, *, scenario_name: str, options: ComposeOptions) -> dict:
    """The compose file as plain data: ``{"name": ..., "services": {...}}``.

    `scenario_name` is the scenario's file name (its path inside the image is derived from it
    unless `options.scenario_in_image` says otherwise).
    """
    in_image = options.scenario_in_image or str(
        PurePosixPath(IMAGE_SCENARIOS_DIR) / PurePosixPath(scenario_name).name
    )
    out = PurePosixPath(OUT_IN_CONTAINER)
    specs = fleet_processes(
        scenario,
        FleetOptions(
            scenario_path=in_image,
            speed=options.speed,
            duration_s=options.duration_s,
            rrd=str(out / "run.rrd"),
            metrics=str(out / "metrics.json"),
            viewer="none",
            secrets_dir=None if options.insecure else SECRETS_IN_CONTAINER,
        ),
    )
    if options.host is not None:
        hosts = sorted({s.host for s in specs})
        specs = [s for s in specs if s.host == options.host]
        if not specs:
            raise ConfigError(
                "--host", f"no process of the fleet runs on {options.host} (hosts: {hosts})"
            )
    net = scenario.network
    secrets: dict[str, dict] = {}
    here = {s.name for s in specs}
    router = next((s.name for s in specs if s.role == "router"), None)
    started: list[str] = []
    services: dict[str, dict] = {}
    for spec in specs:
        argv = spec.argv
        service: dict = {"image": options.image}
        if spec is specs[0]:  # (the router's, in a whole fleet's file)
            service["build"] = {
                "context": options.build_context,
                "dockerfile": "docker/Dockerfile",
                "network": "host",
            }
        service["pull_policy"] = "never"
        service["init"] = True
        service["network_mode"] = "host"
        if spec.role != "router":
            # (on another machine the router is waited for by the client: CONNECT_WAIT_S)
            depends = {} if router is None else {router: {"condition": "service_healthy"}}
            sitl = spec.name.replace("agent-", "sitl-", 1)
            if spec.role == "agent" and sitl in here:
                depends[sitl] = {"condition": "service_started"}
            elif spec.role == "gcs":
                depends.update({name: {"condition": "service_started"} for name in started})
            if depends:
                service["depends_on"] = depends
            started.append(spec.name)
        if spec.role == "target":
            argv = _without_flag(argv, "--duration")
        if spec.role == "gcs":
            if options.gate_formation_m is not None:
                argv = (*argv, "--gate-formation-m", f"{options.gate_formation_m:g}")
            service["volumes"] = [f"{options.out_on_host}:{OUT_IN_CONTAINER}"]
        service["command"] = [_escape(a) for a in argv]
        if not options.insecure:
            names = _secret_files(spec, scenario)
            service["secrets"] = names
            secrets.update({n: {"file": f"{options.secrets_on_host}/{n}"} for n in names})
        if spec.role == "router":
            probe = _HEALTH_PROBE.format(host=net.router_address, port=net.zenoh_port)
            service["healthcheck"] = {
                "test": ["CMD", "python", "-c", probe],
                "interval": "1s",
                "timeout": "5s",
                "retries": 60,
            }
        service["labels"] = _labels(spec, scenario)
        services[spec.name] = service
    name = _project_name(scenario)
    if options.host is not None:
        name += "-" + re.sub(r"[^a-z0-9_-]+", "-", options.host.lower())
    document = {"name": name, "services": services}
    return document | ({"secrets": dict(sorted(secrets.items()))} if secrets else {})


def _key(key: str) -> str:
    return key if _PLAIN_KEY.fullmatch(key) else json.dumps(key)


def _scalar(value) -> str:
    if value is None or isinstance(value, bool | int | float | str):
        return json.dumps(value)
    if isinstance(value, list) and all(
        isinstance(v, str | int | float | bool) or v is None for v in value
    ):
        return "[" + ", ".join(json.dumps(v) for v in value) + "]"
    raise TypeError(f"no YAML form for {value!r}")


def render_yaml(document: dict, *, indent: int = 0) -> str:
    """Block-style YAML of nested dicts whose leaves are scalars or lists of scalars."""
    lines = []
    pad = " " * indent
    for key, value in document.items():
        if isinstance(value, dict):
            lines.append(f"{pad}{_key(key)}:")
            lines.append(render_yaml(value, indent=indent + 2).rstrip("\n"))
        else:
            lines.append(f"{pad}{_key(key)}: {_scalar(value)}")
    return "\n".join(lines) + "\n"


def _invocation(scenario_path: str, options: ComposeOptions) -> str:
    """The `fleetmpc compose` command line that regenerates a file (defaults left out)."""
    parts = ["fleetmpc", "compose", scenario_path]
    defaults = ComposeOptions()
    flags = (
        ("--speed", "speed"),
        ("--duration", "duration_s"),
        ("--scenario-in-image", "scenario_in_image"),
        ("--image", "image"),
        ("--out-dir-var", "out_dir_var"),
        ("--out-dir", "out_dir"),
        ("--gate-formation-m", "gate_formation_m"),
        ("--secrets-dir-var", "secrets_dir_var"),
        ("--secrets-dir", "secrets_dir"),
        ("--insecure", "insecure"),
        ("--host", "host"),
    )
    for flag, field in flags:
        value = getattr(options, field)
        if value == getattr(defaults, field):
            continue
        if value is None:
            parts += [flag, "none"]
        elif value is True:
            parts += [flag]
        elif isinstance(value, float):
            parts += [flag, f"{value:g}"]
        else:
            parts += [flag, value]
    return " ".join(parts)


def compose_yaml(scenario_path: str, options: ComposeOptions | None = None) -> str:
    """The compose file of the scenario at `scenario_path`, as text."""
    options = options or ComposeOptions()
    scenario = load_scenario(scenario_path, live=True)
    doc = compose_document(scenario, scenario_name=Path(scenario_path).name, options=options)
    duration = scenario.duration_s if options.duration_s is None else options.duration_s
    header = [
        f"# The {scenario.name} fleet under docker compose: {len(scenario.vehicles)} UAVs, "
        f"{duration:g} s of fleet time at x{options.speed:g}.",
        f"# Generated by `{_invocation(scenario_path, options)}`: regenerate it, do not edit it.",
        "#",
        *(
            (
                f"# The processes of the machine at {options.host} only ("
                + ", ".join(doc["services"])
                + ").",
                "#",
            )
            if options.host is not None
            else ()
        ),
        "#   docker compose -f <this file> up"
        + (" --abort-on-container-exit --exit-code-from gcs" if "gcs" in doc["services"] else ""),
        "#",
        *(
            ()
            if options.insecure
            else (
                "# Make the run's secrets first (MAVLink keys, Zenoh users and certificates) into",
                f"# {options.secrets_on_host}:",
                "#",
                f"#   fleetmpc keys {scenario_path} -o <that folder>",
                "#",
                *(
                    (
                        "# (once for the whole fleet; this machine needs only the files under",
                        "# `secrets:` at the end)",
                        "#",
                    )
                    if options.host is not None
                    else ()
                ),
            )
        ),
        *(
            (
                "# The exit status is the ground station's: 0 when every gate held. It writes"
                " run.rrd and",
                f"# metrics.json to {options.out_on_host} (a relative path is relative to",
                "# this file's directory).",
            )
            if "gcs" in doc["services"]
            else ()
        ),
        "# Host networking: Linux hosts only.",
        "",
    ]
    return "\n".join(header) + render_yaml(doc)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = ComposeOptions()
    parser.add_argument(
        "scenario", help="scenario TOML file (in scenarios/, which the image holds)"
    )
    parser.add_argument(
        "--speed", type=float, default=d.speed, help="simulated seconds per second (default: 1)"
    )
    parser.add_argument(
        "--duration", type=float, metavar="S", help="fleet time to fly (default: scenario)"
    )
    parser.add_argument(
        "--scenario-in-image",
        metavar="PATH",
        help=f"the scenario's path in the image (default: {IMAGE_SCENARIOS_DIR}/FILE)",
    )
    parser.add_argument("--image", default=d.image, help=f"image to run (default: {d.image})")
    parser.add_argument(
        "--out-dir-var",
        default=d.out_dir_var,
        metavar="NAME",
        help=f"variable naming the host output directory (default: {d.out_dir_var})",
    )
    parser.add_argument(
        "--out-dir",
        default=d.out_dir,
        metavar="DIR",
        help=f"host output directory if the variable is unset (default: {d.out_dir})",
    )
    parser.add_argument(
        "--gate-formation-m",
        default=f"{d.gate_formation_m:g}",
        metavar="M",
        help="ground station's formation gate in metres, or 'none' (default: 0.1)",
    )
    parser.add_argument(
        "--secrets-dir-var",
        default=d.secrets_dir_var,
        metavar="NAME",
        help=f"variable naming the host folder of the secrets (default: {d.secrets_dir_var})",
    )
    parser.add_argument(
        "--secrets-dir",
        default=d.secrets_dir,
        metavar="DIR",
        help=f"host folder of the secrets (`fleetmpc keys`) if the variable is unset (default:"
        f" {d.secrets_dir})",
    )
    parser.add_argument(
        "--insecure", action="store_true", help="no secrets: unsigned MAVLink, an open Zenoh bus"
    )
    parser.add_argument(
        "--host",
        metavar="ADDR",
        help="only the processes of the machine at this address (the scenario's router_host,"
        " ground_station_host or a vehicle's host): one file per machine of a fleet across"
        " machines (default: the whole fleet)",
    )
    parser.add_argument("-o", "--output", type=Path, help="write here instead of stdout")


def _gate(text: str) -> float | None:
    if text.lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise ConfigError(
            "--gate-formation-m", f"must be a number or 'none', got {text!r}"
        ) from None


def run(args: argparse.Namespace) -> int:
    options = ComposeOptions(
        speed=args.speed,
        duration_s=args.duration,
        scenario_in_image=args.scenario_in_image,
        image=args.image,
        out_dir_var=args.out_dir_var,
        out_dir=args.out_dir,
        gate_formation_m=_gate(args.gate_formation_m),
        secrets_dir_var=args.secrets_dir_var,
        secrets_dir=args.secrets_dir,
        insecure=args.insecure,
        host=args.host,
    )
    text = compose_yaml(args.scenario, options)
    if args.output is None:
        sys.stdout.write(text)
    else:
        args.output.write_text(text)
    return 0
