"""The tube LBMPC quadratic program (paper Eqs. 11-13 as corrected in docs/design.md, "Controller").

Decision variables: c_j in R^2, j = 0..M-1 (stacked, 2M). Inputs are parametrized as
    u_j = K_j (zbar_j - zref_j) + u_s,j + c_j,
where zref is the nominal model's rollout of the steady-state inputs u_s (so c = 0 reproduces u_s
and c -> 0 at steady state), and K_j = K0 T(theta_j)' is the DARE gain rotated to the heading of
the linearization point. Both predictions are affine in c (condensed form):
    nominal  zbar_{j+1} = A_j zbar_j + B_j u_j + e_j            (the feedback's reference)
    learned  ztil_{j+1} = A~_j ztil_j + B~_j u_j + e~_j          (cost, minimum separation)
The model is linearized along a trajectory chosen by the caller (never at V = 0).
Cost: sum_{j=1}^{M-1} ||ztil_j - r_j||^2_{Q_j} + ||ztil_M - r_M||^2_{P} + sum_j ||u_j - u_s,j||^2_R
      + rho sum_j (w_j - w_{j-1})^2 (rho = r_yaw_rate_change; w_{-1} the yaw rate flown now).
Constraints: u_j in U ⊖ K R_j (box), speed changes |V_j - V_{j-1}| <= a_max tau from the speed now
(the vehicle cannot stop at once: a plan that could would be overtaken by the actuators), and, for
the linearization to stay valid, a yaw rate within a trust region about the linearization's (the
heading enters the model through sin and cos, so a plan that turned the other way would be predicted
wrongly), and n_kj' ptil_j >= b_kj for every neighbour k and step j whose half-plane the caller set
(`fleetmpc.onboard.core.separation` places them; docs/design.md, "Safety").

The QP's structure and its values each period are `fleetmpc.onboard.core.condensed_qp`'s: OSQP
is set up once with a fixed sparsity pattern (structural zeros kept) and updated every period
with warm start; every solve is checked here (status, finiteness, bounds), and a failed one
leaves the caller the tube's feedback law (`TubeLbmpc.fallback_input`).
"""

import math
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.condensed_qp import CondensedQp, QpData
from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.tube import vehicle_tube
from fleetmpc.onboard.core.unicycle import wrap

__all__ = ["QpSolution", "TubeLbmpc"]

_UNCONVERGED = ("solved inaccurate", "maximum iterations reached")
"""OSQP statuses whose iterate is used if it keeps every constraint (`FEASIBILITY_TOL`): the cost
may be a little short of its optimum, the plan is still one the vehicle may fly."""

FEASIBILITY_TOL = 1e-3
"""How far an unconverged iterate may break a constraint row and still be used [m, m/s, rad/s]:
a millimetre on a separation row, well inside every margin."""

FIRST_INPUT_TOL = 1e-3
"""How far outside U, relative to its upper bounds (and 1e-6 more), a solution's first input may
be and pass its check: a solver's tolerance."""


@dataclass(frozen=True, eq=False)
class QpSolution:
    """A solved (or failed) period."""

    ok: bool
    """True when the solve succeeded and passed every check."""
    status: str
    """OSQP's status, or the check that failed."""
    c: np.ndarray
    """Decision variables (M, 2)."""
    inputs: np.ndarray
    """Planned inputs u_j (M, 2)."""
    nominal: np.ndarray
    """Nominal prediction zbar (M + 1, 3)."""
    learned: np.ndarray
    """Learned prediction ztil (M + 1, 3)."""
    iterations: int


class TubeLbmpc:
    """Tube LBMPC for one vehicle with separation constraints against `n_neighbours` neighbours
    and formation terms toward at most `formation_terms` (default: as many); the QP is built
    once. The tube's gain is computed with every formation term in the stage weight."""

    def __init__(
        self, settings: ControllerSettings, *, n_neighbours: int, formation_terms: int | None = None
    ) -> None:
        s = settings
        self.settings = s
        self.M = M = s.horizon
        self.tau = s.period_s
        self.n_neighbours = n_neighbours
        terms = n_neighbours if formation_terms is None else formation_terms
        self.tube = vehicle_tube(s, formation_terms=terms)
        """The DARE gain, the tube's margins and the tightened input set."""
        self.box = self.tube.box
        self.K0, self.P0 = self.tube.K0, self.tube.P0
        self.problem = CondensedQp(
            s, n_neighbours=n_neighbours, K0=self.K0, P0=self.P0, box=self.box
        )
        """The QP, condensed: its structure, and its values each period."""
        self._warm = np.zeros(2 * M)
        self._last_c: np.ndarray | None = None

    @property
    def tightening(self) -> np.ndarray:
        """How much each input bound shrinks at step j (M, 2)."""
        return self.tube.tightening

    @property
    def tube_radius_m(self) -> np.ndarray:
        """The position tube's radius at j = 0..M (M + 1,) [m]."""
        return self.tube.radius_m

    # -- small maps -----------------------------------------------------------------------------
    def feedback_gain(self, yaw: float) -> np.ndarray:
        """K at heading `yaw` (2, 3): K0 T(yaw)'."""
        c, s_ = np.cos(yaw), np.sin(yaw)
        K = self.K0.copy()
        K[:, 0] = self.K0[:, 0] * c - self.K0[:, 1] * s_
        K[:, 1] = self.K0[:, 0] * s_ + self.K0[:, 1] * c
        return K

    def terminal_weight(self, yaw: float) -> np.ndarray:
        """P at heading `yaw` (3, 3): T P0 T'."""
        return np.array(self.problem.terminal_entries(yaw, 1.0)).reshape(3, 3)

    def fallback_input(self, z: np.ndarray, reference: np.ndarray, u_s: np.ndarray) -> np.ndarray:
        """The tube feedback law u = u_s + K (z - z_ref), clipped to U (used when a solve fails)."""
        err = np.asarray(z, float) - np.asarray(reference, float)
        err[2] = wrap(float(err[2]))
        u = np.asarray(u_s, float) + self.feedback_gain(float(reference[2])) @ err
        u = np.where(np.isfinite(u), u, 0.0)
        return self.box.clip(u)

    def _failed(self, status: str, d: QpData) -> QpSolution:
        return QpSolution(
            ok=False,
            status=status,
            c=np.zeros((self.M, 2)),
            inputs=np.array(d.u_s, dtype=float),
            nominal=self.problem.x0[:, :3].copy(),
            learned=self.problem.x0[:, 3:].copy(),
            iterations=0,
        )

    # -- one period -----------------------------------------------------------------------------
    def solve(self, d: QpData) -> QpSolution:
        """Build this period's QP values, solve it, and check the answer."""
        M, n = self.M, 2 * self.M
        problem = self.problem
        qp = problem.osqp
        problem.assemble(d)
        if not qp.finite():
            # Never hand the solver non-finite data: it would poison its factorization.
            self._last_c = None
            return self._failed("non-finite problem data", d)
        qp.update()
        if self._last_c is not None:
            self._warm[:-2] = self._last_c[2:]
            qp.warm_start(self._warm)
        ok, status, x, iterations = qp.solve()
        if not ok and status in _UNCONVERGED and self._feasible(x):
            ok, status = True, f"{status}, constraints checked"
        if ok and not math.isfinite(x.dot(x)):
            ok, status = False, "non-finite solution"
        if not ok:
            self._last_c = None
            x = np.zeros(n)
        inputs, learned, nominal = problem.predictions(x)  # at c = x
        u0, w0 = inputs[:2].tolist()
        if ok and not self.box.admits(u0, w0, relative_tolerance=FIRST_INPUT_TOL):
            ok, status = False, "first input outside U"
        if ok:
            self._last_c = x
        return QpSolution(
            ok=ok,
            status=status,
            c=x.reshape(M, 2),
            inputs=inputs.reshape(M, 2),
            nominal=nominal.reshape(M + 1, 3),
            learned=learned.reshape(M + 1, 3),
            iterations=iterations,
        )

    def _feasible(self, x: np.ndarray) -> bool:
        """True when x keeps every constraint of this period's QP to within FEASIBILITY_TOL."""
        if not math.isfinite(x.dot(x)):
            return False
        Ax = self.problem.constraint_rows(x)
        qp, tol = self.problem.osqp, FEASIBILITY_TOL
        return bool(np.all(Ax >= qp.l - tol) and np.all(Ax <= qp.u + tol))
