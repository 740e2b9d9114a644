"""A fleet's secrets, made per run: `fleetmpc keys SCENARIO -o DIR`.

    fleetmpc keys scenarios/paper.toml -o keys/

- one MAVLink 2 signing key per vehicle (``mavlink-<id>.key``: a random passphrase whose SHA-256
  is the key, as MAVProxy's ``signing setup`` derives it);
- the Zenoh bus's users, access list and TLS certificates (`fleetmpc.security.zenoh_security`:
  ``zenoh-<user>.json5`` per process, the router's dictionary and certificate).

See docs/design.md, "Security". The directory is created with mode 0700 and every file in it with
0600; nothing is overwritten. `fleetmpc up` makes a fresh set in its run directory unless given
one (``--keys DIR``), and hands each process the path of its own files, never a secret on a
command line.
"""

import argparse
from pathlib import Path

from fleetmpc.errors import ConfigError
from fleetmpc.scenario import Scenario, load_scenario
from fleetmpc.security.mavlink_signing import key_file_name, write_key_file
from fleetmpc.security.zenoh_security import ZenohSecurity, make_zenoh_security

__all__ = ["add_arguments", "check_keys", "make_keys", "run"]


def make_keys(
    scenario: Scenario, directory: Path, *, fleet: str | None = None, mutual_tls: bool = False
) -> Path:
    """Write the fleet's secrets into `directory` (created 0700; must not hold them already):
    a MAVLink signing key per vehicle, and the Zenoh bus's (fleet name `fleet`, default the
    scenario's; client certificates too with `mutual_tls`)."""
    directory = Path(directory)
    net = scenario.network
    make_zenoh_security(  # (creates the folder, 0700)
        directory,
        fleet=fleet or scenario.name,
        vehicle_ids=scenario.vehicle_ids,
        router_host=net.router_address,
        router_port=net.zenoh_port,
        mutual_tls=mutual_tls,
    )
    for vid in scenario.vehicle_ids:
        write_key_file(directory / key_file_name(vid))
    return directory


def check_keys(scenario: Scenario, directory: Path, *, fleet: str | None = None) -> Path:
    """`directory` if it holds this fleet's secrets (made by `make_keys` for the same fleet name,
    vehicles and router address), else ConfigError naming ``--keys`` and what differs."""
    directory = Path(directory)
    bus = ZenohSecurity.load(directory, field="--keys")
    net = scenario.network
    want = {
        "fleet": fleet or scenario.name,
        "vehicles": tuple(scenario.vehicle_ids),
        "router": f"{net.router_address}:{net.zenoh_port}",
    }
    have = {
        "fleet": bus.fleet,
        "vehicles": bus.vehicle_ids,
        "router": f"{bus.router_host}:{bus.router_port}",
    }
    for what, value in want.items():
        if have[what] != value:
            raise ConfigError(
                "--keys", f"{directory} was made for {what} {have[what]}, this fleet has {value}"
            )
    missing = [v for v in scenario.vehicle_ids if not (directory / key_file_name(v)).exists()]
    if missing:
        raise ConfigError("--keys", f"{directory} has no MAVLink key for vehicles {missing}")
    return directory


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario TOML file")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="DIR", help="folder for the keys"
    )
    parser.add_argument("--fleet", help="fleet name on Zenoh (default: the scenario's name)")
    parser.add_argument(
        "--mutual-tls",
        action="store_true",
        help="every process also shows a certificate of the run's CA to the router",
    )


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    if args.output.exists() and any(args.output.iterdir()):
        raise ConfigError("--output", f"{args.output} is not empty; give a new folder")
    make_keys(scenario, args.output, fleet=args.fleet, mutual_tls=args.mutual_tls)
    print(
        f"fleetmpc keys: {len(scenario.vehicles)} MAVLink signing keys and the Zenoh bus's"
        f" users, access list and certificates in {args.output}"
    )
    return 0
