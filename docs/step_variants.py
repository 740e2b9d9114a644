"""What would make the agent step faster, and what each change would cost the design.

    .venv/bin/python docs/step_variants.py VARIANT [--runs N]

Not part of the product: a measurement behind issue 3's step-median target (0.3 ms), which the
issue's own architecture (a DEKF on filterpy, OSQP solving every period) does not reach on this
machine. Each variant is applied to a second set of agents, built like the first; in one lockstep
run of scenarios/paper.toml both agents of each vehicle step on the same input, alternating which
goes first, and the first set's output drives the plant. The ratio of the two sets' median step
times is what the variant changes, far less sensitive to the load of the moment than two
separate runs. Variants:

- lean-kalman: the DEKF's two filters and the target filter do filterpy's update and predict
  equations in plain numpy (no deep copy of z, no posterior copies), in place of
  `KalmanFilter.update` / `predict`. Breaks "DEKF on filterpy".
- skip-osqp: when the unconstrained optimum, P c = -q by Cholesky, meets every constraint it is
  the QP's solution; OSQP is then not called. Breaks "OSQP updated and solved every period".
- both: the two above.
- eps-1e-5: OSQP's eps_abs and eps_rel 1e-5 instead of 1e-6.
"""

import argparse
import dataclasses
import time
import types

import numpy as np
from scipy.linalg import lapack

import gcs.lockstep as lockstep
from gcs.metrics import compute_metrics
from onboard.core.agent import Agent
from onboard.core.lbmpc import QpSolution, TubeLbmpc
from protocol.scenario import load_scenario

VARIANTS = ("lean-kalman", "skip-osqp", "both", "eps-1e-5")


def _lean_update(self, z, R=None, H=None):
    """filterpy's KalmanFilter.update (Joseph form) without its bookkeeping copies."""
    R = self.R if R is None else R
    H = self.H if H is None else H
    self.y = z - H.dot(self.x)
    PHT = self.P.dot(H.T)
    self.S = H.dot(PHT) + R
    self.SI = self.inv(self.S)
    self.K = PHT.dot(self.SI)
    self.x = self.x + self.K.dot(self.y)
    I_KH = self._I - self.K.dot(H)
    self.P = I_KH.dot(self.P).dot(I_KH.T) + self.K.dot(R).dot(self.K.T)


def _lean_predict(self, u=None, B=None, F=None, Q=None):
    """filterpy's KalmanFilter.predict (no input) without its bookkeeping copies."""
    self.x = self.F.dot(self.x)
    self.P = self.F.dot(self.P).dot(self.F.T) + self.Q


def _unconstrained_optimum(mpc: TubeLbmpc) -> np.ndarray | None:
    """-P^-1 q if it satisfies every constraint of the QP just assembled, else None."""
    n = 2 * mpc.M
    if not hasattr(mpc, "_variant_a_rows"):
        steps = 8 * (mpc.M + 1)
        inputs = [8 * j + 6 + i for j in range(mpc.M) for i in (0, 1)]
        mpc._variant_a_rows = np.array(inputs + list(range(steps, mpc._Y.shape[0])))
        mpc._variant_ext = np.zeros(n + 2)
    _, c, info = lapack.dposv(mpc._H[:n, :n], mpc._H[:n, n])
    if info != 0 or not mpc._qp.finite():
        return None
    ext = mpc._variant_ext
    np.negative(c, out=ext[:n])
    Ac = mpc._Y.dot(ext).take(mpc._variant_a_rows)
    if (Ac - mpc._qp.l).min() >= 0.0 and (mpc._qp.u - Ac).min() >= 0.0:
        return ext[:n].copy()
    return None


def _skip_osqp_solve(self: TubeLbmpc, d) -> QpSolution:
    self.assemble(d)
    x = _unconstrained_optimum(self)
    if x is None:
        # (TubeLbmpc.solve assembles again: those periods pay the assembly twice, so the ratio
        # understates what skipping saves.)
        return TubeLbmpc.solve(self, d)
    M, n = self.M, 2 * self.M
    self._x_ext[:n] = x
    y = self._Y_steps.dot(self._x_ext).take(self._by_kind)
    self._last_c = x
    return QpSolution(
        ok=True,
        status="solved",
        c=x.reshape(M, 2),
        inputs=y[:n].reshape(M, 2),
        learned=y[n : n + 3 * M + 3].reshape(M + 1, 3),
        nominal=y[n + 3 * M + 3 :].reshape(M + 1, 3),
        iterations=0,
    )


def _apply(agent: Agent, variant: str) -> None:
    if variant in ("lean-kalman", "both"):
        for f in (agent.dekf.state_filter, agent.dekf.param_filter, agent.target._kf):
            f.update = types.MethodType(_lean_update, f)
            f.predict = types.MethodType(_lean_predict, f)
    if variant in ("skip-osqp", "both"):
        agent.mpc.solve = types.MethodType(_skip_osqp_solve, agent.mpc)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variant", choices=VARIANTS)
    parser.add_argument("--runs", type=int, default=3, help="lockstep runs of paper.toml")
    args = parser.parse_args()
    scenario = load_scenario("scenarios/paper.toml")
    variant_controller = (
        dataclasses.replace(scenario.controller, solver_eps=1e-5)
        if args.variant == "eps-1e-5"
        else scenario.controller
    )
    times: dict[str, list[int]] = {"baseline": [], "variant": []}
    command_gap = [0.0]  # the largest |variant - baseline| of a command entry

    class Pair:
        """A vehicle's baseline agent and its variant, stepping on the same inputs."""

        def __init__(self, vehicle_id, **kwargs):
            self.variant = Agent(vehicle_id, **(kwargs | {"controller": variant_controller}))
            _apply(self.variant, args.variant)
            self.baseline = Agent(vehicle_id, **kwargs)
            self.steps = 0

        def __getattr__(self, name):
            return getattr(self.baseline, name)

        def step(self, inp):
            self.steps += 1
            order = [("baseline", self.baseline), ("variant", self.variant)]
            outs = {}
            for name, agent in order if self.steps % 2 else order[::-1]:
                t0 = time.perf_counter_ns()
                outs[name] = agent.step(inp)
                times[name].append(time.perf_counter_ns() - t0)
            gap = np.abs(outs["variant"].command - outs["baseline"].command).max()
            command_gap[0] = max(command_gap[0], float(gap))
            return outs["baseline"]

    lockstep.Agent = Pair
    try:
        for _ in range(args.runs):
            rec = lockstep.run_lockstep(scenario)
    finally:
        lockstep.Agent = Agent
    base, var = (np.array(times[k]) * 1e-3 for k in ("baseline", "variant"))
    print(
        f"{args.variant}: baseline step median {np.median(base):.1f} us, variant "
        f"{np.median(var):.1f} us; ratio of medians {np.median(var) / np.median(base):.3f}, "
        f"median per-step ratio {np.median(var / base):.3f} ({len(base)} steps)"
    )
    m = compute_metrics(rec)
    print(
        f"largest command difference {command_gap[0]:.1e} (the baseline's commands fly the "
        f"plant; its separation errors {np.round(m['separation_error_m'], 4).tolist()} m)"
    )


if __name__ == "__main__":
    main()
