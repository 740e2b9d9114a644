"""`fleetmpc target`: fly the scenario's scripted target and publish noisy observations on Zenoh.

Time base: fleet time (see `fleetmpc.onboard.runner`), ``(time.time_ns() - epoch_ns) * speed``; the
target is at ``state_at(fleet_s)`` and every observation is stamped with the fleet time it was taken
at, on the scenario's observation rate (simulated Hz) and noise. The epoch is ``--epoch-ns``, or
with ``--wait-epoch`` the first one announced on the bus (the ground station's `FleetEpoch` on
``fleetmpc/<fleet>/epoch``; waiting ends after ``--epoch-timeout`` wall seconds with exit code 2,
and an announced speed other than ``--speed`` is an error, exit 2); without either, the epoch is
this process's start (printed, so the rest of the fleet can be given it). Before the epoch nothing
is published. Observations are sent under sender id `TARGET_ID`. Zenoh:
`fleetmpc.protocol.zenoh_config.options_from_args` (by default the target's member of the fleet's
peer mesh; ``--zenoh-connect`` a client of a router; ``--zenoh-config FILE`` a config file).
SIGINT/SIGTERM: close the session and exit 0.

The source (``--source``, `fleetmpc.targets`): ``script`` (the scenario's scripted target, the
default), ``mavlink:CONNECTION`` (another MAVLink system, ``--sysid`` the one followed; e.g.
``mavlink:udpin:0.0.0.0:14560``) or ``track:FILE`` (a recorded CSV or .tlog replayed on fleet
time, its first fix at ``--track-start``; x1 or faster with ``--speed``). A live source's fixes
are screened, placed about the scenario's home and stamped on fleet time through the source's
clock (`fleetmpc.targets.pipeline`); every rejection is logged naming its fault (the first few of
each fault, then every hundredth), and every `REPORT_S` of fleet time a line gives the counts and
the source clock's offset and drift.
"""

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from fleetmpc.bus.open_bus import add_bus_arguments, open_fleet_bus
from fleetmpc.bus.planbus import PlanBus
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import epoch_key
from fleetmpc.protocol.messages import TARGET_ID
from fleetmpc.scenario import Scenario, load_scenario
from fleetmpc.targets.pipeline import Observation, ObservationPipeline
from fleetmpc.targets.screen import ScreenLimits
from fleetmpc.targets.sources import TargetSource, open_source

__all__ = ["add_arguments", "run", "wait_for_epoch"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""

_SPEED_RTOL = 1e-6

REPORT_S = 10.0
"""A live source's counts and clock are reported every this much fleet time [s]."""

LOGGED_PER_FAULT = 5
"""Rejections of each fault logged in full before only every hundredth is."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    add_bus_arguments(parser)
    epoch = parser.add_mutually_exclusive_group()
    epoch.add_argument("--epoch-ns", type=int, default=None, help="host time.time_ns() of t = 0")
    epoch.add_argument(
        "--wait-epoch", action="store_true", help="take the epoch announced on the bus"
    )
    parser.add_argument(
        "--epoch-timeout",
        type=float,
        default=120.0,
        help="--wait-epoch: give up after this many wall-clock seconds (exit 2)",
    )
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument("--duration", type=float, default=None, help="stop at this fleet time [s]")
    parser.add_argument("--seed", type=int, default=None, help="noise seed (default: scenario)")
    parser.add_argument(
        "--source",
        default="script",
        help="script (default), mavlink:CONNECTION (a pymavlink connection string) or track:FILE",
    )
    parser.add_argument(
        "--sysid", type=int, default=None, help="mavlink: the system followed; .tlog: its system"
    )
    parser.add_argument(
        "--noise-m", type=float, default=None, help="the fixes' noise [m] (default: estimated)"
    )
    parser.add_argument(
        "--track-start", type=float, default=0.0, help="track: fleet time of its first fix [s]"
    )


def _log(text: str) -> None:
    print(f"fleetmpc target: {text}", file=sys.stderr, flush=True)


def wait_for_epoch(
    bus: PlanBus, *, speed: float, timeout_s: float, stop: threading.Event
) -> int | None:
    """The first epoch announced on `bus` (None if `stop` was set first).

    Raises ConfigError on timeout, naming the fleet's epoch key, or if the announced speed is
    not `speed`.
    """
    deadline = time.monotonic() + timeout_s
    while not stop.is_set():
        announced = bus.latest_epoch()
        if announced is not None:
            if not math.isclose(announced.speed, speed, rel_tol=_SPEED_RTOL):
                raise ConfigError(
                    "--speed",
                    f"the fleet epoch is announced at x{announced.speed:g}, this process runs at "
                    f"x{speed:g}",
                )
            return announced.epoch_ns
        left = deadline - time.monotonic()
        if left <= 0:
            raise ConfigError(
                "--epoch-timeout",
                f"no fleet epoch for fleet {bus.fleet!r} on {epoch_key(bus.fleet)} "
                f"within {timeout_s:g} s",
            )
        stop.wait(min(0.05, left))
    return None


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    if not 0.01 <= args.speed <= 1000.0:
        raise ConfigError("--speed", f"must be in [0.01, 1000], got {args.speed}")
    if not 0.0 < args.epoch_timeout <= 1e6:  # also rejects NaN
        raise ConfigError("--epoch-timeout", f"must be in (0, 1e6] s, got {args.epoch_timeout}")
    source_url = args.source
    if source_url == "script" and scenario.target.kind == "track":
        source_url = f"track:{scenario.target.file}"  # (the scenario's recorded track)
    source = None
    if source_url != "script":
        source = open_source(source_url, system_id=args.sysid, track_start_s=args.track_start)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    published = 0
    bus = None
    try:
        bus = open_fleet_bus(args, scenario, sender_id=TARGET_ID)
        if args.wait_epoch:
            _log(f"waiting for the fleet epoch on {epoch_key(bus.fleet)}")
            epoch_ns = wait_for_epoch(
                bus, speed=args.speed, timeout_s=args.epoch_timeout, stop=stop
            )
            if epoch_ns is None:
                return 0
        else:
            epoch_ns = time.time_ns() if args.epoch_ns is None else args.epoch_ns
        print(f"fleetmpc target: epoch_ns {epoch_ns} speed {args.speed:g}", flush=True)
        if source is None:
            published = _fly_script(args, scenario, bus, epoch_ns, stop)
        else:
            _log(f"following {source_url}" + (f", system {args.sysid}" if args.sysid else ""))
            published = _relay(args, scenario, source, bus, epoch_ns, stop)
        return 0
    finally:
        if source is not None:
            source.close()
        if bus is not None:
            bus.close()
        print(f"fleetmpc target: stopped after {published} observations", file=sys.stderr)
        for s, handler in previous.items():
            signal.signal(s, handler)


def _fly_script(
    args: argparse.Namespace, scenario: Scenario, bus: PlanBus, epoch_ns: int, stop: threading.Event
) -> int:
    """Publish the scripted target's noisy positions at its rate; how many were published."""
    target = scenario.target
    period_ns = round(1e9 / target.observation_rate_hz)
    end_ns = None if args.duration is None else round(args.duration * 1e9)
    rng = np.random.default_rng(scenario.seed if args.seed is None else args.seed)
    published = 0
    k = 0
    while not stop.is_set():
        stamp_ns = k * period_ns
        if end_ns is not None and stamp_ns > end_ns:
            break
        wall_due_ns = epoch_ns + stamp_ns / args.speed
        delay_s = (wall_due_ns - time.time_ns()) * 1e-9
        if delay_s > 0 and stop.wait(delay_s):
            break
        pos = target.observe(stamp_ns * 1e-9, rng)
        try:
            bus.publish_target(
                stamp_ns=stamp_ns,
                north_m=float(pos[0]),
                east_m=float(pos[1]),
                noise_std_m=float(target.observation_noise_m),
            )
            published += 1
        except Exception as e:  # keep flying the target
            _log(f"publish failed: {e}")
        # Catch up without a burst if this process was late (e.g. started after the epoch).
        now_stamp = (time.time_ns() - epoch_ns) * args.speed
        k = max(k + 1, int(now_stamp // period_ns))
    return published


def _relay(
    args: argparse.Namespace,
    scenario: Scenario,
    source: TargetSource,
    bus: PlanBus,
    epoch_ns: int,
    stop: threading.Event,
) -> int:
    """Publish a live source's accepted fixes until it ends, --duration, or a signal; how many
    were published."""
    site = scenario.site
    pipeline = ObservationPipeline(
        home_lat_deg=site.home_lat_deg,
        home_lon_deg=site.home_lon_deg,
        limits=ScreenLimits(system_id=args.sysid),
        noise_m=args.noise_m,
    )
    published, next_report_s = 0, REPORT_S
    logged: dict[str, int] = {}
    while not stop.is_set() and not source.finished:
        now_s = (time.time_ns() - epoch_ns) * 1e-9 * args.speed
        if args.duration is not None and now_s > args.duration:
            break
        fixes = source.poll(0.05, now_s)
        if now_s < 0.0:  # (before the epoch: nothing is published, nothing is learnt)
            continue
        for fix in fixes:
            obs = pipeline.take(fix, now_s)
            if obs is not None:
                published += _publish(bus, obs)
        for line in pipeline.log:
            _log_rejection(line, logged)
        pipeline.log.clear()
        if now_s >= next_report_s:
            clock = pipeline.clock.estimate
            _log(pipeline.screen.summary() + ("; " + clock.describe() if clock else ""))
            next_report_s += REPORT_S
    _log(pipeline.screen.summary())
    return published


def _publish(bus: PlanBus, obs: Observation) -> int:
    try:
        bus.publish_target(
            stamp_ns=obs.stamp_ns,
            north_m=obs.north_m,
            east_m=obs.east_m,
            noise_std_m=obs.noise_std_m,
            velocity_m_s=obs.velocity_m_s,
        )
        return 1
    except Exception as e:  # keep relaying
        _log(f"publish failed: {e}")
        return 0


def _log_rejection(line: str, logged: dict[str, int]) -> None:
    """Log a rejection: the first LOGGED_PER_FAULT of its fault, then every hundredth."""
    fault = line.split(")", 1)[0]
    n = logged[fault] = logged.get(fault, 0) + 1
    if n <= LOGGED_PER_FAULT or n % 100 == 0:
        _log(line + (f" [{n} so far]" if n > LOGGED_PER_FAULT else ""))
