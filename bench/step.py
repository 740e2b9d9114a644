"""`fleetmpc bench`: how fast is one agent's control step, and the whole lockstep simulation?

1. Lockstep real-time factor: simulated seconds per wall second of `run_lockstep` on the scenario
   (`--repeats` uninstrumented runs; the median is reported). The per-agent step figures (median,
   p99) are pooled over the agent steps of those same uninstrumented runs.
2. The step split, from as many runs with timers around the pieces, each right after an
   uninstrumented one (the timers add a little overhead of their own): DEKF (DualEkf.step or
   .propagate), QP (OSQP's update + solve of the period's values, FixedPatternQp.update +
   .solve) and model build (the rest of the step: target estimate, slots, seeding,
   linearization, condensing, cost and constraint assembly, checks). Also the time spent inside
   filterpy's `predict` (the DEKF's parameter prediction, its one filterpy call; the target
   filter is written on numpy) and, with OSQP's, the part of the step that is library calls.
3. Side by side on the QPs recorded in the first timed run, vehicle by vehicle in flight order:
   our QP path (TubeLbmpc.solve: condense, assemble the values, update OSQP, solve with warm
   start, check) against the same QP re-built from scratch with cvxpy every step (condense with
   the same code, build the cvxpy problem, solve with OSQP through cvxpy at the same eps,
   max_iter and termination-check interval, no polishing, as ours). Both sides start from the
   same QpData and return c; the ratio is of the medians over the same sampled steps, and the
   largest difference in c is reported, with OSQP's iterations per solve of our replays.
Figures are wall-clock times on this machine, whose load is reported with them; nothing here is
asserted (speed targets belong to the benchmark, not to unit tests).

With `--baseline DIR`, instead: this tree's agent step and lockstep real-time factor against those
of another checkout, side by side in one run (`fleetmpc.bench.baseline`).
"""

import argparse
import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from fleetmpc.errors import FleetMpcError
from fleetmpc.gcs.ground_station import SERIES_FLUSH_S
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.onboard.core.agent import vehicle_mpc
from fleetmpc.onboard.core.condensed_qp import QpData
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.onboard.core.formation import Formation
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.sparse_qp import CHECK_TERMINATION, FixedPatternQp
from fleetmpc.scenario import load_scenario

__all__ = ["add_arguments", "load_average", "run"]

TARGETS = {
    "agent_step_median_ms": 0.3,
    "agent_step_p99_ms": 1.5,
    "cvxpy_over_ours_median": 80.0,
    "lockstep_realtime_factor": 100.0,
}
"""The speed targets (issue 3): at or below for times, at or above for the ratio and factor."""


@contextlib.contextmanager
def _timed(owner: object, names: tuple[str, ...], sink: list[tuple[int, int]]) -> Iterator[None]:
    """Temporarily wrap the functions `names` of `owner` (a class's methods, or a module's
    functions as the module calls them) to append (start, duration) [ns] of each call to
    sink."""
    originals = {name: getattr(owner, name) for name in names}

    def wrap(original: Callable) -> Callable:
        def wrapper(*args, **kwargs):
            t0 = time.perf_counter_ns()
            try:
                return original(*args, **kwargs)
            finally:
                sink.append((t0, time.perf_counter_ns() - t0))

        return wrapper

    for name, original in originals.items():
        setattr(owner, name, wrap(original))
    try:
        yield
    finally:
        for name, original in originals.items():
            setattr(owner, name, original)


def _stats(ns: list[int] | np.ndarray) -> dict[str, float]:
    a = np.asarray(ns, dtype=float) * 1e-6
    if a.size == 0:
        return {"median_ms": float("nan"), "p99_ms": float("nan"), "n": 0}
    return {
        "median_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "n": int(a.size),
    }


def _per_step(calls: list[tuple[int, int]], steps: list[tuple[int, int]]) -> np.ndarray:
    """Total duration [ns] of the calls that started inside each step (start, duration)."""
    out = np.zeros(len(steps))
    if not calls:
        return out
    starts = np.array([s for s, _ in calls])
    durations = np.array([d for _, d in calls])
    order = np.argsort(starts)
    starts, durations = starts[order], durations[order]
    cumulative = np.concatenate([[0], np.cumsum(durations)])
    for i, (t0, dt) in enumerate(steps):
        lo, hi = np.searchsorted(starts, [t0, t0 + dt])
        out[i] = cumulative[hi] - cumulative[lo]
    return out


def _as_arrays(d: QpData) -> QpData:
    """The same QpData with numpy arrays (the agent hands the QP plain-float sequences)."""
    return QpData(
        **{
            name: value if isinstance(value, float) else np.asarray(value, dtype=float)
            for name, value in vars(d).items()
        }
    )


def _input_bounds(mpc: TubeLbmpc, d: QpData, j: int) -> tuple[np.ndarray, np.ndarray]:
    """The bounds of u_j: U tightened by the tube at step j (all but the speed's lower bound 0),
    its yaw rate also within the trust region about the linearization's."""
    v_lo, w_lo, v_hi, w_hi = mpc.box.steps[j]
    lower, upper = np.array([v_lo, w_lo]), np.array([v_hi, w_hi])
    v, w = np.asarray(d.lin_inputs, float)[j].tolist()
    trust = mpc.settings.yaw_rate_trust(v)
    lower[1], upper[1] = (
        max(lower[1], min(w - trust, upper[1])),
        min(upper[1], max(w + trust, lower[1])),
    )
    return lower, upper


def _cvxpy_rebuild(mpc: TubeLbmpc) -> Callable[[QpData], np.ndarray | None]:
    """The same QP written out in cvxpy and built from scratch on every call: the cost on the
    learned prediction, the input box (`_input_bounds`), the speed changes from the speed now,
    and the separation half-planes on the learned prediction."""
    import cvxpy as cp

    s = mpc.settings
    M = mpc.M

    def solve(d: QpData) -> np.ndarray | None:
        Sz, sz, St, st, Hu = mpc.problem.condense(d)
        c = cp.Variable(2 * M)
        terms, cons = [], []
        for j in range(1, M + 1):
            err = St[j] @ c + st[j] - d.targets[j - 1]
            if j < M:
                Q = np.diag([d.position_weights[j - 1]] * 2 + [s.q_heading])
            else:
                Q = d.terminal_scale * mpc.terminal_weight(float(d.targets[-1, 2]))
            terms.append(cp.quad_form(err, Q))
        step, speed = s.speed_rate_max_m_s2 * mpc.tau, d.speed_now_m_s  # speed changes
        yaw_rate = d.yaw_rate_now_rad_s  # and yaw-rate changes, penalized
        for j in range(M):
            u = Hu[j] @ c + d.u_s[j]
            terms.append(cp.quad_form(u - d.u_s[j], np.diag([s.r_speed, s.r_yaw_rate])))
            terms.append(s.r_yaw_rate_change * cp.square(u[1] - yaw_rate))
            lower, upper = _input_bounds(mpc, d, j)
            cons += [u <= upper, u >= lower, cp.abs(u[0] - speed) <= step]
            speed, yaw_rate = u[0], u[1]
        for k in range(mpc.n_neighbours):  # n' ptil_j >= b, on the learned prediction
            for j in range(1, M + 1):
                nx, ny, b = d.separation_planes[k, j - 1]
                if np.isfinite(b):
                    cons.append(np.array([nx, ny]) @ (St[j, :2] @ c + st[j, :2]) >= b)
        prob = cp.Problem(cp.Minimize(sum(terms)), cons)
        prob.solve(
            solver=cp.OSQP,
            eps_abs=s.solver_eps,
            eps_rel=s.solver_eps,
            max_iter=s.solver_max_iter,
            check_termination=CHECK_TERMINATION,
            polishing=False,
        )
        return None if c.value is None else np.asarray(c.value)

    return solve


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenario", nargs="?", default="scenarios/paper.toml", help="scenario TOML file"
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="lockstep runs for the real-time factor (with --baseline: rounds)",
    )
    parser.add_argument(
        "--cvxpy-samples", type=int, default=150, help="QP instances for the cvxpy comparison"
    )
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    parser.add_argument(
        "--baseline",
        metavar="DIR",
        help="instead: this tree's agent step and lockstep speed against those of another"
        " checkout DIR, side by side, --repeats rounds of one run each (fleetmpc.bench.baseline)",
    )
    parser.add_argument(
        "--scale",
        action="store_true",
        help="instead: agent step, QP size and lockstep real-time factor against the fleet's"
        " size (fleetmpc.bench.scale)",
    )
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[10, 25, 50, 100],
        metavar="N",
        help="with --scale: the fleet sizes (default 10 25 50 100)",
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=30.0,
        metavar="S",
        help="with --scale: simulated seconds per run (default 30)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=2,
        metavar="J",
        help="with --scale: worker processes of the second run of each size; with --sweep:"
        " workers of each engine (default 2)",
    )
    parser.add_argument(
        "--sweep",
        action="store_true",
        help="instead: fleetmpc sweep's engines side by side on 48 runs, and memory over"
        " --sweep-runs short runs (fleetmpc.bench.sweep)",
    )
    parser.add_argument(
        "--sweep-runs",
        type=int,
        default=1000,
        metavar="N",
        help="with --sweep: runs of 10 s for the memory check (default 1000)",
    )
    parser.add_argument(
        "--stages",
        action="store_true",
        help="instead: the agent's step stage by stage (median, p99, share of the step) over"
        " --repeats lockstep runs (fleetmpc.bench.stages)",
    )
    parser.add_argument(
        "--gcs-logging",
        action="store_true",
        help="instead: the ground station logging cost per vehicle-period"
        " (fleetmpc.bench.telemetry)",
    )
    parser.add_argument(
        "--flush-s",
        type=float,
        nargs="+",
        default=[1.0, 2.0, 4.0],
        metavar="S",
        help="with --gcs-logging: the ground station's flush intervals to compare"
        " [s of flight, as its --flush-s] (default 1 2 4)",
    )
    parser.add_argument(
        "--series-flush-s",
        type=float,
        default=SERIES_FLUSH_S,
        metavar="S",
        help="with --gcs-logging: the ground station's --series-flush-s [s of flight]"
        f" (default {SERIES_FLUSH_S:g})",
    )


def load_average() -> list[float]:
    """The machine's load averages over 1, 5 and 15 min (empty where the OS has none)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def run(args: argparse.Namespace) -> int:
    """`fleetmpc bench`: one of the other benchmarks when a flag names it, else this module's
    profile of the step (the module docstring)."""
    modes = (args.baseline, args.gcs_logging, args.scale, args.sweep, args.stages)
    if sum(map(bool, modes)) > 1:
        raise FleetMpcError(
            "--baseline, --gcs-logging, --scale, --stages and --sweep: one at a time"
        )
    if args.stages:
        from fleetmpc.bench import stages

        return stages.run(args)
    if args.sweep:
        from fleetmpc.bench import sweep as bench_sweep

        return bench_sweep.run(args)
    if args.scale:
        from fleetmpc.bench import scale

        return scale.run(args)
    if args.baseline:
        from fleetmpc.bench import baseline as bench_baseline

        return bench_baseline.run(args)
    if args.gcs_logging:
        from fleetmpc.bench import telemetry

        return telemetry.run(args)
    return profile(args)


def profile(args: argparse.Namespace) -> int:
    """Steps 1 to 3 of the module docstring on `args.scenario`: printed, and written as JSON
    to `args.json` if given."""
    sc = load_scenario(args.scenario)
    load_before = load_average()
    runs = _fly(sc, max(args.repeats, 1))
    replays = _replay(sc, runs.captured, args.cvxpy_samples)
    result = _result(sc, runs, replays, load_before, load_average())
    _print(result, replays)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


@dataclasses.dataclass
class _Runs:
    """What the lockstep runs of steps 1 and 2 measured."""

    factors: list[float] = dataclasses.field(default_factory=list)
    """Simulated seconds per wall second of each uninstrumented run."""
    step_ms: list[np.ndarray] = dataclasses.field(default_factory=list)
    """Each uninstrumented run's agent steps [ms]."""
    steps: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(start, duration) [ns] of every timed `Agent.step`."""
    dekf: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(start, duration) [ns] of the DEKF's calls in the timed runs."""
    qp: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(start, duration) [ns] of OSQP's update and solve in the timed runs."""
    filterpy: list[tuple[int, int]] = dataclasses.field(default_factory=list)
    """(start, duration) [ns] of the DEKF's calls of filterpy's `predict` in the timed runs."""
    captured: dict[int, list[QpData]] = dataclasses.field(default_factory=dict)
    """Each vehicle's QPs of the first timed run, in flight order."""


def _fly(sc, repeats: int) -> _Runs:
    """`repeats` times: an uninstrumented run, then one with timers (the first of which
    records each vehicle's QPs), alternately, so that both see the same machine."""
    from fleetmpc.onboard.core import dekf
    from fleetmpc.onboard.core.agent import Agent

    runs = _Runs()
    original_solve = TubeLbmpc.solve

    def capturing(self: TubeLbmpc, d: QpData):
        runs.captured.setdefault(id(self), []).append(d)
        return original_solve(self, d)

    for repeat in range(repeats):
        t0 = time.perf_counter()
        rec = run_lockstep(sc)
        runs.factors.append(sc.duration_s / (time.perf_counter() - t0))
        runs.step_ms.append(rec.step_time_ms.ravel())
        with (
            _timed(Agent, ("step",), runs.steps),
            _timed(DualEkf, ("step", "propagate"), runs.dekf),
            _timed(FixedPatternQp, ("update", "solve"), runs.qp),
            _timed(dekf, ("predict",), runs.filterpy),
        ):
            if repeat == 0:
                TubeLbmpc.solve = capturing
            try:
                run_lockstep(sc)
            finally:
                TubeLbmpc.solve = original_solve
    return runs


@dataclasses.dataclass
class _Replays:
    """Step 3: the recorded QPs through our path and a sample of them through cvxpy."""

    ours_ns: list[int] = dataclasses.field(default_factory=list)
    """Our path's time of each sampled QP [ns]."""
    cvx_ns: list[int] = dataclasses.field(default_factory=list)
    """The cvxpy rebuild's time of the same QPs, in the same order [ns]."""
    diffs: list[float] = dataclasses.field(default_factory=list)
    """Largest |c| difference of each sampled QP both solved."""
    iterations: list[int] = dataclasses.field(default_factory=list)
    """OSQP's iterations of each of our replays."""


def _replay(sc, captured: dict[int, list[QpData]], samples: int) -> _Replays:
    """Each vehicle's recorded QPs through a fresh MPC of ours, in flight order (warm start
    as in flight), and every stride-th through a cvxpy rebuild (about `samples` in all)."""
    out = _Replays()
    sequences = list(captured.values())
    stride = max(1, sum(len(q) for q in sequences) // max(samples, 1))
    for seq in sequences:
        mpc = vehicle_mpc(sc.controller, Formation(sc.formation))
        times, solutions = [], []
        for d in seq:
            t0 = time.perf_counter_ns()
            sol = mpc.solve(d)
            times.append(time.perf_counter_ns() - t0)
            solutions.append(sol)
            out.iterations.append(sol.iterations)
        rebuild = _cvxpy_rebuild(vehicle_mpc(sc.controller, Formation(sc.formation)))
        for i in range(0, len(seq), stride):
            t0 = time.perf_counter_ns()
            c_ref = rebuild(_as_arrays(seq[i]))
            out.cvx_ns.append(time.perf_counter_ns() - t0)
            out.ours_ns.append(times[i])
            if solutions[i].ok and c_ref is not None:
                out.diffs.append(float(np.max(np.abs(solutions[i].c.ravel() - c_ref))))
    return out


def _result(sc, runs: _Runs, replays: _Replays, load_before: list, load_after: list) -> dict:
    """The figures as `--json` writes them, with the targets and which were met."""
    split_steps = np.array([d for _, d in runs.steps], dtype=float)
    dekf = _per_step(runs.dekf, runs.steps)
    qp = _per_step(runs.qp, runs.steps)
    filterpy = _per_step(runs.filterpy, runs.steps)
    solved = qp > 0
    step = _stats(np.concatenate(runs.step_ms) * 1e6)
    cvxpy_over_ours = float(np.median(replays.cvx_ns) / np.median(replays.ours_ns))
    iterations = replays.iterations
    result = {
        "scenario": sc.name,
        "horizon": sc.controller.horizon,
        "vehicles": len(sc.vehicles),
        "load_average_before": load_before,
        "load_average_after": load_after,
        "lockstep_realtime_factor": {
            "median": float(np.median(runs.factors)),
            "runs": [float(f) for f in runs.factors],
        },
        "agent_step": step,
        "split_run_agent_step": _stats(split_steps),
        "dekf": _stats(dekf),
        "model_build": _stats((split_steps - dekf - qp)[solved]),
        "qp_osqp": _stats(qp[solved]),
        "filterpy_calls": _stats(filterpy[solved]),
        "library_calls": _stats((filterpy + qp)[solved]),
        "qp_path_ours": _stats(replays.ours_ns),
        "qp_path_cvxpy_rebuild": _stats(replays.cvx_ns),
        "cvxpy_over_ours_median": cvxpy_over_ours,
        "max_abs_c_difference": float(max(replays.diffs)) if replays.diffs else None,
        "osqp_iterations": {
            "median": float(np.median(iterations)),
            "mean": float(np.mean(iterations)),
            "p99": float(np.percentile(iterations, 99)),
        },
        "targets": TARGETS,
    }
    result["targets_met"] = {
        "agent_step_median_ms": step["median_ms"] <= TARGETS["agent_step_median_ms"],
        "agent_step_p99_ms": step["p99_ms"] <= TARGETS["agent_step_p99_ms"],
        "cvxpy_over_ours_median": cvxpy_over_ours >= TARGETS["cvxpy_over_ours_median"],
        "lockstep_realtime_factor": result["lockstep_realtime_factor"]["median"]
        >= TARGETS["lockstep_realtime_factor"],
    }
    return result


_ROWS = (
    ("agent step", "agent_step"),
    ("  DEKF", "dekf"),
    ("  model build", "model_build"),
    ("  QP (OSQP update + solve)", "qp_osqp"),
    ("  filterpy calls (DEKF's predict)", "filterpy_calls"),
    ("  filterpy + OSQP calls", "library_calls"),
    ("QP path, ours", "qp_path_ours"),
    ("QP path, cvxpy rebuild", "qp_path_cvxpy_rebuild"),
)
"""The table's timed rows: their names and `_result`'s keys."""


def _print(result: dict, replays: _Replays) -> None:
    """The table of `result`, with what it was measured on and the targets missed."""
    step, factors = result["agent_step"], result["lockstep_realtime_factor"]
    factor = factors["median"]
    print(
        f"fleetmpc bench: scenario {result['scenario']!r}, M = {result['horizon']}, "
        f"{result['vehicles']} vehicles, {step['n']} agent steps over {len(factors['runs'])} runs "
        f"(load average {result['load_average_before']} before, "
        f"{result['load_average_after']} after)"
    )
    print(f"  {'':32s} {'median ms':>10s} {'p99 ms':>10s}")
    rows = [
        (
            "lockstep real-time factor",
            f"{factor:.0f}x",
            f"(target >= {TARGETS['lockstep_realtime_factor']:.0f}x)",
        ),
        *(
            (name, f"{result[k]['median_ms']:.3f}", f"{result[k]['p99_ms']:.3f}")
            for name, k in _ROWS
        ),
        ("cvxpy rebuild / ours (medians)", f"{result['cvxpy_over_ours_median']:.0f}x", ""),
    ]
    for name, med, p99 in rows:
        print(f"  {name:32s} {med:>10s} {p99:>10s}".rstrip())
    print(_footnote(result, replays))
    missed = [k for k, ok in result["targets_met"].items() if not ok]
    print(
        "  targets: "
        + ("all met" if not missed else "missed " + ", ".join(missed))
        + f" (step median <= {TARGETS['agent_step_median_ms']} ms, "
        f"p99 <= {TARGETS['agent_step_p99_ms']} ms, cvxpy / ours >= "
        f"{TARGETS['cvxpy_over_ours_median']:.0f}x, real time >= "
        f"{TARGETS['lockstep_realtime_factor']:.0f}x)"
    )


def _footnote(result: dict, replays: _Replays) -> str:
    """The split's own step median, how the two QP paths agreed, and OSQP's iterations."""
    diffs, iterations = replays.diffs, result["osqp_iterations"]
    agreed = (
        f", ours and cvxpy agree on c within {max(diffs):.1e} on the {len(diffs)} both solved"
        if diffs
        else ", none that both solved"
    )
    return (
        f"  (split from the timed runs: step median "
        f"{result['split_run_agent_step']['median_ms']:.3f} ms; "
        f"{len(replays.cvx_ns)} QPs side by side{agreed}; OSQP iterations per solve, median "
        f"{iterations['median']:.0f}, mean {iterations['mean']:.1f}, p99 {iterations['p99']:.0f})"
    )
