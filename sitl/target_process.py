"""`fleetmpc target`: fly the scenario's scripted target and publish noisy observations on Zenoh.

Time base: fleet time (see `onboard.runner`), ``(time.time_ns() - epoch_ns) * speed``; the
target is at ``state_at(fleet_s)`` and every observation is stamped with the fleet time it was
taken at, on the scenario's observation rate (simulated Hz) and noise. Without ``--epoch-ns``
the epoch is this process's start (printed, so the rest of the fleet can be given it). Before
the epoch nothing is published. Observations are sent under sender id 250 (not a vehicle id).
Zenoh: by default the last member of the fleet's peer mesh (see `onboard.cli`);
``--zenoh-connect`` makes a client of a router; ``--zenoh-config FILE`` loads a config file.
SIGINT/SIGTERM: close the session and exit 0.
"""

import argparse
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from onboard.core.errors import ConfigError
from onboard.planbus import open_plan_bus
from protocol.messages import TARGET_ID
from protocol.scenario import load_scenario
from protocol.zenoh_config import ZenohOptions

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", required=True, type=Path, help="scenario TOML file")
    zenoh = parser.add_mutually_exclusive_group()
    zenoh.add_argument("--zenoh-config", type=Path, help="Zenoh config file")
    zenoh.add_argument("--zenoh-connect", help="comma-separated router endpoints (client mode)")
    parser.add_argument("--fleet", default=None, help="fleet name on Zenoh (default: scenario)")
    parser.add_argument("--epoch-ns", type=int, default=None, help="host time.time_ns() of t = 0")
    parser.add_argument("--speed", type=float, default=1.0, help="simulated seconds per second")
    parser.add_argument("--duration", type=float, default=None, help="stop at this fleet time [s]")
    parser.add_argument("--seed", type=int, default=None, help="noise seed (default: scenario)")


def _options(args: argparse.Namespace, scenario) -> ZenohOptions:
    if args.zenoh_config is not None:
        return ZenohOptions(config_file=str(args.zenoh_config))
    if args.zenoh_connect:
        items = [e.strip() for e in args.zenoh_connect.split(",") if e.strip()]
        return ZenohOptions(
            mode="client", connect=tuple(e if "/" in e else f"tcp/{e}" for e in items)
        )
    n = len(scenario.vehicles)
    net = scenario.network
    return ZenohOptions.peer_mesh(index=n, size=n + 1, base_port=net.zenoh_port, host=net.host)


def run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    if not 0.01 <= args.speed <= 1000.0:
        raise ConfigError("--speed", f"must be in [0.01, 1000], got {args.speed}")
    target = scenario.target
    epoch_ns = time.time_ns() if args.epoch_ns is None else args.epoch_ns
    period_ns = round(1e9 / target.observation_rate_hz)
    end_ns = None if args.duration is None else round(args.duration * 1e9)
    rng = np.random.default_rng(scenario.seed if args.seed is None else args.seed)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    published = 0
    bus = None
    try:
        bus = open_plan_bus(
            _options(args, scenario),
            fleet=args.fleet or scenario.name,
            vehicle_id=TARGET_ID,
        )
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
                print(f"fleetmpc target: publish failed: {e}", file=sys.stderr, flush=True)
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
