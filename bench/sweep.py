"""`fleetmpc bench --sweep`: the sweep engine's overhead and its memory over many runs.

1. Throughput: the same 48-run sweep (the scenario x controller.horizon 4, 5, 6 x 16 seeds,
   the scenario's duration) on the local process pool and on Dask with `--jobs` workers, in
   turn for `--repeats` rounds: Dask both as `fleetmpc sweep` starts it (a local cluster, its
   start-up timed) and against a cluster started beforehand (a scheduler address, as on a
   cluster the user runs). Each flies into a fresh folder and writes every row; the figures are
   left out (they cost the same on both). Reported: the median wall time of each and its ratio
   to the pool's (issue 41's gate: at most 1.25).
2. Memory: `--sweep-runs` runs of 10 s (the scenario x controller.horizon 4, 5 x seeds) on the
   default engine, the resident memory of this process (the coordinator) and of its children
   (the workers) sampled at every tenth of the runs, then the table and the figures timed.
   Reported: the samples, the growth from the first tenth to the end, and over the last half,
   once Dask's bounded logs (`engine.WORKER_CONFIG`) have filled (issue 41's gate: flat).
3. The engines' own cost: the throughput's three engines again with runs that only sleep
   (`IDLE_RUN_S`, about a paper run's wall time) in their run processes, so that the load of a
   shared machine, which moves the flown runs' times, hardly moves theirs. Reported: each
   engine's median time over the ideal (runs x sleep / workers): start-up, round trips, close.

Wall-clock times on this machine, whose load is reported with them; nothing is asserted.
"""

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from fleetmpc.bench.step import load_average
from fleetmpc.lockstep.engine import dask_available, local_cluster, run_tasks
from fleetmpc.lockstep.sweep import gated_rows, sweep
from fleetmpc.lockstep.sweep_figures import write_sweep_figures
from fleetmpc.lockstep.sweep_grid import Axis, plan_runs
from fleetmpc.lockstep.sweep_store import ResultStore

__all__ = ["run"]

THROUGHPUT_RUNS = 48
GATE_RATIO = 1.25
IDLE_RUN_S = 0.175
"""What a run of the engines' own cost does: sleep this long [s] (a 30-s paper run's wall time
on a quiet core)."""


def _rss_mb() -> tuple[float, float]:
    """Resident memory of this process and of all its children [MB]."""
    import psutil

    me = psutil.Process()
    children = 0
    for child in me.children(recursive=True):
        try:
            children += child.memory_info().rss
        except psutil.Error:
            continue
    return me.memory_info().rss / 1e6, children / 1e6


def _timed_sweep(specs, axes, folder: Path, **engine) -> float:
    store = ResultStore(folder, axes)
    store.open(resume=False)
    t0 = time.monotonic()
    done, failed = sweep(specs, store, quiet=True, **engine)
    wall_s = time.monotonic() - t0
    if done != len(specs) or failed:
        raise RuntimeError(f"{failed} of {done} runs failed in {folder}")
    return wall_s


def _throughput(scenario: str, *, jobs: int, repeats: int, tmp: Path) -> dict:
    axes = [Axis("controller.horizon", (4, 5, 6))]
    specs = plan_runs([scenario], axes, seeds=THROUGHPUT_RUNS // 3)
    times: dict[str, list[float]] = {"local": [], "dask": [], "dask_running": []}
    with local_cluster(jobs) as cluster:  # as the sweep starts one
        for k in range(repeats):
            order = ["local", "dask", "dask_running"]
            for name in order if k % 2 == 0 else order[::-1]:
                engine = {"engine": "local" if name == "local" else "dask", "jobs": jobs}
                engine["scheduler"] = cluster.scheduler_address if name == "dask_running" else None
                wall_s = _timed_sweep(specs, axes, tmp / f"{name}-{k}", **engine)
                times[name].append(wall_s)
                print(f"  round {k + 1}: {name:<13} {wall_s:6.2f} s", flush=True)
    med = {name: statistics.median(v) for name, v in times.items()}
    return {
        "runs": len(specs),
        "wall_s": times,
        "median_s": med,
        "ratio_dask": med["dask"] / med["local"],
        "ratio_dask_running": med["dask_running"] / med["local"],
    }


def _idle_run(spec) -> dict:
    """A run that costs no CPU: the engine's part of a sweep is what remains."""
    time.sleep(IDLE_RUN_S)
    return {"run_id": spec.run_id}


def _idle_sweep(specs, **engine) -> float:
    done = []
    t0 = time.monotonic()
    run_tasks(
        _idle_run,
        specs,
        failed=lambda row: None,
        error_row=lambda spec, error: {"run_id": spec.run_id, "error": error},
        on_finished=done.append,
        time_limit_s=600.0,  # run processes, as the sweep's
        **engine,
    )
    if len(done) != len(specs):
        raise RuntimeError(f"{len(done)} of {len(specs)} idle runs came back")
    return time.monotonic() - t0


def _engine_cost(scenario: str, *, jobs: int, repeats: int) -> dict:
    specs = plan_runs(
        [scenario], [Axis("controller.horizon", (4, 5, 6))], seeds=THROUGHPUT_RUNS // 3
    )
    ideal_s = len(specs) * IDLE_RUN_S / jobs
    times: dict[str, list[float]] = {"local": [], "dask": [], "dask_running": []}
    with local_cluster(jobs) as cluster:
        for _ in range(repeats):
            for name in times:
                engine = {"engine": "local" if name == "local" else "dask", "jobs": jobs}
                engine["scheduler"] = cluster.scheduler_address if name == "dask_running" else None
                times[name].append(_idle_sweep(specs, **engine))
    over = {name: statistics.median(v) - ideal_s for name, v in times.items()}
    return {"runs": len(specs), "ideal_s": ideal_s, "wall_s": times, "over_ideal_s": over}


def _memory(scenario: str, *, runs: int, jobs: int, tmp: Path) -> dict:
    axes = [Axis("controller.horizon", (4, 5)), Axis("duration_s", (10.0,))]
    specs = plan_runs([scenario], axes, seeds=max(1, runs // 2))[:runs]
    store = ResultStore(tmp / "memory", axes)
    store.open(resume=False)
    samples = []
    every = max(1, len(specs) // 10)
    count = 0
    t0 = time.monotonic()

    def sample(row: dict) -> None:
        nonlocal count
        count += 1
        if count % every == 0 or count == len(specs):
            me, children = _rss_mb()
            samples.append(
                {"runs": count, "s": time.monotonic() - t0, "self_mb": me, "workers_mb": children}
            )
            print(
                f"  {count:5d} runs  {time.monotonic() - t0:6.1f} s  coordinator {me:7.1f} MB"
                f"  workers {children:7.1f} MB",
                flush=True,
            )

    engine = "dask" if dask_available() else "local"
    done, failed = sweep(
        specs, store, engine=engine, jobs=jobs, scheduler=None, quiet=True, on_row=sample
    )
    flown_s = time.monotonic() - t0
    t1 = time.monotonic()
    rows = gated_rows(store.read([s.run_id for s in specs]).to_pylist())
    store.write_table(rows)
    figures = write_sweep_figures(rows, ["controller.horizon"], tmp / "memory" / "figures", seeds=1)
    after_s = time.monotonic() - t1
    first, middle, last = samples[0], samples[len(samples) // 2], samples[-1]
    return {
        "engine": engine,
        "runs": done,
        "failed": failed,
        "flown_s": flown_s,
        "table_and_figures_s": after_s,
        "figures": len(figures),
        "samples": samples,
        "coordinator_growth_mb": last["self_mb"] - first["self_mb"],
        "workers_growth_mb": last["workers_mb"] - first["workers_mb"],
        "coordinator_growth_last_half_mb": last["self_mb"] - middle["self_mb"],
        "workers_growth_last_half_mb": last["workers_mb"] - middle["workers_mb"],
    }


def run(args: argparse.Namespace) -> int:
    load_before = load_average()
    out: dict = {"scenario": args.scenario, "jobs": args.jobs, "load_before": load_before}
    with tempfile.TemporaryDirectory(prefix="fleetmpc-bench-sweep-") as tmp:
        if dask_available():
            print(f"throughput: {THROUGHPUT_RUNS} runs of {args.scenario}, {args.jobs} workers")
            t = _throughput(args.scenario, jobs=args.jobs, repeats=args.repeats, tmp=Path(tmp))
            out["throughput"] = t
            med = t["median_s"]
            print(
                f"median wall time: pool {med['local']:.2f} s, dask (local cluster, start-up"
                f" included) {med['dask']:.2f} s = {t['ratio_dask']:.2f}x, dask (running"
                f" cluster) {med['dask_running']:.2f} s = {t['ratio_dask_running']:.2f}x"
                f" (gate: at most {GATE_RATIO}x)"
            )
            c = _engine_cost(args.scenario, jobs=args.jobs, repeats=args.repeats)
            out["engine_cost"] = c
            over = c["over_ideal_s"]
            print(
                f"engines' own cost ({c['runs']} runs that sleep {IDLE_RUN_S} s, ideal"
                f" {c['ideal_s']:.2f} s): median over it: pool {over['local']:.2f} s, dask (local"
                f" cluster) {over['dask']:.2f} s, dask (running cluster)"
                f" {over['dask_running']:.2f} s"
            )
        else:
            print("throughput: skipped, Dask is not installed (pip install 'fleetmpc[cluster]')")
        print(f"memory: {args.sweep_runs} runs of 10 s")
        m = _memory(args.scenario, runs=args.sweep_runs, jobs=args.jobs, tmp=Path(tmp))
        out["memory"] = m
        print(
            f"{m['runs']} runs ({m['failed']} failed) in {m['flown_s']:.1f} s on {m['engine']};"
            f" table and {m['figures'] // 2} figures in {m['table_and_figures_s']:.1f} s;"
            f" from the first tenth to the end: coordinator {m['coordinator_growth_mb']:+.1f} MB,"
            f" workers {m['workers_growth_mb']:+.1f} MB; over the last half (once Dask's"
            f" bounded logs are full): coordinator {m['coordinator_growth_last_half_mb']:+.1f} MB,"
            f" workers {m['workers_growth_last_half_mb']:+.1f} MB"
        )
    out["load_after"] = load_average()
    print(f"load average before {load_before}, after {out['load_after']}")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0
