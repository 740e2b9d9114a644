"""A fleet's secrets, made per run: `fleetmpc keys SCENARIO -o DIR`.

    fleetmpc keys scenarios/paper.toml -o keys/

One MAVLink 2 signing key per vehicle (``mavlink-<id>.key``: a random passphrase whose SHA-256
is the key, as MAVProxy's ``signing setup`` derives it; docs/design.md, "Security"). The
directory is created with mode 0700 and every file in it with 0600; nothing is overwritten.
`fleetmpc up` makes a fresh set in its run directory unless given one (``--keys DIR``), and
hands each process the path of its own file, never the secret on a command line.
"""

import argparse
import os
from pathlib import Path

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.mavlink_signing import key_file_name, write_key_file
from fleetmpc.scenario import Scenario, load_scenario

__all__ = ["add_arguments", "make_keys", "run"]


def make_keys(scenario: Scenario, directory: Path, *, vehicle_ids=None) -> Path:
    """Write the fleet's secrets into `directory` (created 0700; must not hold them already):
    a MAVLink signing key for each of `vehicle_ids` (default: every vehicle)."""
    directory = Path(directory)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(directory, 0o700)
    ids = scenario.vehicle_ids if vehicle_ids is None else list(vehicle_ids)
    for vid in ids:
        write_key_file(directory / key_file_name(vid))
    return directory


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario TOML file")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, metavar="DIR", help="folder for the keys"
    )


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    existing = [
        p for p in (args.output / key_file_name(v) for v in scenario.vehicle_ids) if p.exists()
    ]
    if existing:
        raise ConfigError("--output", f"{existing[0]} exists; give an empty folder")
    make_keys(scenario, args.output)
    print(f"fleetmpc keys: {len(scenario.vehicles)} MAVLink signing keys in {args.output}")
    return 0
