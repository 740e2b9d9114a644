"""`fleetmpc up SCENARIO`: start a whole fleet on this machine, watch it, and bring it down.

    fleetmpc up scenarios/paper.toml --speed 4 --viewer spawn

Starts the processes of `fleetmpc.launch.fleet.fleet_processes` (Zenoh router, target, one SITL
and one agent per vehicle, the ground station) as separate OS processes on loopback, each in its
own session so a Ctrl-C reaches only this launcher, which then stops them in order. Every process
writes ``<run-dir>/logs/<name>.log``. While the fleet flies, a status table shows each vehicle's
mode, arming, slot error, last solve time, oldest neighbour plan, setpoint rate and link age
(from the ground station's status file).

The run ends when the ground station finishes (``--duration`` of fleet time), on Ctrl-C or
SIGTERM, or when a process dies: that process is named with the tail of its log. Shutdown sends
SIGTERM to the ground station first (it closes the recording), then the agents (they command
HOLD) and the target, then the SITLs and the router; anything still alive after a grace period
is killed. Nothing this launcher started outlives it (a viewer spawned with ``--viewer spawn`` is
the user's window and stays open).

Security is on by default: the run's secrets (`fleetmpc.security.secrets`: a MAVLink signing key per
vehicle, the Zenoh bus's users, access list and certificates) are made fresh in
``<run-dir>/secrets`` (mode 0700) unless ``--keys DIR`` names a set; each process is given the
paths of its own. ``--insecure`` flies without them.

Exit status: 0 if the run completed and its gates held, 1 if a gate broke or a process failed,
130 after Ctrl-C, 2 on a configuration error.
"""

import argparse
import dataclasses
import json
import math
import os
import shutil
import signal
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from fleetmpc.bus.faults import LINK_KINDS, FaultSchedule, load_faults
from fleetmpc.errors import ConfigError
from fleetmpc.gcs.ground_station import SERIES_FLUSH_S
from fleetmpc.gcs.metrics import format_summary
from fleetmpc.gcs.telemetry import FLUSH_S
from fleetmpc.launch.fleet import (
    SEPARATE_SITL_LOAD,
    SITL_GROUP,
    FleetOptions,
    auto_vehicles_per_sitl,
    fleet_processes,
)
from fleetmpc.launch.process_faults import ProcessFaults
from fleetmpc.launch.processes import ProcessFailed, ProcessGroup, log_tail
from fleetmpc.launch.status_view import StatusView
from fleetmpc.scenario import flight_time, load_scenario
from fleetmpc.security.secrets import check_keys, make_keys
from fleetmpc.security.zenoh_security import MANIFEST_NAME

__all__ = ["add_arguments", "run"]

EXIT_WITHOUT_TEARDOWN = True
"""Its children are stopped and its files closed when `run` returns (see `fleetmpc.cli.entry`)."""

_ENGAGE_SLACK_S = 15.0
"""Wall seconds the ground station waits for the fleet beyond an agent's connect and engage
timeouts (the processes' start, the setpoint warm-up before engaging)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", type=Path, help="scenario TOML file")
    parser.add_argument(
        "--duration", type=float, metavar="S", help="fleet time (default: scenario)"
    )
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument("--rrd", type=Path, help="recording (default: RUN_DIR/run.rrd)")
    parser.add_argument(
        "--viewer",
        default=None,
        help="spawn, connect=URL or none (default: spawn with a display, none without)",
    )
    parser.add_argument("--metrics", type=Path, help="metrics JSON (default: RUN_DIR/metrics.json)")
    parser.add_argument("--run-dir", type=Path, help="logs and outputs (default: runs/up-<time>)")
    parser.add_argument(
        "--connect-timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="wall seconds each agent waits for its autopilot's HEARTBEAT and first pose"
        " (`fleetmpc agent --connect-timeout`; default 60)",
    )
    parser.add_argument(
        "--engage-timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="wall seconds each agent keeps trying to engage its vehicle, asking again while the"
        " autopilot refuses (`fleetmpc agent --engage-timeout`; default 60: a cold ArduCopter"
        " SITL arms some 40 s after boot); the ground station waits for the whole fleet the"
        f" connect and engage timeouts and {_ENGAGE_SLACK_S:g} s more",
    )
    parser.add_argument(
        "--flush-s",
        type=float,
        metavar="S",
        help="seconds of flight between the ground station's Rerun logging batches"
        f" (default {FLUSH_S:g}: see `fleetmpc gcs --help`)",
    )
    parser.add_argument(
        "--series-flush-s",
        type=float,
        metavar="S",
        help="seconds of flight between its loggings of the time series"
        f" (default {SERIES_FLUSH_S:g})",
    )
    parser.add_argument(
        "--gate-formation-m",
        type=float,
        metavar="M",
        help="also gate the run on its formation: separation and centre-distance errors at most"
        " M metres (as `fleetmpc compose` does with 0.1); default: the safety gate only",
    )
    parser.add_argument(
        "--faults",
        type=Path,
        metavar="FILE",
        help="inject the faults of a fault file: network faults into every agent's plan bus,"
        " process faults (freeze, kill, restart a named process) at their fleet times"
        " (faults/README.md)",
    )
    parser.add_argument(
        "--mavlink",
        action="append",
        default=[],
        metavar="ID=URL",
        help="fly vehicle ID on the autopilot at URL (a real PX4 or ArduPilot, or their SITL:"
        " docs/real-autopilots.md) instead of starting its simulated vehicle; repeatable",
    )
    parser.add_argument(
        "--target",
        default="script",
        metavar="URL",
        help="where the target's observations come from (`fleetmpc target --source`): script"
        " (the scenario's, default), mavlink:CONNECTION (another autopilot, a ground station's"
        " follow-me stream) or track:FILE (a recorded CSV or .tlog): docs/targets.md",
    )
    parser.add_argument(
        "--target-sysid",
        type=int,
        metavar="ID",
        help="the MAVLink system id of the target (--target mavlink:...; a .tlog's system)",
    )
    parser.add_argument(
        "--vehicles-per-sitl",
        type=int,
        metavar="K",
        help="simulated vehicles one SITL process serves (default: 1 while vehicles x speed is"
        f" at most {SEPARATE_SITL_LOAD:g}, else {SITL_GROUP}; a large or fast fleet on few cores"
        ' spends less waking one process than many: docs/design.md, "Waking")',
    )
    parser.add_argument(
        "--agent-records",
        action="store_true",
        help="each agent writes one JSON line per step to RUN_DIR/agents/agent-<id>.jsonl"
        " (pose, command, neighbour plan ages, mode, ...)",
    )
    security = parser.add_mutually_exclusive_group()
    security.add_argument(
        "--keys",
        type=Path,
        metavar="DIR",
        help="the fleet's secrets made by `fleetmpc keys` (default: a fresh set in"
        " RUN_DIR/secrets)",
    )
    security.add_argument(
        "--insecure",
        action="store_true",
        help="no MAVLink signing (anyone who reaches a port can fly a vehicle)",
    )
    parser.add_argument("--quiet", action="store_true", help="no status table")


def _default_viewer() -> str:
    if (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and shutil.which("rerun"):
        return "spawn"
    return "none"


def _fleet_wait_s(args: argparse.Namespace) -> float:
    """Wall seconds the ground station waits for every vehicle to engage: an agent's connect
    and engage timeouts, and `_ENGAGE_SLACK_S`."""
    return args.connect_timeout + args.engage_timeout + _ENGAGE_SLACK_S


def _gcs_options(args: argparse.Namespace) -> list[str]:
    """The ground station's own options of an `up` command line (checked here, so a bad value
    stops `up` before anything starts)."""
    for name in ("connect_timeout", "engage_timeout"):
        value = getattr(args, name)
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(f"--{name.replace('_', '-')}", f"must be seconds > 0, got {value}")
    options = ["--engage-timeout", f"{_fleet_wait_s(args):g}"]
    for name in ("flush_s", "series_flush_s", "gate_formation_m"):
        value = getattr(args, name)
        flag = f"--{name.replace('_', '-')}"
        if value is None:
            continue
        if not (value > 0 and math.isfinite(value)):
            raise ConfigError(flag, f"must be a number > 0, got {value:g}")
        options += [flag, repr(value)]
    return options


def _external_autopilots(items: list[str], scenario) -> dict[int, str]:
    """`--mavlink ID=URL` options as {vehicle id: URL}; errors name the option."""
    out: dict[int, str] = {}
    for item in items:
        vid, sep, url = item.partition("=")
        if not sep or not url or not vid.strip().isdigit():
            raise ConfigError(
                "--mavlink", f"must be ID=URL (e.g. 2=tcp:127.0.0.1:5770), got {item!r}"
            )
        if int(vid) not in scenario.vehicle_ids:
            raise ConfigError(
                "--mavlink", f"vehicle {vid} is not in the scenario (ids: {scenario.vehicle_ids})"
            )
        out[int(vid)] = url
    return out


def _fresh_secrets(scenario, directory: Path) -> Path:
    """A new set of the run's secrets in `directory`. A run directory used again has the last
    run's set, which is replaced; any other folder there is left alone (an error)."""
    if directory.exists():
        if not (directory / MANIFEST_NAME).is_file():
            raise ConfigError(
                "--run-dir", f"{directory} exists and is not a run's secrets; not replacing it"
            )
        shutil.rmtree(directory)
    return make_keys(scenario, directory)


def _epoch_of(status_file: Path) -> int | None:
    """The fleet epoch in the ground station's status file, None before it has one."""
    try:
        return json.loads(status_file.read_text()).get("epoch_ns")
    except (OSError, ValueError, AttributeError):
        return None


def _process_faults(schedule: FaultSchedule, fleet: ProcessGroup, *, speed: float) -> ProcessFaults:
    """The driver of the schedule's process faults on `fleet`: a killed process's exit is
    handled (not a failure), a restart starts its spec again."""

    def signal_process(name: str, signum: int) -> None:
        child = fleet.get(name)
        if signum == signal.SIGKILL:
            child.exit_handled = True
        if child.proc.poll() is None:
            child.proc.send_signal(signum)

    def start_process(name: str) -> None:
        fleet.restart(name)

    return ProcessFaults(
        tuple(f for f in schedule.faults if f.kind in ProcessFaults.KINDS),
        signal_process=signal_process,
        start_process=start_process,
        log=lambda text: print(f"fleetmpc up: fault at {text}", flush=True),
        speed=speed,
    )


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario, live=True)
    duration = flight_time(scenario, speed=args.speed, duration_s=args.duration)
    gcs_options = _gcs_options(args)
    run_dir = args.run_dir or Path("runs") / f"up-{datetime.now():%Y%m%d-%H%M%S}"
    outputs = _Outputs(
        rrd=args.rrd or run_dir / "run.rrd",
        metrics=args.metrics or run_dir / "metrics.json",
        status=run_dir / "status.json",
    )
    fleet = ProcessGroup(run_dir)
    outputs.status.unlink(missing_ok=True)  # (a run dir used again: not the last run's epoch)
    if args.keys is not None:
        check_keys(scenario, args.keys)
    secrets = None
    if not args.insecure:
        secrets = args.keys or _fresh_secrets(scenario, run_dir / "secrets")
    specs = _specs(args, scenario, duration, outputs, run_dir, secrets, gcs_options)
    faults = None
    if args.faults is not None:
        specs, faults = _with_faults(args, scenario, specs, fleet)
    interrupted = threading.Event()
    previous = {
        s: signal.signal(s, lambda *_: interrupted.set()) for s in (signal.SIGINT, signal.SIGTERM)
    }
    view = StatusView(outputs.status, quiet=args.quiet)
    print(
        f"fleetmpc up: {scenario.name}, {len(scenario.vehicles)} UAVs, {duration:g} s at "
        f"x{args.speed:g}; logs in {fleet.logs}",
        flush=True,
    )
    failure: ProcessFailed | None = None
    seen = _Watch()
    try:
        for spec in specs:
            child = fleet.start(spec)
            if spec.role == "router":
                fleet.wait_for_text(child, "listening", timeout_s=15.0)
        wall_limit = time.monotonic() + _fleet_wait_s(args) + duration / args.speed + 60.0
        _supervise(fleet, seen, faults, outputs.status, view, interrupted, duration, wall_limit)
    except ProcessFailed as e:
        failure = e
    finally:
        view.close()
        if faults is not None:
            faults.release()
        t_stop = time.monotonic()
        codes = fleet.stop()
        stop_s = time.monotonic() - t_stop
        for s, handler in previous.items():
            signal.signal(s, handler)
    interrupted_s = stop_s if interrupted.is_set() and seen.rc is None else None
    _report(fleet, faults, seen, failure, interrupted_s, outputs, codes)
    return _exit_status(fleet, seen, failure, interrupted_s is not None, codes)


@dataclass(frozen=True)
class _Outputs:
    """Where a run writes: its recording, its metrics and the ground station's status file."""

    rrd: Path
    metrics: Path
    status: Path


@dataclass
class _Watch:
    """What watching the running fleet saw (`_supervise`)."""

    rc: int | None = None
    """The ground station's exit status when last polled; None while it runs."""
    gcs_lost: bool = False
    """A fault killed the ground station; the fleet flew on without it."""
    router_restarts: int = 0


def _specs(args, scenario, duration, outputs: _Outputs, run_dir, secrets, gcs_options):
    """The fleet's processes for this command line, the ground station's own options added."""
    external = _external_autopilots(args.mavlink, scenario)
    per_sitl = args.vehicles_per_sitl
    if per_sitl is None:
        per_sitl = auto_vehicles_per_sitl(len(scenario.vehicles) - len(external), args.speed)
    specs = fleet_processes(
        scenario,
        FleetOptions(
            scenario_path=str(args.scenario),
            speed=args.speed,
            duration_s=duration,
            rrd=str(outputs.rrd),
            metrics=str(outputs.metrics),
            status_file=str(outputs.status),
            viewer=args.viewer or _default_viewer(),
            agent_records_dir=str(run_dir / "agents") if args.agent_records else None,
            external_autopilots=external,
            target_source=args.target,
            target_sysid=args.target_sysid,
            connect_timeout_s=args.connect_timeout,
            engage_timeout_s=args.engage_timeout,
            secrets_dir=None if secrets is None else str(secrets),
            vehicles_per_sitl=per_sitl,
            wind_epoch_ns=time.time_ns(),  # (the launch: every SITL flies one wind)
        ),
    )
    return [
        s if s.role != "gcs" else dataclasses.replace(s, argv=(*s.argv, *gcs_options))
        for s in specs
    ]


def _with_faults(args, scenario, specs, fleet: ProcessGroup):
    """The processes with the fault file's options (network and link faults to the agents, a
    clock offset to its process at launch), and the faults the launcher itself injects."""
    schedule = load_faults(
        args.faults, vehicle_ids=scenario.vehicle_ids, processes=[s.name for s in specs]
    )
    extra: dict[str, tuple[str, ...]] = {}
    if any(f.network or f.kind in LINK_KINDS for f in schedule.faults):
        for s in specs:
            if s.role == "agent":
                extra[s.name] = ("--faults", str(args.faults.resolve()))
    for f in schedule.faults:
        if f.kind == "clock_offset":  # (at launch: the process starts with it)
            extra[f.process] = (*extra.get(f.process, ()), "--clock-offset", f"{f.offset_s:g}")
            print(f"fleetmpc up: fault: {f.describe()}", flush=True)
    specs = [dataclasses.replace(s, argv=(*s.argv, *extra.get(s.name, ()))) for s in specs]
    return specs, _process_faults(schedule, fleet, speed=args.speed)


def _supervise(
    fleet: ProcessGroup,
    seen: _Watch,
    faults: ProcessFaults | None,
    status_file: Path,
    view: StatusView,
    interrupted: threading.Event,
    duration: float,
    wall_limit: float,
) -> None:
    """Watch the fleet until the ground station exits (or, once a fault has taken it, the
    flight's time is up) or the run is interrupted: inject the launcher's faults when due,
    restart the Zenoh router if it exits, redraw the status; raise ProcessFailed when a
    process fails or the run overruns `wall_limit` (monotonic seconds)."""
    while not interrupted.is_set():
        if faults is not None:
            if faults.epoch_ns is None:
                faults.epoch_ns = _epoch_of(status_file)
            faults.poll()
        gcs = fleet.get("gcs")
        seen.rc = gcs.proc.poll()
        if seen.rc is not None and not gcs.exit_handled:
            return
        if gcs.exit_handled and not seen.gcs_lost:
            seen.gcs_lost = True
            print("fleetmpc up: the ground station is gone; the fleet flies on", flush=True)
        if seen.gcs_lost and (faults.fleet_s() or 0.0) >= duration + 1.0:
            return
        router = fleet.get("zenoh-router")
        code = router.proc.poll()
        if code is not None and not router.exit_handled:
            # A service, not a reason to land the fleet: the agents rejoin it.
            seen.router_restarts += 1
            print(f"fleetmpc up: zenoh-router exited (status {code}); restarting it")
            fleet.restart("zenoh-router")
        bad = fleet.failed()
        if bad is not None:
            raise ProcessFailed(bad)
        if time.monotonic() > wall_limit:
            raise ProcessFailed(gcs, "did not finish in time")
        view.update()
        interrupted.wait(0.1 if faults is not None and faults.pending else 0.5)


def _report(
    fleet: ProcessGroup,
    faults: ProcessFaults | None,
    seen: _Watch,
    failure: ProcessFailed | None,
    interrupted_s: float | None,
    outputs: _Outputs,
    codes: dict[str, int | None],
) -> None:
    """What the run did: faults injected, router restarts, a failure and its log's tail, an
    interruption (`interrupted_s`: how long stopping took), the metrics and the exit codes."""
    if faults is not None and faults.done:
        print("fleetmpc up: faults injected:\n" + "\n".join(f"  {d}" for d in faults.done))
    if seen.router_restarts:
        print(f"fleetmpc up: zenoh-router restarted {seen.router_restarts} time(s) after it exited")
    if failure is not None:
        print(f"fleetmpc up: FAILED: {failure}; the tail of its log:", file=sys.stderr)
        print(log_tail(failure.child.log), file=sys.stderr)
    if interrupted_s is not None:
        stages = ", ".join(f"{role} {t:.1f} s" for role, t in fleet.stage_s.items())
        print(
            f"fleetmpc up: interrupted; every process stopped in {interrupted_s:.1f} s ({stages})",
            file=sys.stderr,
        )
    if outputs.metrics.is_file():
        print(format_summary(json.loads(outputs.metrics.read_text())))
        print(f"metrics: {outputs.metrics}\nrecording: {outputs.rrd}")
    print(f"exit codes: {', '.join(f'{k} {v}' for k, v in codes.items())}", flush=True)


def _exit_status(
    fleet: ProcessGroup,
    seen: _Watch,
    failure: ProcessFailed | None,
    interrupted: bool,
    codes: dict[str, int | None],
) -> int:
    """0 when the fleet flew and every gate held; 1 on a failure or a broken gate; 130 when
    interrupted."""
    if failure is not None:
        return 1
    if interrupted:
        return 130
    if seen.gcs_lost:
        print("fleetmpc up: no metrics: a fault killed the ground station", flush=True)
        return 0
    if codes.get("gcs") != 0:
        log = fleet.get("gcs").log
        print(f"fleetmpc up: ground station reported a broken gate:\n{log_tail(log, 5)}")
        return 1
    return 0
