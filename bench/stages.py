"""`fleetmpc bench --stages`: where one agent's control period spends its time, stage by stage.

`Agent.step` is a sequence of named stages (`Agent.STAGES`: learn, observe_target,
place_formation, gather, build_qp, solve, emit; docs/design.md, "The control period"). This bench
flies the scenario in lockstep `--repeats` times with each stage, and the step around them,
wrapped in a timer at the class (the agent's code has no timers of its own), and reports per
stage the median and p99 of its calls and its share of the time spent in steps; "other" is the
step less its stages (the wait for telemetry or a target, the step's own lines, the timers'
overhead between them). Wall-clock times on this machine, whose load is reported with them.
"""

import argparse
import contextlib
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.onboard.core.agent import Agent
from fleetmpc.scenario import load_scenario

__all__ = ["run", "stage_times", "table"]


@contextlib.contextmanager
def _timing(cls: type, names: tuple[str, ...], sink: dict[str, list[int]]) -> Iterator[None]:
    """Wrap the methods `names` of cls, for the duration, to append each call's duration [ns]
    to sink[name]."""
    originals = {name: getattr(cls, name) for name in names}

    def timed(name: str, original: Callable) -> Callable:
        calls = sink.setdefault(name, [])

        def wrapper(self, *args, **kwargs):
            t0 = time.perf_counter_ns()
            try:
                return original(self, *args, **kwargs)
            finally:
                calls.append(time.perf_counter_ns() - t0)

        return wrapper

    for name, original in originals.items():
        setattr(cls, name, timed(name, original))
    try:
        yield
    finally:
        for name, original in originals.items():
            setattr(cls, name, original)


def stage_times(scenario_path: str, repeats: int) -> tuple[dict[str, list[int]], int]:
    """Durations [ns] of every call of each stage and of the step over `repeats` lockstep runs
    of the scenario (in this process), and the number of runs' vehicles."""
    sc = load_scenario(scenario_path)
    sink: dict[str, list[int]] = {}
    with _timing(Agent, (*Agent.STAGES, "step"), sink):
        for _ in range(max(repeats, 1)):
            run_lockstep(sc)
    return sink, len(sc.vehicles)


def table(sink: dict[str, list[int]]) -> list[dict[str, float | str | int]]:
    """Per stage, then "other" and the step: calls, median and p99 [ms], share of step time."""
    steps = np.asarray(sink["step"], float) * 1e-6
    total = steps.sum()
    rows: list[dict[str, float | str | int]] = []
    staged = 0.0
    for name in Agent.STAGES:
        ms = np.asarray(sink.get(name, []), float) * 1e-6
        staged += ms.sum()
        rows.append(_row(name, ms, ms.sum() / total))
    rows.append({"stage": "other", "calls": "", "median_ms": "", "p99_ms": ""})
    rows[-1]["share"] = (total - staged) / total
    rows.append(_row("step", steps, 1.0))
    return rows


def _row(name: str, ms: np.ndarray, share: float) -> dict[str, float | str | int]:
    empty = ms.size == 0
    return {
        "stage": name,
        "calls": int(ms.size),
        "median_ms": float("nan") if empty else float(np.median(ms)),
        "p99_ms": float("nan") if empty else float(np.percentile(ms, 99)),
        "share": float(share),
    }


def _format(rows: list[dict]) -> list[str]:
    lines = [f"  {'stage':16s} {'calls':>7s} {'median ms':>10s} {'p99 ms':>10s} {'share':>7s}"]
    for r in rows:
        med = r["median_ms"] if r["median_ms"] == "" else f"{r['median_ms']:.4f}"
        p99 = r["p99_ms"] if r["p99_ms"] == "" else f"{r['p99_ms']:.4f}"
        lines.append(
            f"  {r['stage']:16s} {r['calls']!s:>7s} {med:>10s} {p99:>10s} {r['share']:>6.1%}"
        )
    return lines


def run(args: argparse.Namespace) -> int:
    from fleetmpc.bench.step import load_average

    load_before = load_average()
    sink, vehicles = stage_times(args.scenario, args.repeats)
    load_after = load_average()
    rows = table(sink)
    print(
        f"fleetmpc bench --stages: {args.scenario}, {vehicles} vehicles, "
        f"{len(sink['step'])} agent steps over {max(args.repeats, 1)} lockstep runs "
        f"(load average {load_before} before, {load_after} after)"
    )
    print("\n".join(_format(rows)))
    if args.json:
        result = {"scenario": args.scenario, "load_average": [load_before, load_after]}
        Path(args.json).write_text(json.dumps({**result, "stages": rows}, indent=2) + "\n")
    return 0
