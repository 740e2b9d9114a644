"""`fleetmpc sim SCENARIO`: the whole fleet in one process, in lockstep.

Deterministic for a seed."""

import argparse
import json
import math
from pathlib import Path

from gcs.check import check_scenario
from gcs.figures import write_figures
from gcs.lockstep import run_lockstep
from gcs.metrics import compute_metrics
from gcs.progress import ProgressBar
from gcs.recording import write_recording
from onboard.core.errors import ConfigError
from protocol.scenario import load_scenario

__all__ = ["add_arguments", "format_summary", "run"]


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
        help="write the run as a Rerun recording (`fleetmpc report` reads it)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _fraction(x: float | None) -> str:
    return "unknown" if x is None else f"{x:.4f}"


def format_summary(metrics: dict) -> str:
    """A human-readable table of the metrics."""
    rows = [
        ("scenario", metrics["scenario"]),
        ("learning", "on" if metrics["learning"] else "off"),
        ("feasible", "yes" if metrics["feasible"] else "NO (the target outruns the team)"),
        ("duration", f"{metrics['duration_s']:.1f} s"),
    ]
    for (a, b), e in zip(metrics["separation_pairs"], metrics["separation_error_m"], strict=True):
        rows.append((f"separation error {a}-{b}", f"{e:.4f} m"))
    rows += [
        ("centre distance error", f"{metrics['centre_distance_error_m']:.4f} m"),
        ("formation RMS", f"{metrics['formation_rms_m']:.4f} m"),
        ("||c|| final", f"{metrics['c_norm_final']:.4f}"),
        ("min separation", f"{metrics['min_separation_m']:.3f} m"),
        ("inputs within U", _fraction(metrics["inputs_within_bounds"])),
        ("QP fallbacks", str(metrics["qp_fallbacks"])),
    ]
    rows += _manoeuvre_rows(metrics)
    st = metrics["step_time_ms"]
    if st["median"] is not None:
        rows.append(("agent step", f"median {st['median']:.3f} ms, p99 {st['p99']:.3f} ms"))
    share = metrics.get("gcs_logging_share_of_agent_step")
    if share is not None:  # a live run's ground station with a recording
        logging = metrics["gcs_logging_ms_per_vehicle_period"]
        text = f"median {logging['median']:.3f} ms per vehicle-period"
        if logging.get("rerun_threads") is not None:
            text += f" + {logging['rerun_threads']:.3f} in Rerun's threads"
        text += f": {100 * share:.1f} % of the agent step median"
        rows.append(("ground station logging", text))
    for b in metrics["beta_error"]:
        rows.append(
            (
                f"beta error UAV {b['vehicle']}",
                f"a_V {100 * b['speed_effectiveness']:.1f} %, "
                f"a_w {100 * b['yaw_rate_effectiveness']:.1f} %, "
                f"drift {b['drift_m_s']:.3f} m/s",
            )
        )
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


def _manoeuvre_rows(metrics: dict) -> list[tuple[str, str]]:
    """Rows of the worst vehicle, yaw-rate reversals, target prediction and corners (absent from
    a metrics file written before they existed)."""
    rows = []
    if "slot_rms_max_vehicle_m" in metrics:
        rows.append(("worst vehicle slot RMS", f"{metrics['slot_rms_max_vehicle_m']:.4f} m"))
    reversals = metrics.get("yaw_rate_reversals_per_vehicle_min")
    if reversals is not None:
        rows.append(("yaw-rate reversals", f"{reversals:.2f} per vehicle-minute"))
    if "target_prediction_rms_m" in metrics:
        rms = metrics["target_prediction_rms_m"]
        rows.append(("target prediction RMS", "unknown" if rms is None else f"{rms:.3f} m"))
    corners = metrics.get("corners")
    if corners is not None:
        rows.append(("target corners", str(corners)))
    recovery = metrics.get("corner_recovery_s")
    if recovery is not None:
        text = "never" if recovery == math.inf else f"{recovery:.1f} s"
        rows.append(("corner recovery (worst)", text))
    return rows


def run(args: argparse.Namespace) -> int:
    sc = load_scenario(args.scenario)
    if args.duration is not None and not args.duration > 0:
        raise ConfigError("--duration", f"must be > 0, got {args.duration}")
    report = check_scenario(sc)
    if not report.feasible:
        print("WARNING: this scenario is infeasible; the run will show it:")
        for p in report.problems:
            print(f"  - {p}")
    duration = sc.duration_s if args.duration is None else args.duration
    bar = None if args.quiet else ProgressBar(f"sim {sc.name}")
    rec = run_lockstep(
        sc, learning=not args.no_learning, duration_s=duration, seed=args.seed, progress=bar
    )
    metrics = {
        "scenario": sc.name,
        "learning": not args.no_learning and sc.learning.enabled,
        "feasible": report.feasible,
        "duration_s": float(rec.t_s[-1]),
        "seed": sc.seed if args.seed is None else args.seed,
        **compute_metrics(rec),
    }
    print(format_summary(metrics))
    if args.metrics:
        path = Path(args.metrics)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(metrics, indent=2) + "\n")
        print(f"metrics: {path}")
    if args.plots:
        for p in write_figures(rec, args.plots):
            print(f"figure: {p}")
    if args.rrd:
        run_info = {k: metrics[k] for k in ("learning", "feasible", "seed")}
        rid = write_recording(rec, args.rrd, run_info=run_info)
        print(f"recording: {args.rrd} (id {rid})")
    return 0
