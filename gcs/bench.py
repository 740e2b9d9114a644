"""`fleetmpc bench`: how fast is one agent's control step, and the whole lockstep simulation?

1. Lockstep real-time factor: simulated seconds per wall second of `run_lockstep` on the scenario.
2. Per-agent step over the same run, split into DEKF (DualEkf.step), QP (OSQP update + solve) and
   model build (everything else: target prediction, slots, seeding, condensing, assembly).
3. Side by side on the same recorded QP data: our QP path (TubeLbmpc.solve: build values, update,
   solve) against the same QP re-built from scratch with cvxpy every step (solved by OSQP through
   cvxpy, so the difference is the rebuild), as a ratio of medians.
Figures are medians and 99th percentiles of wall time on this machine; nothing here is asserted.
"""

import argparse
import contextlib
import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from gcs.lockstep import run_lockstep
from onboard.core.dekf import DualEkf
from onboard.core.lbmpc import QpData, TubeLbmpc
from onboard.core.sparse_qp import FixedPatternQp
from protocol.scenario import load_scenario

__all__ = ["add_arguments", "run"]


@contextlib.contextmanager
def _timed(cls: type, name: str, sink: list[int]) -> Iterator[None]:
    """Temporarily wrap cls.name to append its wall time [ns] to sink."""
    original = getattr(cls, name)

    def wrapper(self, *args, **kwargs):
        t0 = time.perf_counter_ns()
        try:
            return original(self, *args, **kwargs)
        finally:
            sink.append(time.perf_counter_ns() - t0)

    setattr(cls, name, wrapper)
    try:
        yield
    finally:
        setattr(cls, name, original)


def _stats(ns: list[int] | np.ndarray) -> dict[str, float]:
    a = np.asarray(ns, dtype=float) * 1e-6
    return {
        "median_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "n": int(a.size),
    }


def _cvxpy_rebuild(mpc: TubeLbmpc) -> Callable[[QpData], np.ndarray]:
    import cvxpy as cp

    s = mpc.settings
    M = mpc.M

    def solve(d: QpData) -> np.ndarray:
        Sz, sz, St, st, Hu = mpc.condense(d)
        c = cp.Variable(2 * M)
        terms, cons = [], []
        for j in range(1, M + 1):
            err = St[j] @ c + st[j] - d.targets[j - 1]
            if j < M:
                Q = np.diag([d.position_weights[j - 1]] * 2 + [s.q_heading])
            else:
                Q = d.terminal_scale * mpc.terminal_weight(float(d.targets[-1, 2]))
            terms.append(cp.quad_form(err, Q))
        for j in range(M):
            u = Hu[j] @ c + d.u_s[j]
            terms.append(cp.quad_form(u - d.u_s[j], np.diag([s.r_speed, s.r_yaw_rate])))
            bound = mpc.u_max - mpc.tightening[j]
            cons += [u <= bound, u >= -bound]
        for k in range(mpc.n_neighbours):
            for j in range(1, M + 1):
                margin = d.neighbour_margins[k, j - 1]
                if np.isfinite(margin):
                    p_k = d.neighbour_positions[k, j - 1]
                    away = d.lin_states[j, :2] - p_k
                    n = away / max(float(np.linalg.norm(away)), 1e-9)
                    cons.append(n @ (Sz[j, :2] @ c + sz[j, :2] - p_k) >= margin)
        prob = cp.Problem(cp.Minimize(sum(terms)), cons)
        prob.solve(
            solver=cp.OSQP, eps_abs=s.solver_eps, eps_rel=s.solver_eps, max_iter=s.solver_max_iter
        )
        return np.asarray(c.value)

    return solve


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "scenario", nargs="?", default="scenarios/paper.toml", help="scenario TOML file"
    )
    parser.add_argument(
        "--repeats", type=int, default=3, help="lockstep runs for the real-time factor"
    )
    parser.add_argument(
        "--cvxpy-samples", type=int, default=150, help="QP instances for the cvxpy comparison"
    )
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")


def run(args: argparse.Namespace) -> int:
    sc = load_scenario(args.scenario)
    # 1. Real-time factor, uninstrumented.
    factors = []
    for _ in range(max(args.repeats, 1)):
        t0 = time.perf_counter()
        run_lockstep(sc)
        factors.append(sc.duration_s / (time.perf_counter() - t0))
    # 2. Instrumented run: per-agent step split.
    dekf_ns: list[int] = []
    qp_ns: list[int] = []
    mpc_ns: list[int] = []
    captured: list[QpData] = []
    original_solve = TubeLbmpc.solve

    def capturing(self, d):
        captured.append(d)
        return original_solve(self, d)

    with (
        _timed(DualEkf, "step", dekf_ns),
        _timed(FixedPatternQp, "solve", qp_ns),
        _timed(FixedPatternQp, "update", qp_ns),
    ):
        TubeLbmpc.solve = capturing
        try:
            rec = run_lockstep(sc)
        finally:
            TubeLbmpc.solve = original_solve
    step_ms = rec.step_time_ms.ravel()
    qp = np.add(qp_ns[0::2], qp_ns[1::2]) if len(qp_ns) % 2 == 0 else np.asarray(qp_ns)
    dekf = np.asarray(dekf_ns[: step_ms.size])
    # 3. Our QP path against a cvxpy rebuild, side by side on the same data.
    mpc = TubeLbmpc(sc.controller, n_neighbours=len(sc.vehicles) - 1)
    rebuild = _cvxpy_rebuild(mpc)
    ours_ns, cvx_ns, diffs = [], [], []
    stride = max(1, len(captured) // max(args.cvxpy_samples, 1))
    for d in captured[::stride]:
        t0 = time.perf_counter_ns()
        sol = mpc.solve(d)
        t1 = time.perf_counter_ns()
        c_ref = rebuild(d)
        t2 = time.perf_counter_ns()
        ours_ns.append(t1 - t0)
        cvx_ns.append(t2 - t1)
        if sol.ok and c_ref is not None:
            diffs.append(float(np.max(np.abs(sol.c.ravel() - c_ref))))
        mpc_ns.append(t1 - t0)
    steps = step_ms * 1e6
    build = steps[: dekf.size] - dekf[: steps.size] - qp[: min(steps.size, qp.size)]
    result = {
        "scenario": sc.name,
        "horizon": sc.controller.horizon,
        "lockstep_realtime_factor": {"median": float(np.median(factors)), "runs": len(factors)},
        "agent_step": _stats(steps),
        "dekf": _stats(dekf),
        "model_build": _stats(build),
        "qp_osqp": _stats(qp),
        "qp_path_ours": _stats(ours_ns),
        "qp_path_cvxpy_rebuild": _stats(cvx_ns),
        "cvxpy_over_ours_median": float(np.median(cvx_ns) / np.median(ours_ns)),
        "max_abs_c_difference": float(max(diffs)) if diffs else None,
    }
    rows = [
        ("lockstep real-time factor", f"{result['lockstep_realtime_factor']['median']:.0f}x", ""),
        (
            "agent step",
            f"{result['agent_step']['median_ms']:.3f}",
            f"{result['agent_step']['p99_ms']:.3f}",
        ),
        ("  DEKF", f"{result['dekf']['median_ms']:.3f}", f"{result['dekf']['p99_ms']:.3f}"),
        (
            "  model build",
            f"{result['model_build']['median_ms']:.3f}",
            f"{result['model_build']['p99_ms']:.3f}",
        ),
        (
            "  QP (OSQP update + solve)",
            f"{result['qp_osqp']['median_ms']:.3f}",
            f"{result['qp_osqp']['p99_ms']:.3f}",
        ),
        (
            "QP path, ours",
            f"{result['qp_path_ours']['median_ms']:.3f}",
            f"{result['qp_path_ours']['p99_ms']:.3f}",
        ),
        (
            "QP path, cvxpy rebuild",
            f"{result['qp_path_cvxpy_rebuild']['median_ms']:.3f}",
            f"{result['qp_path_cvxpy_rebuild']['p99_ms']:.3f}",
        ),
        ("cvxpy rebuild / ours (medians)", f"{result['cvxpy_over_ours_median']:.0f}x", ""),
    ]
    print(
        f"fleetmpc bench: scenario {sc.name!r}, M = {sc.controller.horizon}, "
        f"{len(captured)} agent steps"
    )
    print(f"  {'':32s} {'median ms':>10s} {'p99 ms':>10s}")
    for name, med, p99 in rows:
        print(f"  {name:32s} {med:>10s} {p99:>10s}")
    if diffs:
        print(f"  (ours and cvxpy agree on c within {max(diffs):.1e})")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
