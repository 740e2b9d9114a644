"""`fleetmpc agent`: the onboard agent of one vehicle (MAVLink autopilot + Zenoh plans).

    fleetmpc agent --scenario scenarios/paper.toml --vehicle 1 \
        --zenoh-connect 127.0.0.1:7447 --wait-epoch --speed 4

MAVLink: ``--mavlink URL`` (any pymavlink URL), by default the vehicle's SITL as the scenario
describes it (`fleetmpc.network.mavlink_url`: PX4 ``udpin:HOST:14540 + I - 1``, ArduPilot
``tcp:HOST:15760 + 10 (I - 1)``). Zenoh: by default a member of the fleet's full peer mesh on
explicit endpoints (`fleetmpc.protocol.zenoh_config.options_from_args`), scouting off;
``--zenoh-connect`` makes a client of a router, ``--zenoh-config FILE`` loads a Zenoh config file.
Fleet time (`fleetmpc.onboard.runner`): ``--epoch-ns`` gives the epoch, ``--wait-epoch`` takes the
first one the ground station announces on the bus; the agent connects, streams and engages either
way, and steps once the epoch is known. An announced speed other than ``--speed`` is an error (exit
2). SIGINT/SIGTERM: hold the vehicle where it is (`fleetmpc.onboard.setpoints.wind_down`: position
setpoints for 50 ms, then HOLD), close the Zenoh session and the link, print a JSON summary on
stdout, exit 0.
"""

import argparse
import contextlib
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from fleetmpc.bus.faults import LINK_KINDS, FaultLayer, LinkFaults, load_faults
from fleetmpc.bus.open_bus import add_bus_arguments, open_fleet_bus
from fleetmpc.clock import FleetClock
from fleetmpc.errors import ConfigError
from fleetmpc.network import mavlink_url
from fleetmpc.onboard.agent_feed import agent_for
from fleetmpc.onboard.autopilot_link import AutopilotLinkError, open_autopilot_link
from fleetmpc.onboard.runner import FleetRunner, RunnerSettings
from fleetmpc.onboard.setpoints import COMMAND_LIFETIME_PERIODS, SetpointStreamer, wind_down
from fleetmpc.scenario import load_scenario
from fleetmpc.security.mavlink_signing import read_key_file

__all__ = ["add_arguments", "run"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    parser.add_argument("--vehicle", required=True, type=int, help="vehicle id (MAVLink system id)")
    parser.add_argument(
        "--mavlink",
        help="pymavlink URL of the autopilot (default: the vehicle's SITL per the scenario)",
    )
    parser.add_argument(
        "--mavlink-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing key file (a passphrase, mode 0600; see `fleetmpc keys`): sign"
        " what is sent to the autopilot and hear only frames signed with it (default: unsigned)",
    )
    parser.add_argument(
        "--target-system",
        type=int,
        metavar="ID",
        help="fly only the autopilot with this MAVLink system id (default: the first autopilot"
        " heard on the link, whatever its id)",
    )
    add_bus_arguments(parser)
    epoch = parser.add_mutually_exclusive_group()
    epoch.add_argument(
        "--epoch-ns", type=int, default=None, help="host time.time_ns() of fleet time 0"
    )
    epoch.add_argument(
        "--wait-epoch",
        action="store_true",
        help="take the epoch the ground station announces on the bus (steps start then)",
    )
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument(
        "--setpoint-rate-hz",
        type=float,
        default=20.0,
        help="setpoint stream rate in simulated time (>= 10)",
    )
    parser.add_argument("--duration", type=float, default=None, help="stop at this fleet time [s]")
    parser.add_argument(
        "--connect-timeout",
        type=float,
        default=60.0,
        help="wall seconds for the autopilot's HEARTBEAT and first pose (default 60: a real"
        " ArduPilot SITL booting cold reports a position after its estimator has settled)",
    )
    parser.add_argument(
        "--engage-timeout",
        type=float,
        default=60.0,
        help="wall seconds for each engage step (mode, arm, takeoff; default 60: ArduCopter"
        " refuses to arm until its pre-arm checks pass, some 40 s after a cold boot)",
    )
    parser.add_argument("--no-engage", action="store_true", help="never switch to offboard")
    parser.add_argument(
        "--no-reengage",
        action="store_true",
        help="never take the vehicle back after the autopilot left offboard/guided (default: take"
        " it back when the agent's own setpoint gap of 0.5 s or more caused it, never after a"
        " pilot's or a ground station's mode change)",
    )
    parser.add_argument(
        "--clock-offset",
        type=float,
        default=0.0,
        metavar="S",
        help="pretend this host's clock reads S seconds ahead of the fleet's (a fault to inject;"
        " default 0)",
    )
    parser.add_argument(
        "--faults",
        type=Path,
        metavar="FILE",
        help="inject the network faults of a fault file into this agent's plan bus (faults/)",
    )
    parser.add_argument(
        "--record", type=Path, help="write one JSON line per step here (folders are created)"
    )


def _log(text: str) -> None:
    print(f"fleetmpc agent: {text}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, live=True)
    spec = scenario.vehicle(args.vehicle)
    _check_options(args)
    faults = None
    if args.faults is not None:
        faults = load_faults(args.faults, vehicle_ids=scenario.vehicle_ids, network_only=True)
    clock = FleetClock(
        epoch_ns=args.epoch_ns,
        speed=args.speed,
        awaiting_epoch=args.wait_epoch,
        host_offset_ns=round(args.clock_offset * 1e9),
    )
    agent = agent_for(scenario, spec)
    # The setpoint streamer sends only while it holds the GIL, and Python's default 5 ms switch
    # interval lets the control loop keep it that long past a send's due time: 20 ms of fleet
    # time at x4 on a 50 ms stream period. With 1 ms the stream keeps close to its period.
    sys.setswitchinterval(0.001)
    with _stop_on_signals() as stop, _json_lines(args.record) as record:
        return _fly(args, scenario, spec, agent, clock, faults=faults, stop=stop, record=record)


def _fly(args, scenario, spec, agent, clock, *, faults, stop, record) -> int:
    """Open the plan bus and the autopilot link, fly until `stop` (or the runner ends the run),
    then wind the link down, close both and print the runner's summary; the exit status."""

    def fleet_now() -> int | None:
        return clock.fleet_ns(time.time_ns())  # (None before the epoch: no fault applies)

    link = bus = streamer = runner = None
    try:
        bus = open_fleet_bus(args, scenario, sender_id=spec.id)
        if faults is not None:
            bus.faults = FaultLayer(faults, vehicle_id=spec.id, clock=fleet_now, seed=scenario.seed)
        link = _connect(args, scenario, spec, faults, fleet_now)
        streamer = SetpointStreamer(
            link,
            period_s=1.0 / (args.setpoint_rate_hz * clock.speed),
            command_lifetime_s=COMMAND_LIFETIME_PERIODS
            * scenario.controller.period_s
            / clock.speed,
        )
        runner = FleetRunner(
            agent,
            link=link,
            bus=bus,
            settings=_runner_settings(args, scenario),
            clock=clock,
            log=_log,
            record=record,
        )
        streamer.start()
        runner.run(stop, streamer)
        return 0 if runner.failure is None else 2
    except AutopilotLinkError as e:
        _log(str(e))
        return 2
    finally:
        if link is not None:
            wind_down(link, streamer, engaged=runner is not None and runner.engaged)
            link.close()
        if bus is not None:
            bus.close()
        if runner is not None:
            print(json.dumps(runner.summary(streamer)), flush=True)


@contextlib.contextmanager
def _stop_on_signals() -> Iterator[threading.Event]:
    """An event set by SIGINT or SIGTERM while the block runs (their handlers restored after)."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def _json_lines(path: Path | None) -> Iterator[Callable[[dict], None] | None]:
    """A function that writes a row to `path` as a JSON line, flushed (the file closed after
    the block); None without a path."""
    if path is None:
        yield None
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as file:

        def write(row: dict) -> None:
            file.write(json.dumps(row) + "\n")
            file.flush()

        yield write


def _check_options(args: argparse.Namespace) -> None:
    """Refuse an option out of its range, naming it."""
    if not 10.0 <= args.setpoint_rate_hz <= 1000.0:
        raise ConfigError(
            "--setpoint-rate-hz", f"must be in [10, 1000], got {args.setpoint_rate_hz}"
        )
    for name in ("connect_timeout", "engage_timeout"):
        value = getattr(args, name)
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"--{name.replace('_', '-')}", f"must be seconds > 0, got {value}")
    if not (math.isfinite(args.clock_offset) and abs(args.clock_offset) <= 60.0):
        raise ConfigError(
            "--clock-offset", f"must be seconds in [-60, 60], got {args.clock_offset}"
        )


def _connect(args: argparse.Namespace, scenario, spec, faults, fleet_now):
    """The vehicle's autopilot link (the scenario's URL unless --mavlink names another), its
    link faults if the run has any, connected and its autopilot named in the log."""
    url = args.mavlink or mavlink_url(scenario.network, spec)
    signing_key = None if args.mavlink_key is None else read_key_file(args.mavlink_key)
    link = open_autopilot_link(
        url,
        system_id=args.target_system,
        vehicle_id=spec.id,
        log=_log,
        home_deg=(scenario.site.home_lat_deg, scenario.site.home_lon_deg),
        signing_key=signing_key,
    )
    if faults is not None and any(f.kind in LINK_KINDS for f in faults.faults):
        link.faults = LinkFaults(faults, vehicle_id=spec.id, clock=fleet_now, seed=scenario.seed)
    try:
        state = link.connect(timeout_s=args.connect_timeout)
    except BaseException:
        link.close()
        raise
    _log(f"vehicle {spec.id}: {state.autopilot.name} on {url}")
    if state.system_id != spec.id:
        _log(
            f"vehicle {spec.id}: its autopilot has system id {state.system_id}, not"
            f" {spec.id}; flying it as vehicle {spec.id}"
        )
    return link


def _runner_settings(args: argparse.Namespace, scenario) -> RunnerSettings:
    """The control loop's settings from the scenario's period and the command line."""
    return RunnerSettings(
        period_ns=scenario.controller.period_ns,
        engage=not args.no_engage,
        engage_timeout_s=args.engage_timeout,
        reengage_after_gap_s=None if args.no_reengage else 0.5,
        stop_at_fleet_ns=None if args.duration is None else round(args.duration * 1e9),
    )
