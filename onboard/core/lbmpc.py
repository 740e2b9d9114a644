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

Speed: a period runs in a fraction of a millisecond, so the per-period code counts numpy calls.
Everything that does not depend on the period's data is built in the constructor (the identity
parts of the stacked model, the heading weights, the input-bound rows, the QP's index maps); the
linearization of both models, the rotated gains and the c = 0 rollouts come from one plain-float
pass over the horizon; the rest is a handful of batched matrix products.
"""

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from onboard.core.config import ControllerSettings
from onboard.core.errors import InfeasibleError
from onboard.core.sparse_qp import INFINITY, FixedPatternQp
from onboard.core.tube import (
    cruise_linearization,
    dare_gain,
    position_tube_radius,
    robust_input_tightening,
)

__all__ = ["QpData", "QpSolution", "TubeLbmpc"]

# The stacked state X = [zbar; ztil] (6) moves with Ab = blockdiag(A, A~) (6 x 6) and Bb = [B; B~]
# (6 x 2). Flat positions, within one step's Ab and Bb, of the entries that change with the
# linearization point (all others are 0, the identity, or tau):
_AB_HEADING = np.array([0 * 6 + 2, 1 * 6 + 2, 3 * 6 + 5, 4 * 6 + 5])
"""dx+/dth and dy+/dth of A, then of A~."""
_BB_POSITION = np.array([0, 1, 2, 3, 6, 7, 8, 9])
"""B[0:2, 0:2] then B~[0:2, 0:2], row-major."""
# Columns of the per-step row the linearization's float loop writes.
_LIN_A = slice(0, 4)
"""dx/dth, dy/dth of A, then of A~ (to _AB_HEADING)."""
_LIN_B = slice(4, 12)
"""B[0:2, 0:2], then B~[0:2, 0:2] (to _BB_POSITION)."""
_LIN_K = slice(12, 18)
"""K_j row-major."""
_LIN_X0 = slice(18, 24)
"""[zref; ztil] at c = 0, at step j + 1."""
_LIN_RESIDUAL = slice(24, 27)
"""ztil_{j+1}(c = 0) - r_{j+1}, heading wrapped."""
_LIN_WIDTH = 27


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


class _Period(NamedTuple):
    """One period's condensed QP (see `TubeLbmpc._layout` for the rows of Y)."""

    Y: np.ndarray
    """(8M + NM, 2M + 1): every affine map of c the period needs, constant part last."""
    x0: np.ndarray
    """(M + 1, 6): the stacked prediction [zbar; ztil] at c = 0, j = 0..M."""


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
        self._precompute()
        self._last_c: np.ndarray | None = None

    # -- constant structure ---------------------------------------------------------------------
    def _precompute(self) -> None:
        """Build what every period shares, so a period only writes the values that change.

        One period's condensed QP lives in one array Y of 2M + 1 columns (c_0..c_{M-1}, then a
        constant) whose rows are, by block (named slices `_rows_*`):
            states      6M rows   X_j = d[zbar_j; ztil_j]/dc, j = 1..M (the constant column
                                  holds the learned cost residual ztil_j(c = 0) - r_j)
            inputs      2M rows   Hu_j = du_j/dc, j = 0..M-1 (u_j - u_s,j; constant 0)
            separation  NM rows   n_kj' dpbar_j/dc for neighbour k, step j = 1..M
        With W (8M x 8M) the cost weights on the first two blocks (zero on the nominal states),
        the cost is (Y c + y)' W (Y c + y), so one product Y' W Y gives P and q, and A is the
        last two blocks: both are read from Y through flat index maps.

        Cached: the K0 entries as floats; Ab and Bb with their constant entries (identity, tau);
        E_j, which injects c_j into u_j; W with its constant entries (heading and input weights;
        the position weights and the terminal block are rewritten every period);
        the input-bound rows of l and u (the separation rows' u is +infinity); the index maps;
        and the OSQP problem with its fixed pattern.
        """
        s, M, N, n = self.settings, self.M, self.n_neighbours, 2 * self.M
        self._K0_entries = tuple(float(k) for k in self.K0.ravel())
        self._Ab_template = np.tile(np.eye(6), (M, 1, 1))
        self._Bb_template = np.zeros((M, 6, 2))
        self._Bb_template[:, 2, 1] = self.tau
        steps = np.arange(M)[:, None]
        self._Ab_heading = (36 * steps + _AB_HEADING).ravel()  # flat, over all M steps
        self._Bb_position = (12 * steps + _BB_POSITION).ravel()
        self._E = np.zeros((M, 2, n))
        for j in range(M):
            self._E[j, :, 2 * j : 2 * j + 2] = np.eye(2)
        # Rows of Y.
        self._rows_states = slice(0, 6 * M)
        self._rows_inputs = slice(6 * M, 8 * M)
        self._rows_separation = slice(8 * M, 8 * M + N * M)
        self._Y_shape = (8 * M + N * M, n + 1)
        # Weights: stage j's learned position and heading rows, the terminal block, the inputs.
        W = np.zeros((8 * M, 8 * M))
        learned = 6 * np.arange(M)[:, None] + np.array([3, 4, 5])  # rows of ztil_j, j = 1..M
        W[learned[:-1, 2], learned[:-1, 2]] = s.q_heading
        inputs = np.arange(6 * M, 8 * M)
        W[inputs, inputs] = np.tile([s.r_speed, s.r_yaw_rate], M)
        self._W = W
        terminal = learned[-1]
        self._W_variable = np.concatenate(
            [
                (learned[:-1, :2] * (8 * M + 1)).ravel(),  # position weights, j = 1..M-1
                (terminal[:, None] * (8 * M) + terminal[None, :]).ravel(),  # P block, row-major
            ]
        )
        """Flat entries of W written each period: stage position weights, then the terminal P."""
        self._P0_entries = tuple(self.P0.ravel().tolist())
        bound = (self.u_max[None, :] - self.tightening).ravel()
        self._input_lower, self._input_upper = -bound, bound
        self._first_input_limit = tuple(float(u) * (1 + 1e-3) + 1e-6 for u in self.u_max)
        # Pattern: P upper triangle dense; u_j depends on c_0..c_j; a separation row at step j
        # on c_0..c_{j-1}.
        p_mask = np.triu(np.ones((n, n), dtype=bool))
        in_mask = np.zeros((2 * M, n), dtype=bool)
        for j in range(M):
            in_mask[2 * j : 2 * j + 2, : 2 * j + 2] = True
        sep_mask = np.zeros((N * M, n), dtype=bool)
        for k in range(N):
            for j in range(1, M + 1):
                sep_mask[k * M + j - 1, : 2 * j] = True
        self._qp = FixedPatternQp(
            p_mask, np.vstack([in_mask, sep_mask]), eps=s.solver_eps, max_iter=s.solver_max_iter
        )
        self._qp.u[2 * M :] = INFINITY
        self._warm = np.zeros(n)
        self._x_ext = np.zeros(n + 1)  # [c; 0]: Y's rows at c, constant column ignored

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
        return np.array(self._terminal_entries(yaw, 1.0)).reshape(3, 3)

    def fallback_input(self, z: np.ndarray, reference: np.ndarray, u_s: np.ndarray) -> np.ndarray:
        """The tube feedback law u = u_s + K (z - z_ref), clipped to U (used when a solve fails)."""
        err = np.asarray(z, float) - np.asarray(reference, float)
        err[2] = (err[2] + np.pi) % (2 * np.pi) - np.pi
        u = np.asarray(u_s, float) + self.feedback_gain(float(reference[2])) @ err
        u = np.where(np.isfinite(u), u, 0.0)
        return np.clip(u, -self.u_max, self.u_max)

    def _failed(self, status: str, x0: np.ndarray, d: QpData) -> QpSolution:
        return QpSolution(
            ok=False,
            status=status,
            c=np.zeros((self.M, 2)),
            inputs=np.array(d.u_s, dtype=float),
            nominal=x0[:, :3].copy(),
            learned=x0[:, 3:].copy(),
            iterations=0,
        )

    # -- one period -----------------------------------------------------------------------------
    def _linearize(
        self, d: QpData
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Both models along the linearization trajectory, in one plain-float pass over j.

        Returns Phi (M, 6, 6) = Ab + Bb [K 0] (how the stacked state's dependence on c
        propagates), Bb (M, 6, 2), K (M, 2, 3), x0 (M + 1, 6), the stacked prediction at c = 0
        ([zref; ztil], the linearized models' rollouts of u_s from z0), and the learned cost
        residual at c = 0 (M, 3) for j = 1..M, heading wrapped. Per step j, at
        phi = th + tau a_w w / 2:
            A = I + (dx/dth, dy/dth, 0) e3',  dx/dth = -tau a_V v sin phi,
            dy/dth = tau a_V v cos phi,  B = [[tau a_V cos phi, dx/dth tau a_w / 2],
            [tau a_V sin phi, dy/dth tau a_w / 2], [0, tau a_w]],
            e = (tau d_x - dx/dth phi, tau d_y - dy/dth phi, 0),
        with (a_V, a_w, d_x, d_y) = beta for the learned model and (1, 1, 0, 0) for the nominal.
        With M a handful of steps, a float loop is cheaper than a few dozen numpy calls on
        (M,)-arrays.
        """
        M, tau = self.M, self.tau
        a_v, a_w, d_x, d_y = np.asarray(d.beta, dtype=float).tolist()
        tv, hw, tw = tau * a_v, 0.5 * tau * a_w, tau * a_w  # learned
        hn = 0.5 * tau  # nominal, a_V = a_w = 1
        k00, k01, k02, k10, k11, k12 = self._K0_entries
        sin, cos, pi, two_pi = math.sin, math.cos, math.pi, 2.0 * math.pi
        xb, yb, hb = np.asarray(d.z0, dtype=float).tolist()
        xt, yt, ht = xb, yb, hb
        out: list[float] = []  # per step: the _LIN_COLUMNS
        steps = zip(
            d.lin_states[:M, 2].tolist(),
            d.lin_inputs.tolist(),
            d.u_s.tolist(),
            d.targets.tolist(),
            strict=True,
        )
        for th, (v, w), (us_v, us_w), (rx, ry, rh) in steps:
            phi = th + hn * w
            s, c = sin(phi), cos(phi)
            dx, dy = -tau * v * s, tau * v * c
            b00, b01, b10, b11 = tau * c, dx * hn, tau * s, dy * hn
            xb, yb, hb = (
                xb + dx * hb + b00 * us_v + b01 * us_w - dx * phi,
                yb + dy * hb + b10 * us_v + b11 * us_w - dy * phi,
                hb + tau * us_w,
            )
            phi = th + hw * w
            s, c = sin(phi), cos(phi)
            tx, ty = -tv * v * s, tv * v * c
            t00, t01, t10, t11 = tv * c, tx * hw, tv * s, ty * hw
            xt, yt, ht = (
                xt + tx * ht + t00 * us_v + t01 * us_w + tau * d_x - tx * phi,
                yt + ty * ht + t10 * us_v + t11 * us_w + tau * d_y - ty * phi,
                ht + tw * us_w,
            )
            c, s = cos(th), sin(th)
            out += (
                dx, dy, tx, ty,
                b00, b01, b10, b11, t00, t01, t10, t11,
                k00 * c - k01 * s, k00 * s + k01 * c, k02,
                k10 * c - k11 * s, k10 * s + k11 * c, k12,
                xb, yb, hb, xt, yt, ht,
                xt - rx, yt - ry, (ht - rh + pi) % two_pi - pi,
            )  # fmt: skip
        lin = np.fromiter(out, float, len(out)).reshape(M, _LIN_WIDTH)
        Phi = self._Ab_template.copy()
        Phi.ravel()[self._Ab_heading] = lin[:, _LIN_A].ravel()
        Bb = self._Bb_template.copy()
        Bb.ravel()[self._Bb_position] = lin[:, _LIN_B].ravel()
        Bb[:, 5, 1] = tw  # B~[2, 1] = tau a_w (B[2, 1] = tau is constant)
        K = lin[:, _LIN_K].reshape(M, 2, 3)
        Phi[:, :, :3] += Bb @ K
        x0 = np.empty((M + 1, 6))
        x0[0, :3] = x0[0, 3:] = d.z0
        x0[1:] = lin[:, _LIN_X0]
        return Phi, Bb, K, x0, lin[:, _LIN_RESIDUAL]

    def _condense(self, d: QpData) -> _Period:
        """Fill Y's state and input rows: one recursion on the stacked sensitivities,
        X_1 = Bb_0 E_0, X_{j+1} = Phi_j X_j + Bb_j E_j (only the columns of c_0..c_j are
        nonzero), and Hu_j = K_j dzbar_j/dc + E_j."""
        M, n = self.M, 2 * self.M
        Phi, Bb, K, x0, residual = self._linearize(d)
        Y = np.zeros(self._Y_shape)
        X = Y[self._rows_states, :n].reshape(M, 6, n)  # X[j - 1] is X_j
        X[0, :, :2] = Bb[0]
        for j in range(1, M):
            w = 2 * j
            X[j, :, :w] = Phi[j].dot(X[j - 1, :, :w])
            X[j, :, w : w + 2] = Bb[j]
        Y[self._rows_states, n].reshape(M, 6)[:, 3:] = residual
        Hu = Y[self._rows_inputs, :n].reshape(M, 2, n)
        Hu[1:] = K[1:] @ X[: M - 1, :3]
        Hu += self._E
        return _Period(Y, x0)

    def condense(self, d: QpData) -> tuple[np.ndarray, ...]:
        """Affine maps of c: (Sz, sz) nominal states, (St, st) learned states, Hu inputs.

        Shapes: Sz, St (M + 1, 3, 2M); sz, st (M + 1, 3); Hu (M, 2, 2M), whose constant part
        is u_s.
        """
        M, n = self.M, 2 * self.M
        Y, x0 = self._condense(d)
        S = np.zeros((M + 1, 6, n))
        S[1:] = Y[self._rows_states, :n].reshape(M, 6, n)
        Hu = Y[self._rows_inputs, :n].reshape(M, 2, n).copy()
        return S[:, :3], x0[:, :3].copy(), S[:, 3:], x0[:, 3:].copy(), Hu

    def solve(self, d: QpData) -> QpSolution:
        """Build this period's QP values, solve it, and check the answer."""
        M, N, n = self.M, self.n_neighbours, 2 * self.M
        qp = self._qp
        Y, x0 = self._condense(d)
        u_s = d.u_s.ravel()
        # Cost: P = 2 Y' W Y and q = 2 Y' W y over the state and input rows.
        W = self._W  # every entry that varies is written here
        W.ravel()[self._W_variable] = [
            *(w for w in d.position_weights[: M - 1].tolist() for _ in "xy"),
            *self._terminal_entries(float(d.targets[-1, 2]), float(d.terminal_scale)),
        ]
        Yc = Y[: 8 * M]
        H = Yc.T.dot(W.dot(Yc))  # (n + 1, n + 1): [[P / 2, q / 2], [., .]]
        Hc = H[:n, :n]
        np.multiply(H[:n, n], 2.0, out=qp.q)
        # Input constraints: u_j = Hu_j c + u_s,j within the tightened box.
        np.subtract(self._input_lower, u_s, out=qp.l[: 2 * M])
        np.subtract(self._input_upper, u_s, out=qp.u[: 2 * M])
        # Separation constraints, one row per neighbour k and step j = 1..M.
        if N:
            normals, qp.l[2 * M :] = self._separation(d, x0)
            X = Y[self._rows_states, :n].reshape(M, 6, n)
            rows = np.matmul(normals, X[:, :2])  # (N, M, 1, n)
            Y[self._rows_separation, :n] = rows.reshape(N * M, n)
        qp.gather(Hc + Hc.T, Y[6 * M :, :n])
        if not qp.finite():
            # Never hand the solver non-finite data: it would poison its factorization.
            self._last_c = None
            return self._failed("non-finite problem data", x0, d)
        qp.update()
        if self._last_c is not None:
            self._warm[:-2] = self._last_c[2:]
            qp.warm_start(self._warm)
        ok, status, x, iterations = qp.solve()
        if ok and not math.isfinite(x.dot(x)):
            ok, status = False, "non-finite solution"
        if not ok:
            self._last_c = None
            x = np.zeros(n)
        # Predictions and inputs: the state and input rows of Y at c = x (constant column x 0).
        self._x_ext[:n] = x
        y = Yc.dot(self._x_ext)
        inputs = y[self._rows_inputs]
        inputs += u_s
        u0, w0 = inputs[:2].tolist()
        v_lim, w_lim = self._first_input_limit
        if ok and (abs(u0) > v_lim or abs(w0) > w_lim):
            ok, status = False, "first input outside U"
        if ok:
            self._last_c = x
        z = x0.copy()
        z[1:] += y[self._rows_states].reshape(M, 6)
        return QpSolution(
            ok=ok,
            status=status,
            c=x.reshape(M, 2),
            inputs=inputs.reshape(M, 2),
            nominal=z[:, :3],
            learned=z[:, 3:],
            iterations=iterations,
        )

    def _separation(self, d: QpData, x0: np.ndarray) -> tuple[np.ndarray, list[float]]:
        """Unit normals (N, M, 1, 2) and lower bounds (N M) of the separation rows.

        The normal n_kj points from neighbour k's predicted position to the linearization point
        at step j (from z0 when the two coincide); the row is n_kj' pbar_j(c) >= margin_kj, i.e.
        n_kj' dpbar_j/dc c >= margin_kj - n_kj' (zref_j - p_kj). A row whose margin is not finite
        is off: zero normal, lower bound -infinity. Plain floats: N M is a handful of pairs.
        """
        M, N = self.M, self.n_neighbours
        lin = d.lin_states[1:, :2].tolist()
        ref = x0[1:, :2].tolist()
        x_0, y_0 = np.asarray(d.z0[:2], dtype=float).tolist()
        normals, lower = [], []
        for p_k, margins in zip(
            d.neighbour_positions.tolist(), d.neighbour_margins.tolist(), strict=True
        ):
            for (px, py), margin, (lx, ly), (rx, ry) in zip(p_k, margins, lin, ref, strict=True):
                if not math.isfinite(margin):
                    normals += (0.0, 0.0)
                    lower.append(-INFINITY)
                    continue
                ax, ay = lx - px, ly - py
                dist = math.hypot(ax, ay)
                if dist < 1e-6:
                    ax, ay = x_0 - px, y_0 - py
                    dist = math.hypot(ax, ay)
                dist = max(dist, 1e-9)
                nx, ny = ax / dist, ay / dist
                normals += (nx, ny)
                lower.append(margin - (nx * (rx - px) + ny * (ry - py)))
        return np.array(normals).reshape(N, M, 1, 2), lower

    def _terminal_entries(self, yaw: float, scale: float) -> tuple[float, ...]:
        """The 9 entries (row-major) of scale T(yaw) P0 T(yaw)', from P0's entries."""
        a, b, d, _, e, f, _, _, g = self._P0_entries  # P0 is symmetric
        c, s = math.cos(yaw), math.sin(yaw)
        r0 = (c * a - s * b, c * b - s * e)  # row 0 of T P0, position columns
        r1 = (s * a + c * b, s * b + c * e)
        p00 = scale * (r0[0] * c - r0[1] * s)
        p01 = scale * (r0[0] * s + r0[1] * c)
        p11 = scale * (r1[0] * s + r1[1] * c)
        p02 = scale * (c * d - s * f)
        p12 = scale * (s * d + c * f)
        return p00, p01, p02, p01, p11, p12, p02, p12, scale * g
