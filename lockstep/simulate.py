"""`fleetmpc sim SCENARIO`: the whole fleet in one process, in lockstep.

Deterministic for a seed."""

import argparse
import json
from pathlib import Path

from fleetmpc.bus.faults import load_faults
from fleetmpc.check.feasibility import check_scenario
from fleetmpc.errors import ConfigError
from fleetmpc.gcs.figures import write_figures
from fleetmpc.gcs.metrics import compute_metrics, format_summary, known_model_figures
from fleetmpc.gcs.progress import ProgressBar
from fleetmpc.gcs.telemetry import add_telemetry_argument, open_sink
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import load_scenario

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario TOML file")
    parser.add_argument(
        "--no-learning", action="store_true", help="freeze beta at nominal (plain tube MPC)"
    )
    parser.add_argument(
        "--duration", type=float, metavar="S", help="simulated seconds (default: the scenario's)"
    )
    parser.add_argument(
        "--seed", type=int, metavar="N", help="random seed (default: the scenario's)"
    )
    parser.add_argument("--metrics", metavar="FILE", help="write the metrics as JSON")
    parser.add_argument("--plots", metavar="DIR", help="write the paper's figures as PNG")
    parser.add_argument(
        "--rrd",
        metavar="FILE",
        help="write the run as a Rerun recording (`fleetmpc report` reads it); the same as"
        " --telemetry rrd:FILE",
    )
    parser.add_argument(
        "--faults",
        metavar="FILE",
        help="inject the network faults of a fault file (TOML, see faults/README.md) into the"
        " plan bus",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        metavar="J",
        help="step the agents in J processes (default 1; the figures are the same for any J)",
    )
    parser.add_argument(
        "--known-model",
        action="store_true",
        help="also fly the run with every agent told its vehicle's true effectiveness and the"
        " wind where it is (what a perfect learner knows), and report both formation RMS and"
        " their ratio learned_over_known",
    )
    add_telemetry_argument(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    sc = load_scenario(args.scenario)
    if args.duration is not None and not args.duration > 0:
        raise ConfigError("--duration", f"must be > 0, got {args.duration}")
    if args.jobs < 1:
        raise ConfigError("--jobs", f"must be >= 1, got {args.jobs}")
    report = check_scenario(sc)
    if not report.feasible:
        print("WARNING: this scenario is infeasible; the run will show it:")
        for p in report.problems:
            print(f"  - {p}")
    faults = None
    if args.faults is not None:
        faults = load_faults(args.faults, vehicle_ids=sc.vehicle_ids)
    duration = sc.duration_s if args.duration is None else args.duration
    urls = ([f"rrd:{args.rrd}"] if args.rrd else []) + list(args.telemetry)
    sinks = [open_sink(url) for url in urls]
    run_info = {
        "learning": not args.no_learning and sc.learning.enabled,
        "feasible": report.feasible,
        "seed": sc.seed if args.seed is None else args.seed,
    }
    known = {}
    if args.known_model:  # (first, so that its figure is in the recording's run_info too)
        known = {"known_model_formation_rms_m": _known_model_rms(sc, args, duration, faults)}
    bar = None if args.quiet else ProgressBar(f"sim {sc.name}")
    try:
        rec = run_lockstep(
            sc,
            learning=not args.no_learning,
            duration_s=duration,
            seed=args.seed,
            progress=bar,
            sinks=sinks,
            run_info={**run_info, **known, "source": "lockstep"},
            jobs=args.jobs,
            faults=faults,
        )
    finally:
        if bar is not None:
            bar.close()
    metrics = {
        "scenario": sc.name,
        **run_info,
        "duration_s": float(rec.t_s[-1]),
        **compute_metrics(rec),
    }
    if known:
        metrics |= known_model_figures(metrics, known["known_model_formation_rms_m"])
    print(format_summary(metrics))
    if args.metrics:
        path = Path(args.metrics)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(metrics, indent=2) + "\n")
        print(f"metrics: {path}")
    if args.plots:
        for p in write_figures(rec, args.plots):
            print(f"figure: {p}")
    for url in urls:
        print(f"telemetry: {url}")
    return 0


def _known_model_rms(sc, args, duration, faults) -> float:
    """The formation RMS of the run flown with every agent told its truth."""
    known = run_lockstep(
        sc, duration_s=duration, seed=args.seed, jobs=args.jobs, faults=faults, known_model=True
    )
    return compute_metrics(known)["formation_rms_m"]
