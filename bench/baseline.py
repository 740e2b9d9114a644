"""`fleetmpc bench --baseline DIR`: this tree's speed against another checkout's, side by side.

Speed is quoted as a ratio measured in one run on one machine. DIR is another checkout of this
repository (e.g. `git worktree add /tmp/base <commit>`). For each of `--repeats` rounds, each tree
flies the scenario in a process of its own (`sys.executable` with PYTHONPATH and the working
directory at the tree), the two in turn and in alternating order, so that both see the same
machine. Each tree flies its own copy of the scenario file (the same path in that checkout), where
it has one: the table says when the two differ. A process flies a short warm-up, then the scenario
with the tree's `run_lockstep` (`fleetmpc.lockstep.flight`, or where an older checkout has it:
`_LAYOUTS`), and reports the agent step times its FlightRecord holds (`step_time_ms`, one per agent
and period) and the wall time of the run. Per tree: the median and p99 of the agent steps of every
round pooled, and the median of the rounds' real-time factors (simulated seconds per wall second);
then this tree over the baseline for each. Wall-clock times; nothing is asserted.
"""

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from fleetmpc.bench.step import load_average
from fleetmpc.errors import FleetMpcError

__all__ = ["TARGETS", "THIS_TREE", "compare", "run"]

THIS_TREE = Path(__file__).resolve().parents[1]
"""The checkout this module belongs to."""

TARGETS = {
    "step_median_over_baseline": 0.33,
    "step_p99_over_baseline": 0.5,
    "lockstep_realtime_factor": 100.0,
}
"""The speed targets against a baseline (docs/benchmarks.md, "The control period at a third of
its cost"): this tree's agent step median at most a third of the baseline's and its p99 at most
half, and its lockstep at least 100x real time."""

_LAYOUTS = (
    ("lockstep/flight.py", "fleetmpc/scenario.py", "fleetmpc.lockstep.flight", "fleetmpc.scenario"),
    ("sim/lockstep.py", "fleetmpc/scenario.py", "fleetmpc.sim.lockstep", "fleetmpc.scenario"),
    ("gcs/lockstep.py", "protocol/scenario.py", "gcs.lockstep", "protocol.scenario"),
)
"""The layouts a checkout may have, newest first: the two files that tell it, and the modules
its `run_lockstep` and `load_scenario` are in. The lockstep was `sim/` before it was named for
what it is (f3acd72); before the `fleetmpc` package each part was a top-level package."""

_CHILD = """
import importlib, json, os, sys, time
if os.path.exists("fleetmpc/__init__.py"):  # one package whose parts are top-level folders
    import fleetmpc
    fleetmpc.__path__.append(os.getcwd())  # as pyproject's package-dir maps them
run_lockstep = importlib.import_module(sys.argv[2]).run_lockstep
load_scenario = importlib.import_module(sys.argv[3]).load_scenario

scenario = load_scenario(sys.argv[1])
run_lockstep(scenario, duration_s=2.0)  # warm-up: a process's first steps pay for first calls
t0 = time.perf_counter()
record = run_lockstep(scenario)
wall_s = time.perf_counter() - t0
packages = ("fleetmpc", "gcs", "onboard", "protocol", "sitl")
ours = [m for name, m in sys.modules.items() if name.split(".")[0] in packages]
result = {
    "duration_s": scenario.duration_s,
    "wall_s": wall_s,
    "step_ms": record.step_time_ms.ravel().tolist(),
    "modules": [m.__file__ for m in ours if getattr(m, "__file__", None)],
}
print(json.dumps(result))
"""
"""One tree's measurement, run as `python -c _CHILD SCENARIO LOCKSTEP_MODULE SCENARIO_MODULE` in
that tree."""


def _fly(tree: Path, scenario: Path) -> dict:
    """Fly the scenario once in a process running the tree's code; the child's report."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(scenario), *_modules(tree)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        tail = "\n".join(done.stderr.strip().splitlines()[-5:])
        raise FleetMpcError(f"the run in {tree} failed (exit {done.returncode}):\n{tail}")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    strays = [f for f in report["modules"] if not Path(f).resolve().is_relative_to(tree)]
    if strays:
        raise FleetMpcError(f"the run in {tree} imported code from elsewhere: {strays[0]}")
    return report


def _describe(tree: Path) -> str:
    """The tree's commit, with `-dirty` when it has uncommitted changes (`git describe`)."""
    done = subprocess.run(
        ["git", "-C", str(tree), "describe", "--always", "--dirty"],
        capture_output=True,
        text=True,
        check=False,
    )
    return done.stdout.strip() if done.returncode == 0 else "not a git checkout"


def _modules(tree: Path) -> tuple[str, str] | None:
    """The modules of `tree`'s `run_lockstep` and `load_scenario` (`_LAYOUTS`), None when it is
    no checkout of fleetmpc."""
    for lockstep, scenario, *modules in _LAYOUTS:
        if (tree / lockstep).is_file() and (tree / scenario).is_file():
            return tuple(modules)
    return None


def _tree(path: str | Path, *, role: str) -> Path:
    tree = Path(path).resolve()
    if _modules(tree) is None:
        files = ", ".join(lockstep for lockstep, *_ in _LAYOUTS)
        raise FleetMpcError(f"{role}: {tree} is not a checkout of fleetmpc (no {files})")
    return tree


def _scenario_in(tree: Path, path: Path) -> Path:
    """The scenario file `tree` flies: a file of this checkout at the same place in `tree`,
    where that has one (a file changed since the other tree was written may use keys its code
    does not know: each tree flies it as it wrote it), otherwise `path` itself."""
    if path.is_relative_to(THIS_TREE) and (tree / path.relative_to(THIS_TREE)).is_file():
        return tree / path.relative_to(THIS_TREE)
    return path


def _summary(reports: list[dict]) -> dict:
    steps = np.concatenate([r["step_ms"] for r in reports])
    factors = [r["duration_s"] / r["wall_s"] for r in reports]
    return {
        "step_median_ms": float(np.median(steps)),
        "step_p99_ms": float(np.percentile(steps, 99)),
        "steps": int(steps.size),
        "realtime_factor": float(np.median(factors)),
        "round_step_medians_ms": [float(np.median(r["step_ms"])) for r in reports],
        "round_realtime_factors": factors,
    }


def compare(
    scenario: str | Path, *, baseline: str | Path, rounds: int, tree: str | Path = THIS_TREE
) -> dict:
    """Measure `tree` (this one by default) and the baseline tree on the scenario, `rounds` times
    each, in turn; their figures and tree / baseline."""
    trees = {"this": _tree(tree, role="tree"), "baseline": _tree(baseline, role="--baseline")}
    path = Path(scenario).resolve()
    if not path.is_file():
        raise FleetMpcError(f"scenario: no such file: {scenario}")
    files = {name: _scenario_in(t, path) for name, t in trees.items()}
    reports: dict[str, list[dict]] = {name: [] for name in trees}
    for r in range(rounds):
        order = list(trees) if r % 2 == 0 else list(reversed(trees))
        for name in order:
            reports[name].append(_fly(trees[name], files[name]))
    this, base = _summary(reports["this"]), _summary(reports["baseline"])
    return {
        "scenario": str(path),
        "rounds": rounds,
        "trees": {
            name: {"path": str(t), "commit": _describe(t), "scenario": str(files[name])}
            for name, t in trees.items()
        },
        "same_scenario_file": files["this"].read_bytes() == files["baseline"].read_bytes(),
        "this": this,
        "baseline": base,
        "this_over_baseline": {
            key: this[key] / base[key]
            for key in ("step_median_ms", "step_p99_ms", "realtime_factor")
        },
        "round_ratios": {
            "step_median": [
                a / b
                for a, b in zip(
                    this["round_step_medians_ms"], base["round_step_medians_ms"], strict=True
                )
            ],
            "realtime_factor": [
                a / b
                for a, b in zip(
                    this["round_realtime_factors"], base["round_realtime_factors"], strict=True
                )
            ],
        },
        "targets": TARGETS,
    }


def run(args: argparse.Namespace) -> int:
    from fleetmpc.scenario import load_scenario

    sc = load_scenario(args.scenario)
    load_before = load_average()
    result = compare(args.scenario, baseline=args.baseline, rounds=max(args.repeats, 1))
    load_after = load_average()
    result |= {"load_average_before": load_before, "load_average_after": load_after}
    this, base, ratio = result["this"], result["baseline"], result["this_over_baseline"]
    trees = result["trees"]
    print(
        f"fleetmpc bench --baseline: scenario {sc.name!r}, M = {sc.controller.horizon}, "
        f"{len(sc.vehicles)} vehicles; {result['rounds']} rounds, each tree in its own process, "
        f"in turn (load average {load_before} before, {load_after} after)"
    )
    for name, label in (("this", "this tree"), ("baseline", "baseline")):
        tree = trees[name]
        print(f"  {label + ':':10s} {tree['path']} ({tree['commit']}), flying {tree['scenario']}")
    if not result["same_scenario_file"]:
        print("  (the two trees' scenario files differ: each flies its own)")
    print(f"  {'':28s} {'this tree':>10s} {'baseline':>10s} {'this / baseline':>16s}")
    median_target = TARGETS["step_median_over_baseline"]
    p99_target = TARGETS["step_p99_over_baseline"]
    rows = [
        (
            "agent step median ms",
            f"{this['step_median_ms']:.3f}",
            f"{base['step_median_ms']:.3f}",
            f"{ratio['step_median_ms']:.2f}x",
            f"(target <= {median_target:g}x)",
        ),
        (
            "agent step p99 ms",
            f"{this['step_p99_ms']:.3f}",
            f"{base['step_p99_ms']:.3f}",
            f"{ratio['step_p99_ms']:.2f}x",
            f"(target <= {p99_target:g}x)",
        ),
        (
            "lockstep real-time factor",
            f"{this['realtime_factor']:.0f}x",
            f"{base['realtime_factor']:.0f}x",
            f"{ratio['realtime_factor']:.2f}x",
            f"(this tree: target >= {TARGETS['lockstep_realtime_factor']:.0f}x)",
        ),
    ]
    for name, a, b, r, note in rows:
        print(f"  {name:28s} {a:>10s} {b:>10s} {r:>16s}  {note}".rstrip())
    rounds = result["round_ratios"]
    print(
        "  (this / baseline by round: step median "
        + " ".join(f"{x:.2f}" for x in rounds["step_median"])
        + "; real-time factor "
        + " ".join(f"{x:.2f}" for x in rounds["realtime_factor"])
        + ")"
    )
    print(
        f"  ({this['steps']} and {base['steps']} agent steps; this / baseline above 1x is slower"
        " for the times, below 1x for the factor)"
    )
    met = {
        "step_median_over_baseline": ratio["step_median_ms"] <= median_target,
        "step_p99_over_baseline": ratio["step_p99_ms"] <= p99_target,
        "lockstep_realtime_factor": this["realtime_factor"] >= TARGETS["lockstep_realtime_factor"],
    }
    result["targets_met"] = met
    missed = [k for k, ok in met.items() if not ok]
    print("  targets: " + ("all met" if not missed else "missed " + ", ".join(missed)))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
