"""The `fleetmpc` console script: one entry point, one subcommand per job.

Each subcommand lives in its own module exposing `add_arguments(parser)` and `run(args) -> int`;
modules are imported only when their subcommand runs, so `fleetmpc --help` stays fast.
"""

import argparse
import atexit
import importlib
import os
import sys
from types import ModuleType

from fleetmpc.errors import FleetMpcError

__all__ = ["entry", "main"]

# subcommand -> (module, one-line help)
_COMMANDS: dict[str, tuple[str, str]] = {
    "check": (
        "fleetmpc.check.feasibility",
        "feasibility report of a scenario, before anything flies",
    ),
    "sim": ("fleetmpc.lockstep.simulate", "in-process lockstep simulation of a whole fleet"),
    "bench": (
        "fleetmpc.bench.step",
        "per-agent step timing against a cvxpy rebuild, and lockstep speed",
    ),
    "suite": (
        "fleetmpc.lockstep.suite",
        "fly every scenario of a folder over seeds, learning on and off; gates",
    ),
    "sweep": (
        "fleetmpc.lockstep.sweep",
        "fly scenarios x varied fields x seeds on a cluster engine; a table and figures",
    ),
    "sitl": (
        "fleetmpc.sitl.cli",
        "one simulated vehicle behind a PX4 or ArduPilot MAVLink interface",
    ),
    "agent": (
        "fleetmpc.onboard.cli",
        "the onboard agent of one vehicle: MAVLink autopilot + Zenoh plans",
    ),
    "target": (
        "fleetmpc.targets.process",
        "fly the scripted target and publish its observations",
    ),
    "zenoh-router": (
        "fleetmpc.protocol.zenoh_router",
        "a Zenoh router for a fleet (compose, multi-host)",
    ),
    "report": ("fleetmpc.gcs.report", "figures and metrics from a Rerun recording (.rrd)"),
    "gcs": (
        "fleetmpc.gcs.ground_station",
        "ground station: telemetry, plans and metrics into Rerun",
    ),
    "up": ("fleetmpc.launch.up", "start a whole fleet on this machine, watch it, bring it down"),
    "compose": (
        "fleetmpc.launch.compose",
        "the fleet as a docker compose file (one service per process)",
    ),
    "keys": ("fleetmpc.security.secrets", "a fleet's secrets: one MAVLink signing key per vehicle"),
    "real-autopilots": (
        "fleetmpc.launch.real_autopilots",
        "the fleet measured against real PX4 and ArduCopter SITLs (built by their projects)",
    ),
    "home": (
        "fleetmpc.launch.home",
        "where to boot a real autopilot's SITL so it starts where its vehicle starts",
    ),
}


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; its exit status."""
    return _dispatch(argv)[0]


def entry() -> None:
    """The console script (and ``python -m fleetmpc.cli``): `main`, then exit with its status.

    A fleet process (its module sets ``EXIT_WITHOUT_TEARDOWN``: agent, gcs, target, sitl,
    zenoh-router, and `up`, which stops them) has closed and flushed everything it wrote when
    `run` returns, so after the atexit hooks it leaves with `os._exit`: the interpreter's
    teardown of its Zenoh, Rerun and pymavlink objects took 0.5-2.5 s per process when a whole
    fleet stopped at once, longer than the rest of `fleetmpc up`'s shutdown.
    """
    code, module = _dispatch(None)
    if getattr(module, "EXIT_WITHOUT_TEARDOWN", False):
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def _dispatch(argv: list[str] | None) -> tuple[int, ModuleType]:
    parser = argparse.ArgumentParser(prog="fleetmpc", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_module, help_text) in _COMMANDS.items():
        sub.add_parser(name, help=help_text, description=help_text)
    # Parse the subcommand name first, then let only that module define its arguments.
    args_list = sys.argv[1:] if argv is None else argv
    known, _ = parser.parse_known_args(args_list[:1] or ["--help"])
    module_name, help_text = _COMMANDS[known.command]
    module = importlib.import_module(module_name)
    full = argparse.ArgumentParser(prog=f"fleetmpc {known.command}", description=help_text)
    module.add_arguments(full)
    args = full.parse_args(args_list[1:])
    try:
        return int(module.run(args) or 0), module
    except FleetMpcError as e:
        print(f"fleetmpc {known.command}: error: {e}", file=sys.stderr)
        return 2, module
    except KeyboardInterrupt:
        return 130, module


if __name__ == "__main__":
    entry()
