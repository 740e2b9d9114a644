"""The tube LBMPC quadratic program (paper Eqs. 11-13 as corrected in DESIGN.md).

Decision variables: c_j in R^2, j = 0..M-1 (stacked, 2M). Inputs are parametrized as
    u_j = K_j (zbar_j - zref_j) + u_s,j + c_j,
where zref is the nominal model's rollout of the steady-state inputs u_s (so c = 0 reproduces u_s
and c -> 0 at steady state), and K_j = K0 T(theta_j)' is the DARE gain rotated to the heading of
the linearization point. Both predictions are affine in c (condensed form):
    nominal  zbar_{j+1} = A_j zbar_j + B_j u_j + e_j            (constraints: tube-tightened U,
                                                                  minimum separation)
    learned  ztil_{j+1} = A~_j ztil_j + B~_j u_j + e~_j          (cost)
The model is linearized along a trajectory chosen by the caller (never at V = 0).
Cost: sum_{j=1}^{M-1} ||ztil_j - r_j||^2_{Q_j} + ||ztil_M - r_M||^2_{P} + sum_j ||u_j - u_s,j||^2_R.
Constraints: u_j in U ⊖ K R_j (box), n_kj' (pbar_j - p_kj) >= margin_kj for every neighbour k whose
predicted position is within reach (a half-plane inner approximation of the disc constraint).

OSQP is set up once with a fixed sparsity pattern (structural zeros kept) and updated every period
with warm start; every solve is checked (status, finiteness, bounds).
"""

from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from onboard.core.config import ControllerSettings
from onboard.core.errors import InfeasibleError
from onboard.core.tube import (
    cruise_linearization,
    dare_gain,
    position_tube_radius,
    robust_input_tightening,
)
from onboard.core.unicycle import NOMINAL_BETA, linearize

__all__ = ["QpData", "QpSolution", "TubeLbmpc"]


@dataclass(frozen=True, eq=False)
class QpData:
    """Everything one period's QP depends on. Shapes use M = horizon, N = number of neighbours."""

    z0: np.ndarray
    """Current state estimate (3,)."""
    lin_states: np.ndarray
    """Linearization trajectory (M + 1, 3); lin_states[0] should be z0."""
    lin_inputs: np.ndarray
    """Linearization inputs (M, 2); speeds must not be 0."""
    beta: np.ndarray
    """Learned oracle parameters (4,)."""
    u_s: np.ndarray
    """Steady-state inputs under the learned model (M, 2)."""
    targets: np.ndarray
    """Cost targets r_j for j = 1..M (M, 3): position and heading (unwrapped near lin_states)."""
    position_weights: np.ndarray
    """Position weight of each stage j = 1..M (M,) [1/m^2]."""
    terminal_scale: float
    """Scale of the terminal weight P (formation weight present / formation weight assumed)."""
    neighbour_positions: np.ndarray
    """Neighbours' predicted positions at j = 1..M (N, M, 2)."""
    neighbour_margins: np.ndarray
    """Required distance from each neighbour at j = 1..M (N, M) [m]; inf or nan disables a row."""


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


def _pattern_indices(mask: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray, np.ndarray]:
    """CSC matrix holding every entry of `mask` (zeros kept), and the (row, col) of each entry."""
    m = sp.csc_matrix(mask.astype(float))
    m.sort_indices()
    cols = np.repeat(np.arange(mask.shape[1]), np.diff(m.indptr))
    rows = m.indices.copy()
    m.data[:] = 0.0
    return m, rows, cols


class TubeLbmpc:
    """Tube LBMPC for one vehicle with `n_neighbours` neighbours; the QP is built once."""

    def __init__(self, settings: ControllerSettings, *, n_neighbours: int) -> None:
        s = settings
        self.settings = s
        self.M = M = s.horizon
        self.tau = s.period_s
        self.n_neighbours = n_neighbours
        self.u_max = np.array([s.speed_max_m_s, s.yaw_rate_max_rad_s])
        self.A0, self.B0 = cruise_linearization(s.reference_speed_m_s, s.period_s)
        q_pos = s.q_position + n_neighbours * s.q_formation
        self.Q0 = np.diag([q_pos, q_pos, s.q_heading])
        self.R = np.diag([s.r_speed, s.r_yaw_rate])
        self.K0, self.P0 = dare_gain(self.A0, self.B0, self.Q0, self.R)
        w_bar = np.array([s.w_position_m, s.w_position_m, s.w_heading_rad])
        self.tightening = robust_input_tightening(self.A0, self.B0, self.K0, w_bar, M)
        worst = self.tightening / self.u_max
        if np.any(worst >= 1.0):
            j, i = np.unravel_index(int(np.argmax(worst)), worst.shape)
            name = ("speed", "yaw rate")[i]
            raise InfeasibleError(
                "controller.w_position_m",
                f"the tightened input set U ⊖ K R_j is empty: the {name} bound "
                f"{self.u_max[i]:g} shrinks by {self.tightening[j, i]:.3g} at step {j}; "
                "reduce the disturbance box W or the horizon, or raise the input bounds",
            )
        self.tube_radius_m = position_tube_radius(self.A0, self.B0, self.K0, w_bar, M)
        self._bound = self.u_max[None, :] - self.tightening
        self._r = np.array([s.r_speed, s.r_yaw_rate])
        self._E = np.zeros((M, 2, 2 * M))
        for j in range(M):
            self._E[j, :, 2 * j : 2 * j + 2] = np.eye(2)
        self._setup_solver()
        self._last_c: np.ndarray | None = None

    # -- QP structure ---------------------------------------------------------------------------
    def _setup_solver(self) -> None:
        M, N, n = self.M, self.n_neighbours, 2 * self.M
        p_mask = np.triu(np.ones((n, n), dtype=bool))
        in_mask = np.zeros((2 * M, n), dtype=bool)
        for j in range(M):
            in_mask[2 * j : 2 * j + 2, : 2 * j + 2] = True
        sep_mask = np.zeros((N * M, n), dtype=bool)
        for k in range(N):
            for j in range(1, M + 1):
                sep_mask[k * M + j - 1, : 2 * j] = True
        a_mask = np.vstack([in_mask, sep_mask])
        P, self._p_rows, self._p_cols = _pattern_indices(p_mask)
        A, self._a_rows, self._a_cols = _pattern_indices(a_mask)
        P.data[:] = np.eye(n)[self._p_rows, self._p_cols]
        A.data[:] = 0.0
        m = a_mask.shape[0]
        self._A_dense = np.zeros((m, n))
        self._l = np.full(m, -np.inf)
        self._u = np.full(m, np.inf)
        s = self.settings
        self._solver = osqp.OSQP()
        self._solver.setup(
            P=P,
            q=np.zeros(n),
            A=A,
            l=-np.ones(m),
            u=np.ones(m),
            verbose=False,
            eps_abs=s.solver_eps,
            eps_rel=s.solver_eps,
            max_iter=s.solver_max_iter,
            warm_starting=True,
            polishing=False,
        )

    def feedback_gain(self, yaw: float) -> np.ndarray:
        """K at heading `yaw` (2, 3): K0 T(yaw)'."""
        c, s_ = np.cos(yaw), np.sin(yaw)
        K = self.K0.copy()
        K[:, 0] = self.K0[:, 0] * c - self.K0[:, 1] * s_
        K[:, 1] = self.K0[:, 0] * s_ + self.K0[:, 1] * c
        return K

    def terminal_weight(self, yaw: float) -> np.ndarray:
        """P at heading `yaw` (3, 3): T P0 T'."""
        c, s_ = np.cos(yaw), np.sin(yaw)
        T = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        return T @ self.P0 @ T.T

    def fallback_input(self, z: np.ndarray, reference: np.ndarray, u_s: np.ndarray) -> np.ndarray:
        """The tube feedback law u = u_s + K (z - z_ref), clipped to U (used when a solve fails)."""
        err = np.asarray(z, float) - np.asarray(reference, float)
        err[2] = (err[2] + np.pi) % (2 * np.pi) - np.pi
        u = np.asarray(u_s, float) + self.feedback_gain(float(reference[2])) @ err
        u = np.where(np.isfinite(u), u, 0.0)
        return np.clip(u, -self.u_max, self.u_max)

    def _failed(
        self, M: int, status: str, sz: np.ndarray, st: np.ndarray, d: QpData
    ) -> "QpSolution":
        return QpSolution(
            ok=False,
            status=status,
            c=np.zeros((M, 2)),
            inputs=np.array(d.u_s, dtype=float),
            nominal=sz,
            learned=st,
            iterations=0,
        )

    # -- one period -----------------------------------------------------------------------------
    def condense(self, d: QpData) -> tuple[np.ndarray, ...]:
        """Affine maps of c: (Sz, sz) nominal states, (St, st) learned states, Hu inputs.

        Runs one recursion on the stacked state X_j = [zbar_j; ztil_j] (6 x (2M + 1)), whose last
        column is the constant part: X_{j+1} = (Ablk + Bblk [K_j 0]) X_j + Bblk (E_j c + u_s,j) + e.
        """
        M, n, tau = self.M, 2 * self.M, self.tau
        A, B, e = linearize(d.lin_states[:M], d.lin_inputs, NOMINAL_BETA, tau)
        At, Bt, et = linearize(d.lin_states[:M], d.lin_inputs, d.beta, tau)
        th = d.lin_states[:M, 2]
        c, s_ = np.cos(th), np.sin(th)
        K = np.empty((M, 2, 3))
        K[:, :, 0] = self.K0[None, :, 0] * c[:, None] - self.K0[None, :, 1] * s_[:, None]
        K[:, :, 1] = self.K0[None, :, 0] * s_[:, None] + self.K0[None, :, 1] * c[:, None]
        K[:, :, 2] = self.K0[None, :, 2]
        Bb = np.concatenate([B, Bt], axis=1)  # (M, 6, 2)
        Ab = np.zeros((M, 6, 6))
        Ab[:, :3, :3] = A
        Ab[:, 3:, 3:] = At
        Phi = Ab.copy()
        Phi[:, :, :3] += Bb @ K
        X = np.zeros((M + 1, 6, n + 1))
        X[0, :3, n] = X[0, 3:, n] = d.z0  # constant column: the rollout of u_s (zref, c = 0)
        const = (Bb @ d.u_s[:, :, None])[:, :, 0]
        const[:, :3] += e
        const[:, 3:] += et
        for j in range(M):
            w = 2 * j
            Xn = X[j + 1]
            Xn[:, : w + 2] = Phi[j] @ X[j, :, : w + 2]
            Xn[:, w : w + 2] += Bb[j]
            Xn[:, n] = Ab[j] @ X[j, :, n] + const[j]
        Hu = K @ X[:M, :3, :n] + self._E  # (M, 2, n); the constant part of u_j is u_s,j
        return X[:, :3, :n], X[:, :3, n], X[:, 3:, :n], X[:, 3:, n], Hu

    def solve(self, d: QpData) -> QpSolution:
        """Build this period's QP values, solve it, and check the answer."""
        M, n = self.M, 2 * self.M
        Sz, sz, St, st, Hu = self.condense(d)
        # Cost.
        res = st[1:] - d.targets
        res[:, 2] = (res[:, 2] + np.pi) % (2 * np.pi) - np.pi
        Wd = np.empty((M - 1, 3))
        Wd[:, 0] = Wd[:, 1] = d.position_weights[: M - 1]
        Wd[:, 2] = self.settings.q_heading
        G = St[1:M]
        Pt = d.terminal_scale * self.terminal_weight(float(d.targets[-1, 2]))
        GM = St[M]
        GW = G * Wd[:, :, None]
        H = (
            np.einsum("jin,jim->nm", GW, G)
            + GM.T @ Pt @ GM
            + np.einsum("jin,jim->nm", Hu * self._r[None, :, None], Hu)
        )
        H = H + H.T  # = 2 * (symmetric H)
        q = 2.0 * (np.einsum("jin,ji->n", GW, res[: M - 1]) + GM.T @ (Pt @ res[-1]))
        # Input constraints: u_j = Hu_j c + u_s,j within the tightened box.
        A = self._A_dense
        A[: 2 * M] = Hu.reshape(2 * M, n)
        self._l[: 2 * M] = (-self._bound - d.u_s).ravel()
        self._u[: 2 * M] = (self._bound - d.u_s).ravel()
        # Separation constraints, one row per neighbour k and step j = 1..M.
        N = self.n_neighbours
        if N:
            p_k = d.neighbour_positions  # (N, M, 2)
            away = d.lin_states[None, 1:, :2] - p_k
            dist = np.hypot(away[..., 0], away[..., 1])
            fallback_dir = d.z0[None, None, :2] - p_k
            close = dist < 1e-6
            away = np.where(close[..., None], fallback_dir, away)
            dist = np.where(close, np.hypot(away[..., 0], away[..., 1]), dist)
            nrm = away / np.maximum(dist, 1e-9)[..., None]
            active = np.isfinite(d.neighbour_margins)
            rows = np.einsum("kji,jin->kjn", nrm, Sz[1:, :2]) * active[..., None]
            A[2 * M :] = rows.reshape(N * M, n)
            lower = d.neighbour_margins - np.einsum("kji,kji->kj", nrm, sz[None, 1:, :2] - p_k)
            self._l[2 * M :] = np.where(active, lower, -np.inf).ravel()
        Px, Ax = H[self._p_rows, self._p_cols], A[self._a_rows, self._a_cols]
        if not (
            np.isfinite(Px).all()
            and np.isfinite(Ax).all()
            and np.isfinite(q).all()
            and not np.isnan(self._l).any()
            and not np.isnan(self._u).any()
        ):
            # Never hand the solver non-finite data: it would poison its factorization.
            self._last_c = None
            return self._failed(M, "non-finite problem data", sz, st, d)
        solver = self._solver
        solver.update(Px=Px, Ax=Ax, q=q, l=self._l, u=self._u)
        if self._last_c is not None:
            solver.warm_start(x=np.concatenate([self._last_c[2:], np.zeros(2)]))
        result = solver.solve(raise_error=False)
        status = str(result.info.status)
        x = result.x
        ok = result.info.status_val == osqp.SolverStatus.OSQP_SOLVED
        if ok and (x is None or not np.all(np.isfinite(x))):
            ok, status = False, "non-finite solution"
        if not ok:
            self._last_c = None
            x = np.zeros(n)
        inputs = (Hu @ x) + d.u_s
        if ok and np.any(np.abs(inputs[0]) > self.u_max * (1 + 1e-3) + 1e-6):
            ok, status = False, "first input outside U"
        if ok:
            self._last_c = x
        return QpSolution(
            ok=ok,
            status=status,
            c=x.reshape(M, 2),
            inputs=inputs,
            nominal=(Sz @ x) + sz,
            learned=(St @ x) + st,
            iterations=int(result.info.iter),
        )
