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
"""

import argparse
import math
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.open_bus import add_bus_arguments, open_fleet_bus
from fleetmpc.onboard.planbus import PlanBus
from fleetmpc.protocol.keys import epoch_key
from fleetmpc.protocol.messages import TARGET_ID
from fleetmpc.scenario import load_scenario

__all__ = ["add_arguments", "run", "wait_for_epoch"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""

_SPEED_RTOL = 1e-6


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
    target = scenario.target
    period_ns = round(1e9 / target.observation_rate_hz)
    end_ns = None if args.duration is None else round(args.duration * 1e9)
    rng = np.random.default_rng(scenario.seed if args.seed is None else args.seed)
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
        k = 0
        while not stop.is_set():
            stamp_ns = k * period_ns
            if end_ns is not None and stamp_ns > end_ns:
                break
            wall_due_ns = epoch_ns + stamp_ns / args.speed
            delay_s = (wall_due_ns - time.time_ns()) * 1e-9
            if delay_s > 0 and stop.wait(delay_s):
                break
            t_s = stamp_ns * 1e-9
            pos = target.observe(t_s, rng)
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
        return 0
    finally:
        if bus is not None:
            bus.close()
        print(f"fleetmpc target: stopped after {published} observations", file=sys.stderr)
        for s, handler in previous.items():
            signal.signal(s, handler)
