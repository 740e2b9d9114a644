"""`fleetmpc suite --faults DIR`: the fault matrix, every network fault file of DIR against the
paper's scenario and a larger one, in lockstep, each beside the same run without faults.

A row per (scenario, fault file): the formation RMS of the last 10 s against the fault-free
run's, the minimum separation, the neighbour plan ages the agents used (p99, largest), what the
faults did and what the receivers dropped, and the recovery: how long after the faults' end
the worst vehicle is back within `RECOVERED_M` of its slot for good. Gates: separation at least
d_safe, and formation RMS at most `FORMATION_FACTOR` times the fault-free run's. Exit status 1
when a gate is missed.
"""

import argparse
import json
import math
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from fleetmpc.bus.faults import FaultSchedule, load_faults
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import load_scenario, toml_files

__all__ = ["DEFAULT_SCENARIOS", "FORMATION_FACTOR", "RECOVERED_M", "run"]

DEFAULT_SCENARIOS = ("scenarios/paper.toml", "scenarios/grid9.toml")
FORMATION_FACTOR = 1.5
"""Largest formation RMS of a faulty run, as a multiple of the fault-free run's."""
RECOVERED_M = 0.3
"""Recovered: the worst vehicle's distance to its slot stays within this [m]."""


def _fault_end_s(schedule: FaultSchedule) -> float:
    return max(f.start_s + f.duration_s for f in schedule.faults)


def _recovery_s(rec, end_s: float) -> float | None:
    """Time from `end_s` until the worst slot distance stays within RECOVERED_M; None when
    the faults last to the end, inf when it never settles."""
    if not math.isfinite(end_s) or end_s >= rec.t_s[-1]:
        return None
    worst = np.max(np.linalg.norm(rec.truth[:, :, :2] - rec.slots, axis=2), axis=1)
    after = np.flatnonzero(rec.t_s >= end_s)
    out = after[worst[after] > RECOVERED_M]
    if out.size == 0:
        return 0.0
    if out[-1] == len(rec.t_s) - 1:
        return math.inf
    return float(rec.t_s[out[-1] + 1] - end_s)


def _fly(task: tuple[str, str | None]) -> dict:
    scenario_path, fault_path = task
    sc = load_scenario(scenario_path)
    schedule = None
    if fault_path is not None:
        schedule = load_faults(fault_path, vehicle_ids=sc.vehicle_ids)
    rec = run_lockstep(sc, faults=schedule)
    m = compute_metrics(rec)
    network = m.get("network") or {}
    return {
        "scenario": sc.name,
        "faults": None if fault_path is None else Path(fault_path).stem,
        "formation_rms_m": m["formation_rms_m"],
        "min_separation_m": m["min_separation_m"],
        "d_safe_m": sc.controller.d_safe_m,
        "plan_age_p99_s": m["plan_age_s"]["p99"],
        "plan_age_max_s": m["plan_age_s"]["max"],
        "qp_fallbacks": m["qp_fallbacks"],
        "injected": network.get("injected", {}),
        "received": network.get("received", {}),
        "recovery_s": None if schedule is None else _recovery_s(rec, _fault_end_s(schedule)),
    }


def _cell(x: float | None, fmt: str) -> str:
    if x is None:
        return "-"
    return "never" if x == math.inf else format(x, fmt)


def format_table(rows: list[dict]) -> str:
    head = (
        f"{'scenario':<10} {'faults':<18} {'form RMS m':>10} {'no faults':>9} {'ratio':>6} "
        f"{'min sep m':>9} {'age p99 s':>9} {'age max s':>9} {'recovery s':>10} {'QP fb':>5}"
        "  what the faults did; dropped by receivers (dup / out of order)  gates"
    )
    lines = [head]
    for r in rows:
        did = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in r["injected"].items() if v)
        got = r["received"]
        lines.append(
            f"{r['scenario']:<10} {r['faults']:<18} {r['formation_rms_m']:>10.3f} "
            f"{r['baseline_rms_m']:>9.3f} {r['ratio']:>6.2f} {r['min_separation_m']:>9.2f} "
            f"{_cell(r['plan_age_p99_s'], '.2f'):>9} {_cell(r['plan_age_max_s'], '.2f'):>9} "
            f"{_cell(r['recovery_s'], '.1f'):>10} {r['qp_fallbacks']:>5}  "
            f"{did or 'nothing'}; {got.get('duplicates', 0)} / {got.get('out_of_order', 0)}  "
            f"{', '.join(r['gates_failed']) or 'ok'}"
        )
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    folder = Path(args.faults)
    files = toml_files(folder, field="--faults", what="fault file")
    scenarios = list(args.fault_scenarios or DEFAULT_SCENARIOS)
    for path in scenarios:  # refuse a bad file before flying anything
        sc = load_scenario(path)
        for f in files:
            load_faults(f, vehicle_ids=sc.vehicle_ids)
    tasks = [(s, None) for s in scenarios] + [(s, str(f)) for s in scenarios for f in files]
    jobs = max(1, (os.cpu_count() or 1) if args.jobs is None else args.jobs)
    t0 = time.monotonic()
    with ProcessPoolExecutor(max_workers=min(jobs, len(tasks))) as pool:
        results = list(pool.map(_fly, tasks))
    wall_s = time.monotonic() - t0
    baseline = {r["scenario"]: r["formation_rms_m"] for r in results if r["faults"] is None}
    rows = []
    for r in results:
        if r["faults"] is None:
            continue
        r["baseline_rms_m"] = baseline[r["scenario"]]
        r["ratio"] = r["formation_rms_m"] / r["baseline_rms_m"]
        r["gates_failed"] = [
            name
            for name, missed in (
                ("separation", r["min_separation_m"] < r["d_safe_m"]),
                ("formation", r["ratio"] > FORMATION_FACTOR),
            )
            if missed
        ]
        rows.append(r)
    print(format_table(rows))
    failed = sorted({g for r in rows for g in r["gates_failed"]})
    args.json.parent.mkdir(parents=True, exist_ok=True)
    doc = {"faults": str(folder), "scenarios": scenarios, "wall_time_s": wall_s, "rows": rows}
    args.json.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"{len(tasks)} runs in {wall_s:.1f} s wall time on {jobs} workers; JSON: {args.json}")
    if failed:
        print(f"gates missed: {', '.join(failed)}")
        return 1
    print("every gate held")
    return 0
