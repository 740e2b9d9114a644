"""`fleetmpc suite [DIR]`: fly every scenario of a folder, over seeds, with learning on and off,
and hold each run to the gates.

Every ``*.toml`` in DIR (sorted) is flown in lockstep for seeds s, s + 1, ..., s + K - 1 (s the
scenario's own seed) with learning on and off (only off when the file itself disables learning),
one run per task on the engine of `fleetmpc sweep` (`fleetmpc.lockstep.engine`: a process pool, or
Dask with --engine dask or --scheduler ADDRESS); the suite is a sweep of no varied field. Each
task returns a row of plain numbers (the metrics the gates read, not the flight record), through
`fly_row`, which flies every sweep's runs too. Gates (the constants below) are then applied to
the rows:

- slot RMS: learning-on runs with a feasible target (`check_scenario`) hold formation_rms_m
  within `SLOT_RMS_MAX_M` (`PAPER_SLOT_RMS_MAX_M` for the paper scenario);
- learning ratio: where the truth holds dynamics the nominal model lacks (an effectiveness
  other than 1, or wind) and the target is feasible, learning cuts the formation RMS of the same
  seed to at most `LEARNING_RATIO_MAX` of the learning-off run's;
- min separation: no two vehicles ever come closer than the scenario's d_safe_m;
- reversals: at most `REVERSALS_MAX_PER_VEHICLE_MIN` yaw-rate reversals per vehicle-minute;
- QP fallbacks: at most `QP_FALLBACK_MAX_FRACTION` of the agent steps;
- corner recovery: where the target turns corners, learning-on runs with a feasible target
  settle within `CORNER_RECOVERY_MAX_S` of each;
- effectiveness: learning-on runs with a feasible target end with every vehicle's learned
  speed and yaw-rate effectiveness within `EFFECTIVENESS_ERROR_MAX` of the truth.

Each learning-on run also has a known-model run of the same seed (unless --no-known-model): the
agents told the truth's effectiveness and wind (docs/design.md, "The known-model run"). The
table shows the learned run's formation RMS over it, `learned_over_known`: how far the learner
is from the limit of this controller. It is reported, not gated; the known-model runs are
held to the every-run gates.

A run that raises (or flies past a time limit) is flown once more; if it fails again it is a row
with its error and fails the gate "error"; when only the feasibility
check raises, the run still flies and its row carries the numbers, the check's error (gate
"error") and feasible = None, judged by the other gates as if its target were feasible.

Output: a line per finished run (unless --quiet), the table, the wall time; the rows, the gates
and the wall time as JSON (non-finite numbers as JSON's Infinity, which Python's json reads
back). Exit status 1 when any gate is missed, 0 otherwise, 2 for a bad DIR or argument.
"""

import argparse
import json
import math
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.bus.faults import FaultSchedule
from fleetmpc.check.feasibility import check_scenario
from fleetmpc.errors import ConfigError
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.lockstep import engine, fault_matrix
from fleetmpc.lockstep.engine import Finished, run_tasks
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import Scenario, load_scenario, toml_files

__all__ = [
    "CORNER_RECOVERY_MAX_S",
    "DEFAULT_JSON",
    "EFFECTIVENESS_ERROR_MAX",
    "GATES",
    "LEARNING_RATIO_MAX",
    "PAPER_SCENARIO",
    "PAPER_SLOT_RMS_MAX_M",
    "QP_FALLBACK_MAX_FRACTION",
    "REVERSALS_MAX_PER_VEHICLE_MIN",
    "SLOT_RMS_MAX_M",
    "SuiteTask",
    "add_arguments",
    "apply_gates",
    "error_row",
    "fly",
    "flew",
    "fly_row",
    "format_table",
    "has_unmodeled_dynamics",
    "run",
    "suite_tasks",
]

SLOT_RMS_MAX_M = 0.15
"""Largest formation RMS (distance to slot over the last 10 s) of a learning-on run whose target
is feasible [m]."""

PAPER_SLOT_RMS_MAX_M = 0.05
"""The same for the paper's scenario (`PAPER_SCENARIO`), which the README's results hold [m]."""

PAPER_SCENARIO = "paper"
"""Name of the scenario held to `PAPER_SLOT_RMS_MAX_M`."""

LEARNING_RATIO_MAX = 0.3
"""Largest formation RMS with learning over the same seed's without, where the truth has
unmodeled dynamics and the target is feasible [-]."""

REVERSALS_MAX_PER_VEHICLE_MIN = 3.0
"""Most yaw-rate reversals per vehicle and minute of flight, every run [1/min]."""

QP_FALLBACK_MAX_FRACTION = 0.01
"""Largest share of agent steps (periods x vehicles) whose QP fell back, every run [-]."""

CORNER_RECOVERY_MAX_S = 15.0
"""Longest recovery from a corner of the target, learning-on runs with a feasible target [s]."""

EFFECTIVENESS_ERROR_MAX = 0.10
"""Largest relative error of a learned speed or yaw-rate effectiveness at the end of a
learning-on run with a feasible target [-]."""

GATES: dict[str, str] = {
    "slot_rms": f"learning on, feasible target: formation RMS <= {SLOT_RMS_MAX_M} m "
    f"({PAPER_SLOT_RMS_MAX_M} m for {PAPER_SCENARIO!r})",
    "learning_ratio": "learning on, feasible target, unmodeled dynamics: formation RMS on / off "
    f"(same seed) <= {LEARNING_RATIO_MAX}",
    "min_separation": "every run: min separation >= the scenario's d_safe_m",
    "reversals": f"every run: yaw-rate reversals <= {REVERSALS_MAX_PER_VEHICLE_MIN:g} per "
    "vehicle-minute",
    "qp_fallbacks": f"every run: QP fallbacks <= {100 * QP_FALLBACK_MAX_FRACTION:g} % of agent "
    "steps",
    "corner_recovery": "learning on, feasible target with corners: corner recovery <= "
    f"{CORNER_RECOVERY_MAX_S:g} s",
    "effectiveness": "learning on, feasible target: learned speed and yaw-rate effectiveness "
    f"within {100 * EFFECTIVENESS_ERROR_MAX:g} % of the truth at the end",
    "error": "every run: it completes",
}
"""Every gate by name, with what it asks."""

DEFAULT_JSON = Path("runs/suite/suite.json")
"""Where the JSON goes without --json."""


@dataclass(frozen=True)
class SuiteTask:
    """One run of the suite."""

    path: str
    """Scenario file."""
    seed: int
    """Random seed of the run."""
    learning: bool
    """Learn beta online (False: plain tube MPC)."""
    duration_s: float
    """Simulated seconds."""
    known_model: bool = False
    """The known-model run (learning is then True)."""


def has_unmodeled_dynamics(sc: Scenario) -> bool:
    """True when some vehicle's truth differs from the nominal model: an effectiveness other than
    1 or a wind (mean or gust)."""
    return any(
        v.truth.speed_effectiveness != 1.0
        or v.truth.yaw_rate_effectiveness != 1.0
        or any(w != 0.0 for w in v.truth.wind.mean_m_s)
        or v.truth.wind.gust_amplitude_m_s != 0.0
        for v in sc.vehicles
    )


def _load(path: Path) -> Scenario:
    try:
        return load_scenario(path)
    except ConfigError as e:
        raise ConfigError(str(path), str(e)) from None


def suite_tasks(
    paths: list[Path], *, seeds: int, duration_s: float | None = None, known_model: bool = True
) -> list[SuiteTask]:
    """The runs of the suite, in table order: file, seed, learning on then off (off only when the
    file disables learning), then the known-model run where learning is on (if `known_model`);
    each for `duration_s`, or the scenario's duration if None."""
    tasks = []
    for path in paths:
        sc = _load(path)
        learning = (True, False) if sc.learning.enabled else (False,)
        duration = sc.duration_s if duration_s is None else duration_s
        for seed in range(sc.seed, sc.seed + seeds):
            tasks += [SuiteTask(str(path), seed, on, duration) for on in learning]
            if known_model and sc.learning.enabled:
                tasks.append(SuiteTask(str(path), seed, True, duration, known_model=True))
    return tasks


def _error_text(error: BaseException) -> str:
    return traceback.format_exception_only(error)[-1].strip()


def error_row(
    *, file: str, seed: int, learning: bool, error: str, wall_s: float, known_model: bool = False
) -> dict:
    """The row of a run that did not fly: no numbers, its error."""
    return {
        "scenario": Path(file).stem,
        "file": file,
        "seed": seed,
        "learning": learning,
        "known_model": known_model,
        "error": error,
        "wall_s": wall_s,
    }


def flew(row: dict) -> bool:
    return "formation_rms_m" in row


def fly(task: SuiteTask) -> dict:
    """Fly one run (in a worker process): its row of plain numbers, or its error."""

    def load() -> tuple[Scenario, None]:
        return load_scenario(task.path).with_overrides(duration_s=task.duration_s), None

    return fly_row(
        load, file=task.path, seed=task.seed, learning=task.learning, known_model=task.known_model
    )


def fly_row(
    load: Callable[[], tuple[Scenario, FaultSchedule | None]],
    *,
    file: str,
    seed: int,
    learning: bool,
    known_model: bool = False,
) -> dict:
    """Fly the scenario (and faults) `load` gives: the run's row of plain numbers, or
    the row of its error (no numbers); `known_model`: the known-model run. `fleetmpc suite` and
    `fleetmpc sweep` fly every run through here (a run's time limit is the engine's:
    `fleetmpc.lockstep.run_process`)."""
    t0 = time.monotonic()
    check_error = None
    try:
        sc, faults = load()
        try:
            feasible = check_scenario(sc).feasible
        except Exception as e:  # feasibility unknown; the run still flies
            feasible, check_error = None, f"check: {_error_text(e)}"
        rec = run_lockstep(sc, learning=learning, seed=seed, faults=faults, known_model=known_model)
        m = compute_metrics(rec)
    except Exception as e:  # a crash is reported as a row; the other runs go on
        wall_s = time.monotonic() - t0
        return error_row(
            file=file,
            seed=seed,
            learning=learning,
            error=_error_text(e),
            wall_s=wall_s,
            known_model=known_model,
        )
    periods = len(rec.t_s)
    steps = periods * len(sc.vehicles)
    beta = m["beta_error"]
    ages = m["plan_age_s"] or {}
    return {
        "scenario": sc.name,
        "file": file,
        "seed": seed,
        "learning": learning,
        "known_model": known_model,
        "error": check_error,
        "vehicles": len(sc.vehicles),
        "d_safe_m": sc.controller.d_safe_m,
        "unmodeled_dynamics": has_unmodeled_dynamics(sc),
        "feasible": feasible,
        "duration_s": float(rec.t_s[-1]),
        "periods": periods,
        "formation_rms_m": m["formation_rms_m"],
        "slot_rms_max_vehicle_m": m["slot_rms_max_vehicle_m"],
        "separation_error_max_m": max(m["separation_error_m"], default=None),
        "centre_distance_error_m": m["centre_distance_error_m"],
        "c_norm_final": m["c_norm_final"],
        "min_separation_m": m["min_separation_m"],
        "inputs_within_bounds": m["inputs_within_bounds"],
        "yaw_rate_reversals_per_vehicle_min": m["yaw_rate_reversals_per_vehicle_min"],
        "qp_fallbacks": m["qp_fallbacks"],
        "qp_fallback_fraction": m["qp_fallbacks"] / steps,
        "target_prediction_rms_m": m["target_prediction_rms_m"],
        "corners": m["corners"],
        "corner_recovery_s": m["corner_recovery_s"],
        "beta_error_speed_max": max(b["speed_effectiveness"] for b in beta),
        "beta_error_yaw_rate_max": max(b["yaw_rate_effectiveness"] for b in beta),
        "beta_error_drift_max_m_s": max(b["drift_m_s"] for b in beta),
        "plan_age_p99_s": ages.get("p99"),
        "plan_age_max_s": ages.get("max"),
        "plan_missing_fraction": ages.get("missing_fraction"),
        "wall_s": time.monotonic() - t0,
    }


def _failures(row: dict) -> list[str]:
    failed = [] if row.get("error") is None else ["error"]
    if not flew(row):
        return failed
    judged = (  # unknown feasibility: judged
        row["learning"] and not row.get("known_model") and row["feasible"] is not False
    )
    limit = PAPER_SLOT_RMS_MAX_M if row["scenario"] == PAPER_SCENARIO else SLOT_RMS_MAX_M
    if judged and not row["formation_rms_m"] <= limit:
        failed.append("slot_rms")
    ratio = row.get("learning_ratio")
    if (
        judged
        and row["unmodeled_dynamics"]
        and ratio is not None
        and not ratio <= LEARNING_RATIO_MAX
    ):
        failed.append("learning_ratio")
    if not row["min_separation_m"] >= row["d_safe_m"]:
        failed.append("min_separation")
    if not row["yaw_rate_reversals_per_vehicle_min"] <= REVERSALS_MAX_PER_VEHICLE_MIN:
        failed.append("reversals")
    if not row["qp_fallback_fraction"] <= QP_FALLBACK_MAX_FRACTION:
        failed.append("qp_fallbacks")
    if judged and row["corners"] and not row["corner_recovery_s"] <= CORNER_RECOVERY_MAX_S:
        failed.append("corner_recovery")
    effectiveness = (row["beta_error_speed_max"], row["beta_error_yaw_rate_max"])
    if judged and not all(e <= EFFECTIVENESS_ERROR_MAX for e in effectiveness):
        failed.append("effectiveness")
    return failed


def apply_gates(rows: list[dict]) -> list[dict]:
    """The rows with `learning_ratio` (learning-on rows: formation RMS over the learning-off
    run's of the same file and seed; None without one), `learned_over_known` (the same over the
    known-model run's) and `gates_failed` (names from GATES)."""
    off = _formation_rms(rows, lambda r: not r["learning"])
    known = _formation_rms(rows, lambda r: bool(r.get("known_model")))
    out = []
    for r in rows:
        learned = r["learning"] and not r.get("known_model") and flew(r)
        key = (r["file"], r["seed"])
        r = {
            **r,
            "learning_ratio": _ratio(r, off.get(key)) if learned else None,
            "learned_over_known": _ratio(r, known.get(key)) if learned else None,
        }
        out.append({**r, "gates_failed": _failures(r)})
    return out


def _formation_rms(rows: list[dict], which: Callable[[dict], bool]) -> dict:
    """The formation RMS of the rows `which` picks that flew, by (file, seed)."""
    return {(r["file"], r["seed"]): r["formation_rms_m"] for r in rows if which(r) and flew(r)}


def _ratio(row: dict, base: float | None) -> float | None:
    return row["formation_rms_m"] / base if base is not None and base > 0.0 else None


def _number(x: float | None, fmt: str, *, none: str = "-") -> str:
    if x is None:
        return none
    return "inf" if x == math.inf else format(x, fmt)


_COLUMNS = (
    ("scenario", "<"),
    ("seed", ">"),
    ("learn", "<"),
    ("form RMS m", ">"),
    ("worst slot m", ">"),
    ("on/off", ">"),
    ("lrn/known", ">"),
    ("min sep m", ">"),
    ("rev/veh-min", ">"),
    ("QP fb %", ">"),
    ("pred RMS m", ">"),
    ("corner rec s", ">"),
    ("gates", "<"),
)


def _cells(r: dict) -> tuple[str, ...]:
    head = (r["scenario"], str(r["seed"]), "on" if r["learning"] else "off")
    verdict = ", ".join(r["gates_failed"]) or "ok"
    if not flew(r):
        return (*head, *("-" for _ in range(9)), verdict)
    corners = "-" if not r["corners"] else _number(r["corner_recovery_s"], ".1f")
    return (
        *head,
        _number(r["formation_rms_m"], ".3f"),
        _number(r["slot_rms_max_vehicle_m"], ".3f"),
        _number(r.get("learning_ratio"), ".2f"),
        _number(r.get("learned_over_known"), ".2f"),
        _number(r["min_separation_m"], ".2f"),
        _number(r["yaw_rate_reversals_per_vehicle_min"], ".2f"),
        _number(100.0 * r["qp_fallback_fraction"], ".2f"),
        _number(r["target_prediction_rms_m"], ".3f", none="unknown"),
        corners,
        verdict,
    )


def format_table(rows: list[dict]) -> str:
    """The rows (after `apply_gates`) as a text table; an infeasible target is marked '*', one
    whose feasibility is unknown (the check failed) '?'; the errors follow the table. The
    known-model runs are not lines of their own: the learned runs' `lrn/known` shows them, and
    a gate one of them misses is named on its learned run's line."""
    rows = _known_model_folded(rows)
    marks = {False: " *", None: " ?"}
    cells = [
        (c[0] + (marks.get(r["feasible"], "") if flew(r) else ""), *c[1:])
        for r, c in ((r, _cells(r)) for r in rows)
    ]
    names = [name for name, _ in _COLUMNS]
    widths = [max(len(x) for x in col) for col in zip(names, *cells, strict=True)]
    lines = []
    for line in (names, *cells):
        parts = [f"{x:{align}{w}}" for x, (_, align), w in zip(line, _COLUMNS, widths, strict=True)]
        lines.append("  ".join(parts).rstrip())
    feasibility = {r["feasible"] for r in rows if flew(r)}
    if False in feasibility:
        lines.append("* infeasible target (fleetmpc check): slot RMS, ratio and corner gates off")
    if None in feasibility:
        lines.append("? feasibility unknown (the check failed): judged as feasible")
    errors: dict[str, int] = {}
    for r in rows:
        if r.get("error") is not None:
            errors[r["error"]] = errors.get(r["error"], 0) + 1
    for message, count in errors.items():
        lines.append(f"error in {count} run{'s' if count > 1 else ''}: {message}")
    return "\n".join(lines)


def _known_model_folded(rows: list[dict]) -> list[dict]:
    """The rows but the known-model runs, whose missed gates go to their learned run's row as
    "known model: GATE"."""
    missed: dict[tuple, list[str]] = {}
    for r in rows:
        if r.get("known_model"):
            missed.setdefault((r["file"], r["seed"]), []).extend(
                f"known model: {g}" for g in r["gates_failed"]
            )
    return [
        {**r, "gates_failed": r["gates_failed"] + missed.get((r["file"], r["seed"]), [])}
        if r["learning"]
        else r
        for r in rows
        if not r.get("known_model")
    ]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dir",
        nargs="?",
        default="scenarios",
        help="folder of scenario TOML files (default: %(default)s)",
    )
    parser.add_argument(
        "--seeds", type=int, default=3, metavar="K", help="seeds per scenario (default: 3)"
    )
    parser.add_argument(
        "--jobs", type=int, default=None, metavar="J", help="worker processes (default: CPUs)"
    )
    parser.add_argument(
        "--json", type=Path, default=DEFAULT_JSON, metavar="FILE", help="JSON output file"
    )
    parser.add_argument(
        "--duration", type=float, metavar="S", help="simulated seconds (default: each scenario's)"
    )
    parser.add_argument(
        "--faults",
        metavar="FAULT_DIR",
        help="fly the fault matrix instead: every fault file of FAULT_DIR against"
        " --fault-scenario files (default: paper.toml and grid9.toml), each beside its run"
        " without faults",
    )
    parser.add_argument(
        "--fault-scenario",
        dest="fault_scenarios",
        action="append",
        metavar="FILE",
        help="a scenario for the fault matrix (repeatable)",
    )
    parser.add_argument(
        "--no-known-model",
        dest="known_model",
        action="store_false",
        help="skip the known-model runs (and the lrn/known column): a third fewer runs",
    )
    engine.add_engine_arguments(parser, default="local")
    parser.add_argument("--quiet", action="store_true", help="no line per finished run")


def failed_error(row: dict) -> str | None:
    """The error of a run that did not fly (its row has no numbers); None when it flew."""
    return None if flew(row) else (row.get("error") or "failed")


def _task_error_row(task: SuiteTask, error: str) -> dict:
    return error_row(
        file=task.path,
        seed=task.seed,
        learning=task.learning,
        error=error,
        wall_s=0.0,
        known_model=task.known_model,
    )


def _progress(done: int, total: int, row: dict) -> str:
    head = f"[{done}/{total}] {row['scenario']} seed {row['seed']} "
    head += (
        "known model"
        if row.get("known_model")
        else f"learning {'on' if row['learning'] else 'off'}"
    )
    if not flew(row):
        return f"{head}: ERROR {row['error']}"
    line = (
        f"{head}: formation RMS {row['formation_rms_m']:.3f} m, "
        f"min separation {row['min_separation_m']:.2f} m ({row['wall_s']:.1f} s)"
    )
    return line if row.get("error") is None else f"{line}; ERROR {row['error']}"


def run(args: argparse.Namespace) -> int:
    if args.faults is not None:
        if args.json == DEFAULT_JSON:
            args.json = DEFAULT_JSON.with_name("faults.json")
        return fault_matrix.run(args)
    folder = Path(args.dir)
    paths = toml_files(folder, field="DIR", what="scenario")
    if args.seeds < 1:
        raise ConfigError("--seeds", f"must be >= 1, got {args.seeds}")
    jobs = (os.cpu_count() or 1) if args.jobs is None else args.jobs
    if jobs < 1:
        raise ConfigError("--jobs", f"must be >= 1, got {jobs}")
    if args.duration is not None and not args.duration > 0:
        raise ConfigError("--duration", f"must be > 0, got {args.duration}")
    tasks = suite_tasks(
        paths, seeds=args.seeds, duration_s=args.duration, known_model=args.known_model
    )
    t0 = time.monotonic()
    results: dict[SuiteTask, dict] = {}

    def finished(done: Finished) -> None:
        results[done.task] = done.row
        if not args.quiet:
            print(_progress(len(results), len(tasks), done.row), flush=True)

    run_tasks(
        fly,
        # the longest runs first, so that none starts late while the other workers stand idle
        sorted(tasks, key=lambda t: -t.duration_s),
        failed=failed_error,
        error_row=_task_error_row,
        on_finished=finished,
        engine=engine.engine_of(args, default="local"),
        jobs=jobs,
        scheduler=args.scheduler,
    )
    wall_s = time.monotonic() - t0
    rows = apply_gates([results[t] for t in tasks])
    print(format_table(rows))
    failed = sorted({g for r in rows for g in r["gates_failed"]})
    doc = {
        "dir": str(folder),
        "seeds": args.seeds,
        "jobs": jobs,
        "wall_time_s": wall_s,
        "passed": not failed,
        "gates": GATES,
        "failed_gates": failed,
        "rows": rows,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"{len(rows)} runs in {wall_s:.1f} s wall time on {jobs} workers; JSON: {args.json}")
    if failed:
        print(f"gates missed: {', '.join(failed)}")
        return 1
    print("every gate held")
    return 0
