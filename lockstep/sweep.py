"""`fleetmpc sweep SCENARIO...`: fly a grid of scenarios x varied fields x learning x faults x
seeds on a cluster engine, keep one row per run, draw the figures (docs/sweeps.md).

    fleetmpc sweep scenarios/paper.toml --vary controller.horizon=5,10,15 --seeds 20

Every run is flown in lockstep (`fleetmpc.lockstep.suite.fly_row`, as the suite's) on Dask's
distributed scheduler (a local cluster of this machine's cores, or ``--scheduler ADDRESS``'s)
or, with ``--engine local`` or without the ``cluster`` extra, a process pool. Each finished run
is written at once to ``OUT/runs/<run id>.parquet``; at the end (also after Ctrl-C) the table
``OUT/results.parquet`` holds every run of the grid that has finished, with the gates applied,
and ``OUT/figures/`` the figures. ``--resume`` flies only the runs of the grid without a file.

Exit status: 0 when every run flew, 1 when some failed (their rows say why), 2 for a bad
argument (nothing flies), 130 after Ctrl-C.
"""

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from fleetmpc.errors import ConfigError
from fleetmpc.lockstep import suite
from fleetmpc.lockstep.engine import (
    EngineLost,
    Finished,
    add_engine_arguments,
    dask_available,
    engine_of,
    run_tasks,
)
from fleetmpc.lockstep.sweep_figures import write_sweep_figures
from fleetmpc.lockstep.sweep_grid import Axis, RunSpec, parse_vary, plan_runs, split_values
from fleetmpc.lockstep.sweep_run import code_version, fly_spec, spec_row
from fleetmpc.lockstep.sweep_store import METRIC_COLUMNS, ResultStore
from fleetmpc.scenario import toml_files

__all__ = ["DEFAULT_OUT", "TIME_LIMIT_S", "add_arguments", "gated_rows", "run", "sweep"]

DEFAULT_OUT = Path("runs/sweep")
TIME_LIMIT_S = 600.0
"""Default wall time after which a run is stopped and recorded as failed [s]."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenarios", nargs="+", metavar="SCENARIO", help="scenario TOML files or folders of them"
    )
    parser.add_argument(
        "--vary",
        action="append",
        default=[],
        metavar="PATH=V1,V2",
        help="fly each value of a scenario field by its dotted path (controller.horizon=5,10;"
        " vehicles[*].truth.speed_effectiveness=0.8,1.0; faults[0].probability=0.1,0.3 for the"
        " fault file); repeatable: the grid is every combination",
    )
    parser.add_argument(
        "--seeds", type=int, default=3, metavar="K", help="seeds per grid point (default: 3)"
    )
    parser.add_argument(
        "--learning",
        default="on",
        metavar="on,off",
        help="learning on, off, or both (on,off) (default: on)",
    )
    parser.add_argument(
        "--faults",
        metavar="FILE[,FILE]",
        help="fault file(s) to fly, comma-separated; 'none' for runs without (default: none)",
    )
    parser.add_argument(
        "--duration", type=float, metavar="S", help="simulated seconds (default: each scenario's)"
    )
    parser.add_argument(
        "--time-limit",
        type=float,
        default=TIME_LIMIT_S,
        metavar="S",
        help="wall time after which a run's process is killed, whatever it is doing, and the run"
        " recorded as failed (default: %(default)g s)",
    )
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help="results folder (default: %(default)s)"
    )
    parser.add_argument(
        "--resume", action="store_true", help="complete the sweep in --out: fly what is missing"
    )
    parser.add_argument(
        "--retry-failed",
        action="store_true",
        help="with --resume, fly the runs recorded as failed again too",
    )
    parser.add_argument(
        "--jobs", type=int, default=None, metavar="J", help="local workers (default: CPUs)"
    )
    add_engine_arguments(parser, default="dask, or local without the cluster extra")
    parser.add_argument("--no-figures", action="store_true", help="the table only")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _learning(text: str) -> tuple[bool, ...]:
    words = {"on": True, "off": False}
    values = split_values(text)
    if not values or any(v not in words for v in values) or len(set(values)) != len(values):
        raise ConfigError("--learning", f"must be on, off or on,off, got {text!r}")
    return tuple(words[v] for v in values)


def _fault_files(text: str | None) -> list[str | None]:
    if text is None:
        return [None]
    files = [None if f == "none" else f for f in split_values(text)]
    if len(set(files)) != len(files) or any(f == "" for f in files):
        raise ConfigError("--faults", f"a file is given twice or empty: {text!r}")
    return files


def _scenario_files(items: Sequence[str]) -> list[Path]:
    files = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            files += toml_files(path, field="SCENARIO", what="scenario")
        elif path.is_file():
            files.append(path)
        else:
            raise ConfigError("SCENARIO", f"no such file or folder: {path}")
    return files


class _Bar:
    """Runs done and failed, and the time left: a bar on a terminal, a line per tenth else."""

    def __init__(self, total: int, *, quiet: bool) -> None:
        self.total, self.done, self.failed, self.retried = total, 0, 0, 0
        self._t0 = time.monotonic()
        self._tenth = 0
        self._quiet = quiet
        console = Console(file=sys.stderr)
        self._live = None
        if not quiet and console.is_terminal:
            self._live = Progress(
                TextColumn("sweep"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("failed {task.fields[failed]}"),
                TimeElapsedColumn(),
                TextColumn("left"),
                TimeRemainingColumn(),
                console=console,
            )
            self._task = self._live.add_task("sweep", total=total, failed=0)
            self._live.start()

    def advance(self, *, failed: bool) -> None:
        self.done += 1
        self.failed += failed
        if self._live is not None:
            self._live.update(self._task, completed=self.done, failed=self.failed)
        elif not self._quiet and self.done * 10 // self.total > self._tenth:
            self._tenth = self.done * 10 // self.total
            elapsed = time.monotonic() - self._t0
            left = elapsed / self.done * (self.total - self.done)
            print(
                f"sweep: {self.done}/{self.total} runs, {self.failed} failed, "
                f"{elapsed:.0f} s, about {left:.0f} s left",
                file=sys.stderr,
                flush=True,
            )

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None


def gated_rows(rows: Sequence[dict]) -> list[dict]:
    """The table's rows with ``learning_ratio`` and ``gates_failed`` (`suite.apply_gates`): a
    learning-on run is paired with the learning-off run of the same inputs otherwise."""
    judged = []
    for r in rows:
        row = dict(r)
        if r["status"] != "ok":  # no numbers: the suite's error row
            row = {k: v for k, v in row.items() if k not in METRIC_COLUMNS}
        row["file"] = json.dumps([r["file"], r["overrides"], r["faults"]])
        judged.append(row)
    gated = suite.apply_gates(judged)
    return [
        {**r, "learning_ratio": g["learning_ratio"], "gates_failed": g["gates_failed"]}
        for r, g in zip(rows, gated, strict=True)
    ]


def sweep(
    specs: Sequence[RunSpec],
    store: ResultStore,
    *,
    engine: str,
    jobs: int | None,
    scheduler: str | None,
    time_limit_s: float | None = TIME_LIMIT_S,
    quiet: bool,
    on_row=None,
) -> tuple[int, int]:
    """Fly the specs, writing each run's row as it finishes, a run stopped as failed after
    `time_limit_s` of wall time; (runs flown, runs failed)."""
    bar = _Bar(len(specs), quiet=quiet)

    def finished(done: Finished) -> None:
        row = {
            **done.row,
            "attempts": done.attempts,
            "first_error": done.first_error,
            "worker": done.worker,
        }
        store.write(row)
        bar.advance(failed=row["status"] != "ok")
        if on_row is not None:
            on_row(row)

    def error_row(spec: RunSpec, error: str) -> dict:
        flown = suite.error_row(
            file=spec.file, seed=spec.seed, learning=spec.learning, error=error, wall_s=math.nan
        )
        return {**flown, **spec_row(spec), "status": "failed", "version": code_version()}

    def started(where: str) -> None:
        if not quiet:
            print(f"flying on {where}", file=sys.stderr, flush=True)

    try:
        run_tasks(
            fly_spec,
            specs,
            failed=lambda row: None if row["status"] == "ok" else (row["error"] or "failed"),
            error_row=error_row,
            on_finished=finished,
            engine=engine,
            jobs=jobs,
            scheduler=scheduler,
            time_limit_s=time_limit_s,
            on_start=started,
        )
    finally:
        bar.close()
    return bar.done, bar.failed


def run(args: argparse.Namespace) -> int:
    axes: list[Axis] = [parse_vary(v) for v in args.vary]
    if args.duration is not None:
        if not args.duration > 0:
            raise ConfigError("--duration", f"must be > 0, got {args.duration}")
        if any(a.path == "duration_s" for a in axes):
            raise ConfigError("--duration", "duration_s is varied already (--vary duration_s=...)")
        axes.append(Axis("duration_s", (args.duration,)))
    if args.time_limit is not None and not args.time_limit > 0:
        raise ConfigError("--time-limit", f"must be > 0, got {args.time_limit}")
    if args.retry_failed and not args.resume:
        raise ConfigError("--retry-failed", "goes with --resume")
    engine = engine_of(args, default="dask" if dask_available() else "local")
    specs = plan_runs(
        _scenario_files(args.scenarios),
        axes,
        seeds=args.seeds,
        learning=_learning(args.learning),
        fault_files=_fault_files(args.faults),
    )
    store = ResultStore(args.out, axes)
    store.open(resume=args.resume)
    ids = [s.run_id for s in specs]
    have = store.finished(ids)
    todo = [
        s for s in specs if s.run_id not in have or (args.retry_failed and have[s.run_id] != "ok")
    ]
    plan = {
        "scenarios": sorted({s.file for s in specs}),
        "vary": {a.path: list(a.values) for a in axes},
        "seeds": args.seeds,
        "learning": args.learning,
        "faults": args.faults,
        "runs": len(specs),
        "run_ids": ids,
    }
    (store.folder / "sweep.json").write_text(json.dumps(plan, indent=2) + "\n")
    print(
        f"{len(specs)} runs in the grid: {len(specs) - len(todo)} done already, {len(todo)} to fly"
    )
    t0 = time.monotonic()
    try:
        flown, failed = sweep(
            todo,
            store,
            engine=engine,
            jobs=args.jobs,
            scheduler=args.scheduler,
            time_limit_s=args.time_limit,
            quiet=args.quiet,
        )
    except (KeyboardInterrupt, EngineLost) as e:
        rows = gated_rows(store.read(ids).to_pylist())
        store.write_table(rows)
        what = "interrupted" if isinstance(e, KeyboardInterrupt) else f"stopped: {e}"
        print(
            f"{what}; {len(rows)} of {len(specs)} runs written in {store.folder}: the same "
            "command with --resume flies the rest",
            file=sys.stderr,
        )
        return 130 if isinstance(e, KeyboardInterrupt) else 1
    wall_s = time.monotonic() - t0
    rows = gated_rows(store.read(ids).to_pylist())
    table_path = store.write_table(rows)
    print(f"{flown} runs flown in {wall_s:.1f} s, {failed} failed; table: {table_path}")
    _report(rows, store, ids)
    if not args.no_figures:
        varied = [a.path for a in axes if len(a.values) > 1]
        paths = write_sweep_figures(rows, varied, store.folder / "figures", seeds=args.seeds)
        print(f"{len(paths) // 2} figures (PNG and SVG) in {store.folder / 'figures'}")
    return 1 if any(r["status"] != "ok" for r in rows) else 0


def _report(rows: Sequence[dict], store: ResultStore, ids: Sequence[str]) -> None:
    """What the table holds besides the numbers: other grids' runs, versions, gates, errors."""
    others = store.other_runs(ids)
    if others:
        print(f"({others} runs of another grid in {store.runs} are not in the table)")
    versions = sorted({r["version"] for r in rows})
    if len(versions) > 1:
        print(f"note: the rows were flown by {len(versions)} versions: {', '.join(versions)}")
    misses: dict[str, int] = {}
    for r in rows:
        for g in r["gates_failed"]:
            misses[g] = misses.get(g, 0) + 1
    if misses:
        print("gates missed: " + ", ".join(f"{g} in {n} runs" for g, n in sorted(misses.items())))
    errors = sorted({r["error"] for r in rows if r["status"] != "ok"})
    for e in errors[:5]:
        print(f"failed: {e}")
