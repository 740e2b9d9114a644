"""`fleetmpc bench --scale`: how the agent step and the lockstep simulation grow with the fleet.

For each fleet size N of `--sizes`, the grid of `scenarios/scale/grid50.toml` resized to N vehicles
(rows of up to 10) flies `--duration` seconds in lockstep, once with the agents stepped in this
process and once in `--jobs` worker processes, the two in turn. Per N: the agent step median and
p99 (of the in-process run), the QP's size (decision variables, constraint rows, and how many of
those are separation rows: K M), the real-time factor (simulated seconds per wall second,
startup of the workers included) of both runs, and the runs' formation RMS and minimum
separation (which must be the same in both). Then the step median of the largest N over that of
the smallest, both measured in this one run. Wall-clock times; nothing is asserted.
"""

import argparse
import json
import time
import tomllib
from pathlib import Path

import numpy as np

from fleetmpc.bench.step import load_average
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.onboard.core.agent import vehicle_mpc
from fleetmpc.onboard.core.formation import Formation
from fleetmpc.scenario import Scenario, parse_scenario

__all__ = ["grid_of", "run"]

GRID = Path(__file__).resolve().parents[1] / "scenarios" / "scale" / "grid50.toml"
COLUMNS = 10


def grid_of(count: int) -> Scenario:
    """`scenarios/scale/grid50.toml` with `count` vehicles (rows of up to COLUMNS)."""
    doc = tomllib.loads(GRID.read_text())
    pattern = doc["formation"]["pattern"]
    pattern["count"], pattern["columns"] = count, min(COLUMNS, count)
    doc["name"] = f"grid{count}"
    return parse_scenario(doc, source=f"{GRID} resized to {count}")


def _fly(sc: Scenario, duration_s: float, jobs: int) -> dict:
    t0 = time.perf_counter()
    rec = run_lockstep(sc, duration_s=duration_s, jobs=jobs)
    wall_s = time.perf_counter() - t0
    m = compute_metrics(rec)
    steps = rec.step_time_ms.ravel()
    return {
        "realtime_factor": duration_s / wall_s,
        "step_median_ms": float(np.median(steps)),
        "step_p99_ms": float(np.percentile(steps, 99)),
        "formation_rms_m": m["formation_rms_m"],
        "min_separation_m": m["min_separation_m"],
    }


def run(args: argparse.Namespace) -> int:
    load_before = load_average()
    rows = []
    for n in args.sizes:
        sc = grid_of(n)
        M = sc.controller.horizon
        k = vehicle_mpc(sc.controller, Formation(sc.formation)).n_neighbours
        row = {  # OSQP's rows: 2 M inputs, K M separation, M speed changes
            "vehicles": n,
            "qp_variables": 2 * M,
            "qp_rows": (3 + k) * M,
            "separation_rows": k * M,
        }
        alone = _fly(sc, args.duration, 1)
        pooled = _fly(sc, args.duration, args.jobs)
        row.update(
            step_median_ms=alone["step_median_ms"],
            step_p99_ms=alone["step_p99_ms"],
            realtime_factor_jobs_1=alone["realtime_factor"],
            **{f"realtime_factor_jobs_{args.jobs}": pooled["realtime_factor"]},
            formation_rms_m=alone["formation_rms_m"],
            min_separation_m=alone["min_separation_m"],
            same_figures=alone["formation_rms_m"] == pooled["formation_rms_m"]
            and alone["min_separation_m"] == pooled["min_separation_m"],
        )
        rows.append(row)
        print(
            f"N = {n:3d}: step median {row['step_median_ms']:.3f} ms, p99 "
            f"{row['step_p99_ms']:.3f} ms; QP {row['qp_variables']} variables, {row['qp_rows']}"
            f" rows ({row['separation_rows']} separation); real time x"
            f"{row['realtime_factor_jobs_1']:.1f} (jobs 1), x"
            f"{row[f'realtime_factor_jobs_{args.jobs}']:.1f} (jobs {args.jobs}); formation RMS"
            f" {row['formation_rms_m']:.3f} m, min separation {row['min_separation_m']:.2f} m;"
            f" same figures with jobs {args.jobs}: {'yes' if row['same_figures'] else 'NO'}",
            flush=True,
        )
    ratio = rows[-1]["step_median_ms"] / rows[0]["step_median_ms"]
    print(
        f"step median, N = {rows[-1]['vehicles']} over N = {rows[0]['vehicles']}: {ratio:.2f}"
        f" (machine load before: {load_before})"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"rows": rows, "step_median_ratio": ratio, "load": load_before}, indent=1)
        )
    return 0
