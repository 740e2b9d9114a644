"""The tube LBMPC's QP in condensed form: its fixed structure and each period's values
(docs/design.md, "Controller"; `fleetmpc.onboard.core.lbmpc` solves it).

With the inputs parametrized as u_j = K_j (zbar_j - zref_j) + u_s,j + c_j, both predictions are
affine in c:
    nominal  zbar_{j+1} = A_j zbar_j + B_j u_j + e_j            (the feedback's reference)
    learned  ztil_{j+1} = A~_j ztil_j + B~_j u_j + e~_j          (cost, minimum separation)
each linearized along the caller's trajectory. `CondensedQp` eliminates the predictions through
one triangular system and writes the cost (P, q) and the constraint rows (A, l, u: the tightened
input box with its yaw-rate trust region, the separation half-planes, the speed changes) into
OSQP's buffer, on the fixed sparsity pattern of a `FixedPatternQp`; it also gives the
predictions and inputs at any c.

Speed: a period runs in a fraction of a millisecond, so the per-period code counts numpy calls.
Everything that does not depend on the period's data is built in the constructor (the constant
entries of the condensing system and of the weights, the QP's index maps). One plain-float pass
over the horizon linearizes both models, rotates the gains, rolls out c = 0, and builds the
bounds, the separation rows and the terminal weight; its values reach their places in one
scatter; one triangular solve condenses the horizon (`CondensedQp._precompute`); an elementwise
product and two BLAS products give the cost; one take hands P, A and q to OSQP; one product gives
the solution's predictions and inputs, and one take sorts them by kind into contiguous arrays.
"""

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas

from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.sparse_qp import INFINITY, FixedPatternQp
from fleetmpc.onboard.core.tube import InputBox
from fleetmpc.onboard.core.unicycle import linearization, wrap

__all__ = ["CondensedQp", "QpData"]

_BLOCK = 8
"""Rows per step j in the condensing system: zbar_j (3), ztil_j (3), u_j (2)."""


Floats = (
    np.ndarray | Sequence[float] | Sequence[Sequence[float]] | Sequence[Sequence[Sequence[float]]]
)
"""An array, or the same numbers as (nested) sequences of plain floats."""


def _rows(a: Floats) -> list:
    """Nested plain-float lists (or the sequences as given) of a small array-like."""
    return a.tolist() if isinstance(a, np.ndarray) else a


@dataclass(frozen=True, eq=False)
class QpData:
    """Everything one period's QP depends on. Shapes use M = horizon, N = number of neighbours.

    Each array may also be given as nested sequences of plain floats of its shape (rows as lists
    or tuples): the agent computes its data in floats, and the QP's float pass reads them as
    floats, so an array round trip in between would cost more than the arithmetic on them.
    """

    z0: Floats
    """Current state estimate (3,)."""
    lin_states: Floats
    """Linearization trajectory (M + 1, 3); lin_states[0] should be z0."""
    lin_inputs: Floats
    """Linearization inputs (M, 2); speeds must not be 0."""
    beta: Floats
    """Learned oracle parameters (4,)."""
    u_s: Floats
    """Steady-state inputs under the learned model (M, 2)."""
    targets: Floats
    """Cost targets r_j for j = 1..M (M, 3): position and heading (unwrapped near lin_states)."""
    position_weights: Floats
    """Position weight of each stage j = 1..M (M,) [1/m^2]."""
    terminal_scale: float
    """Scale of the terminal weight P (formation weight present / formation weight assumed)."""
    speed_now_m_s: float
    """The speed the vehicle was last commanded [m/s]: the first planned speed changes from it
    by at most speed_rate_max_m_s2 tau."""
    yaw_rate_now_rad_s: float
    """The yaw rate the vehicle was last commanded [rad/s]: the first planned yaw rate's change
    from it is penalized like the later ones' (r_yaw_rate_change)."""
    separation_planes: Floats
    """Per neighbour k and step j = 1..M, a half-plane (n_x, n_y, b) that the learned prediction's
    position must keep to, n' ptil_j >= b, with n a unit normal (N, M, 3); a non-finite b
    disables the row."""


class CondensedQp:
    """The condensed QP of one vehicle with `n_neighbours` neighbours: structure built once,
    values written each period (`assemble`), solved by the caller through `osqp`."""

    def __init__(
        self,
        settings: ControllerSettings,
        *,
        n_neighbours: int,
        K0: np.ndarray,
        P0: np.ndarray,
        box: InputBox,
    ) -> None:
        self.settings = settings
        self.M = settings.horizon
        self.tau = settings.period_s
        self.n_neighbours = n_neighbours
        self.K0, self.P0 = K0, P0
        """The DARE gain and terminal weight at heading 0 (`fleetmpc.onboard.core.tube`)."""
        self.box = box
        """U and its tightened box of each step j (`InputBox.steps`)."""
        self._precompute()

    # -- constant structure ---------------------------------------------------------------------
    def _precompute(self) -> None:
        """Build what every period shares, so a period only writes the values that change.

        Condensing as one triangular system. Stack, per step j = 0..M, the two predictions and
        the input they lead to, v_j = [zbar_j; ztil_j; u_j] (8 rows, `_BLOCK`; u_M is padding),
        then the separation rows s_kj = n_kj' ptil_j for neighbour k and step j = 1..M (N M
        rows; on the learned prediction, where the vehicle is expected to be, wind included),
        then the speed-change rows a_j = V_j - V_{j-1}, j = 0..M-1 (M rows; V_{-1} is the speed
        now, a constant). Their derivatives with respect to c obey
            dzbar_0 = dztil_0 = 0
            du_j         - K_j dzbar_j                  = E_j   (E_j injects c_j into u_j)
            dzbar_{j+1}  - A_j dzbar_j   - B_j du_j     = 0
            dztil_{j+1}  - A~_j dztil_j  - B~_j du_j    = 0
            ds_kj        - n_kj' dptil_j                = 0
            da_j         - dV_j + dV_{j-1}              = 0   (no dV_{-1} term),
        a unit lower-triangular system T D = E (m x m, m = 8 (M + 1) + N M + M) whose forward
        substitution (one BLAS dtrsm) is the recursion through the horizon.

        Y (m x 2M + 2) holds D in its first 2M columns, then two constant columns: the learned
        cost residual ztil_j(c = 0) - r_j on the ztil_j rows, j = 1..M (0 elsewhere), and the
        rows' values at c = 0 (zref_j, ztil_j(c = 0), u_s,j: the linearized models' rollouts of
        u_s from z0). With W twice the cost weights on the step rows (block diagonal by step:
        Q on ztil_j, the terminal P on ztil_M, R on u_j, 0 on zbar), the cost is
        (Y c + y)' W (Y c + y) / 2 over the first 2M + 1 columns, so one product H = Y' W Y
        holds OSQP's P and q as [[P, q], [q', .]]; OSQP's A is the u, s and a rows of Y; and one
        product Y [c; 0; 1] gives every prediction and input of the solution. W is diagonal but
        for the terminal P, so it is kept as its diagonal (0 on the ztil_M rows), repeated along
        the columns of Y (`_w`, so that the diagonal part of W Y is an elementwise product of
        two arrays of one shape), and P_M, whose product with the ztil_M rows overwrites theirs.
        The products run over all 2M + 2 columns of the step rows (a contiguous block whose last
        column's products go unread), so that BLAS reads Y in place.

        Also cached: the K0 and P0 entries as floats, the packer of the float pass, and the OSQP
        problem with its fixed pattern (`osqp`).
        """
        M, N = self.M, self.n_neighbours
        self._steps = _BLOCK * (M + 1)
        self._m = self._steps + N * M + M
        self._K0_entries = tuple(float(k) for k in self.K0.ravel())
        self._P0_entries = tuple(self.P0.ravel().tolist())
        self._zbar_row = [_BLOCK * j for j in range(M + 1)]  # rows of zbar_j, ztil_j and u_j
        self._ztil_row = [_BLOCK * j + 3 for j in range(M + 1)]
        self._u_row = [_BLOCK * j + 6 for j in range(M + 1)]
        p_mask, a_mask = self._pattern()
        views, index = self._allocate(p_mask, a_mask)
        self._set_up_solver(p_mask, a_mask, views["qp"])
        self._T, self._Y = views["T"], views["Y"]
        self._write_constant_system()
        self._lin_dest = self._scatter_map(index)
        self._pack = struct.Struct(f"{len(self._lin_dest)}d").pack
        self._set_up_weights()
        self._set_up_products(views, index)

    def _pattern(self) -> tuple[np.ndarray, np.ndarray]:
        """OSQP's pattern: P's upper triangle dense; A's rows, Y's u rows (u_j depends on
        c_0..c_j), then its separation rows (a row at step j on c_0..c_{j-1}), then its
        speed-change rows (u_j - u_{j-1} on c_0..c_j)."""
        M, N, n = self.M, self.n_neighbours, 2 * self.M
        p_mask = np.triu(np.ones((n, n), dtype=bool))
        in_mask = np.zeros((2 * M, n), dtype=bool)
        for j in range(M):
            in_mask[2 * j : 2 * j + 2, : 2 * j + 2] = True
        sep_mask = np.zeros((N * M, n), dtype=bool)
        for k in range(N):
            for j in range(1, M + 1):
                sep_mask[k * M + j - 1, : 2 * j] = True
        accel_mask = np.zeros((M, n), dtype=bool)
        for j in range(M):
            accel_mask[j, : 2 * j + 2] = True
        return p_mask, np.vstack([in_mask, sep_mask, accel_mask])

    def _allocate(
        self, p_mask: np.ndarray, a_mask: np.ndarray
    ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The period buffer (OSQP's values, T, Y, P_M, H) as views, and, carved from
        np.arange alongside, each entry's flat index.

        Persistent buffers: OSQP's values, T, Y, P_M and H are views into one flat buffer, so
        that the period's float pass reaches every value it computes (T's and Y's entries, the
        bounds l and u, the terminal P) with one scatter through a flat index map (`_lin_dest`),
        and P, A and q reach OSQP with one take (`_qp_sources`). Entries that never change (T's
        unit diagonal, the identity parts of A and A~, B's tau, K_j's heading column, which the
        rotation leaves as K0's, the heading and input weights, the separation rows'
        u = +infinity) are written once. A period overwrites every entry that depends on its
        data, so nothing of an earlier period (even a non-finite one) survives into the next;
        the stage position weights in `_w`, which change only with the number of formation
        terms, are rewritten whenever they differ from the last period's.
        """
        m, n = self._m, 2 * self.M
        shapes = {
            "qp": ((FixedPatternQp.data_size(p_mask, a_mask),), "C"),
            "T": ((m, m), "F"),  # Fortran order: dtrsm reads it in place
            "Y": ((m, n + 2), "C"),
            "P_M": ((3, 3), "C"),
            "H": ((n + 2, n + 2), "C"),
        }
        total = sum(math.prod(shape) for shape, _ in shapes.values())
        self._buffer = np.zeros(total)
        views, index, start = {}, {}, 0
        for name, (shape, order) in shapes.items():
            stop = start + math.prod(shape)
            views[name] = self._buffer[start:stop].reshape(shape, order=order)
            index[name] = np.arange(start, stop).reshape(shape, order=order)
            start = stop
        return views, index

    def _set_up_solver(self, p_mask: np.ndarray, a_mask: np.ndarray, data: np.ndarray) -> None:
        """OSQP on the fixed pattern, its values in `data`; A's rows read from Y's rows."""
        s, M, n = self.settings, self.M, 2 * self.M
        a_rows = [self._u_row[j] + i for j in range(M) for i in (0, 1)]
        self._a_rows = np.array(a_rows + list(range(self._steps, self._m)))
        """Y's rows that are A's, in A's order."""
        self.osqp = FixedPatternQp(
            p_mask,
            a_mask,
            eps=s.solver_eps,
            max_iter=s.solver_max_iter,
            a_rows=self._a_rows,
            a_row_length=n + 2,
            data=data,
        )
        self.osqp.u[2 * M : 2 * M + self.n_neighbours * M] = INFINITY  # lower bounds only

    def _write_constant_system(self) -> None:
        """T's entries that never change (its unit diagonal, the identity parts of A and A~,
        B's tau, K_j's heading column, the speed-change rows) and E."""
        M, m, T = self.M, self._m, self._T
        zbar_row, ztil_row, u_row = self._zbar_row, self._ztil_row, self._u_row
        accel = self._steps + self.n_neighbours * M  # the first speed-change row
        T[np.arange(m), np.arange(m)] = 1.0
        for j in range(M):
            T[zbar_row[j + 1] + 2, u_row[j] + 1] = -self.tau  # B[2, 1] (B~[2, 1] varies)
            T[u_row[j] : u_row[j] + 2, zbar_row[j] + 2] = -self.K0[:, 2]  # (not rotated)
            for r in range(3):  # the identity parts of A_j and A~_j
                T[zbar_row[j + 1] + r, zbar_row[j] + r] = -1.0
                T[ztil_row[j + 1] + r, ztil_row[j] + r] = -1.0
        for j in range(M):  # the speed-change rows: ds_j - du_j + du_{j-1} = 0
            T[accel + j, u_row[j]] = -1.0
            if j:
                T[accel + j, u_row[j - 1]] = 1.0
        self._E = np.zeros((m, 2 * M), order="F")
        for j in range(M):
            self._E[u_row[j] : u_row[j] + 2, 2 * j : 2 * j + 2] = np.eye(2)

    def _scatter_map(self, index: dict[str, np.ndarray]) -> np.ndarray:
        """Where the float pass's values go, in its order (`_fill`): flat buffer positions."""
        M, N, n, steps = self.M, self.n_neighbours, 2 * self.M, self._steps
        qp = self.osqp
        il, iu = index["qp"][qp.layout["l"]], index["qp"][qp.layout["u"]]
        iT, iY = index["T"], index["Y"]
        dest = iY[: self._ztil_row[0] + 3, n + 1].tolist()  # zbar_0 = ztil_0 = z0
        for j in range(M):
            zb, zt, u = self._zbar_row[j], self._ztil_row[j], self._u_row[j]
            zb1, zt1 = self._zbar_row[j + 1], self._ztil_row[j + 1]
            for entries in (
                iT[u : u + 2, zb : zb + 2],  # K_j's position columns
                iY[u : u + 2, n + 1],  # u_s,j
                il[2 * j : 2 * j + 2],  # its bounds, lower
                iu[2 * j : 2 * j + 2],  # and upper
                iT[zb1 : zb1 + 2, zb + 2],  # A_j's heading column
                iT[zb1 : zb1 + 2, u : u + 2],  # B_j
                iT[zt1 : zt1 + 2, zt + 2],  # A~_j's heading column
                iT[zt1 : zt1 + 2, u : u + 2],  # B~_j
                iT[zt1 + 2 : zt1 + 3, u + 1],  # B~_j[2, 1]
                iY[zb1 : zt1 + 3, n + 1],  # zref_{j+1}, ztil_{j+1} at c = 0
                iY[zt1 : zt1 + 3, n],  # cost residual
            ):
                dest += entries.ravel().tolist()
        for k in range(N):
            for j in range(1, M + 1):
                row = self._ztil_row[j]
                dest += iT[steps + k * M + j - 1, row : row + 2].tolist()
                dest.append(int(il[2 * M + k * M + j - 1]))
        for j in range(M):  # the speed-change rows' bounds
            dest += (int(il[2 * M + N * M + j]), int(iu[2 * M + N * M + j]))
        dest += index["P_M"].ravel().tolist()  # terminal P, row-major
        return np.array(dest, dtype=np.intp)

    def _set_up_weights(self) -> None:
        """W's diagonal by step block, doubled (so that Y' W Y is OSQP's P, and q its column n):
        q_heading and the stage position weights (`_set_stage_weights`) on ztil_j, R on u_j; the
        terminal P on ztil_M is written every period, through the scatter."""
        s, M, n = self.settings, self.M, 2 * self.M
        self._w = np.zeros((self._steps, n + 2))
        self._w_steps = w = self._w.reshape(M + 1, _BLOCK, n + 2)
        w[1:M, 5] = 2.0 * s.q_heading
        w[:M, 6], w[:M, 7] = 2.0 * s.r_speed, 2.0 * s.r_yaw_rate
        self._stage_weights: list[float] = [0.0] * (M - 1)
        """The position weights of j = 1..M-1 that `_w` holds (zero until the first period)."""

    def _set_up_products(self, views: dict[str, np.ndarray], index: dict[str, np.ndarray]) -> None:
        """The views and index maps the period's products read and write."""
        M, n, qp, Y = self.M, 2 * self.M, self.osqp, self._Y
        zbar_row, ztil_row, u_row = self._zbar_row, self._ztil_row, self._u_row
        self._P_M = views["P_M"]
        self._H = views["H"]  # [[P, q, .], [q', ., .], ...]: P's upper triangle and q to OSQP
        iH = index["H"]
        self._qp_sources = qp.value_sources(iH[:n, :n], index["Y"], iH[:n, n])
        self._qp_values = qp.data[: qp.layout["q"].stop]
        """OSQP's Px, Ax and q, gathered from H and Y with one take."""
        self._Y_steps = Y[: self._steps]
        self._yaw_rows = np.array([u_row[j] + 1 for j in range(M)])
        """Y's rows of the planned yaw rates."""
        self._yaw_change = np.zeros((M, n + 1))
        """Each planned yaw rate's change from the one before (the first: from the yaw rate
        flown now), as [derivative in c; value at c = 0]."""
        self._WY = np.zeros((self._steps, n + 2))
        terminal = slice(ztil_row[M], ztil_row[M] + 3)
        self._Y_terminal, self._WY_terminal = Y[terminal], self._WY[terminal]
        self._by_kind = np.array(
            [u_row[j] + i for j in range(M) for i in range(2)]
            + [ztil_row[j] + i for j in range(M + 1) for i in range(3)]
            + [zbar_row[j] + i for j in range(M + 1) for i in range(3)]
        )
        """The step rows as the solution hands them out: inputs, learned, nominal predictions."""
        self.x0 = Y[: self._steps, n + 1].reshape(M + 1, _BLOCK)[:, :6]
        """[zref; ztil] at c = 0, j = 0..M (M + 1, 6): a view into Y."""
        self._x_ext = np.zeros(n + 2)  # [c; 0; 1]: Y's rows at c
        self._x_ext[-1] = 1.0

    # -- one period -----------------------------------------------------------------------------
    def _fill(self, d: QpData) -> None:
        """One plain-float pass over the period's data: both models along the linearization
        trajectory, the rotated gains, the c = 0 rollouts, the input bounds, the separation rows
        and the terminal weight, scattered into T, Y's constant columns, OSQP's l and u and P_M;
        then the stage position weights into `_w` if they changed.

        Values go out in `_lin_dest`'s order through one `struct` pack. With M a handful of
        steps, a float loop is cheaper than a few dozen numpy calls on (M,)-arrays.
        """
        xb, yb, hb = _rows(d.z0)
        out = [xb, yb, hb, xb, yb, hb]  # zbar_0, ztil_0; then per step, `_lin_dest`'s entries
        ref = self._horizon_entries(d, out)
        if self.n_neighbours:
            self._separation(d, ref, out)
        # Speed changes: u_0 - V_now and u_j - u_{j-1} within +-a_max tau, less their values at
        # c = 0 (the steady speeds' changes).
        step = self.settings.speed_rate_max_m_s2 * self.tau
        last = float(d.speed_now_m_s)
        for us_v, _ in _rows(d.u_s):
            out += (-step - (us_v - last), step - (us_v - last))
            last = us_v
        # The terminal P at the last target heading (doubled).
        out += self.terminal_entries(_rows(d.targets)[-1][2], 2.0 * d.terminal_scale)
        self._buffer[self._lin_dest] = np.frombuffer(self._pack(*out))
        self._set_stage_weights(_rows(d.position_weights)[: self.M - 1])

    def _horizon_entries(self, d: QpData, out: list[float]) -> list[tuple[float, float]]:
        """Per step j, appends to `out` the entries of the period's system: -K_j's position
        columns (K_j = K0 T(th_j)'), u_s,j, the input rows' bounds (the tightened box less
        u_s,j, the yaw rate within its trust region), the negated linearizations of both models
        at the linearization point (`fleetmpc.onboard.core.unicycle.linearization`; the nominal
        one at beta = (1, 1, 0, 0)), their rollouts of u_s at c = 0 (zref, ztil) and the cost
        residual, its heading wrapped. Returns ptil(0)'s positions, j = 1..M (where the
        separation rows are linearized)."""
        tau, trust_at = self.tau, self.settings.yaw_rate_trust
        a_v, a_w, d_x, d_y = _rows(d.beta)
        k00, k01, _, k10, k11, _ = self._K0_entries
        sin, cos = math.sin, math.cos
        xb, yb, hb = _rows(d.z0)
        xt, yt, ht = xb, yb, hb
        ref: list[tuple[float, float]] = []
        steps = zip(
            _rows(d.lin_states)[: self.M],
            _rows(d.lin_inputs),
            _rows(d.u_s),
            _rows(d.targets),
            self.box.steps,
            strict=True,
        )
        for (_, _, th), (v, w), (us_v, us_w), (rx, ry, rh), (lo_v, lo_w, hi_v, hi_w) in steps:
            c, s = cos(th), sin(th)
            # The yaw rate keeps within the trust region about the linearization's, wider the
            # slower the linearization flies (`ControllerSettings.yaw_rate_trust`).
            trust = trust_at(v)
            lo_w, hi_w = max(lo_w, min(w - trust, hi_w)), min(hi_w, max(w + trust, lo_w))
            out += (
                k01 * s - k00 * c, -k00 * s - k01 * c,  # -K_j's position columns
                k11 * s - k10 * c, -k10 * s - k11 * c,
                us_v, us_w,  # u_s,j
                lo_v - us_v, lo_w - us_w, hi_v - us_v, hi_w - us_w,  # input rows' l, u
            )  # fmt: skip
            phi, _, _, dx, dy, b00, b01, b10, b11, _ = linearization(th, v, w, 1.0, 1.0, tau)
            xb, yb, hb = (
                xb + dx * hb + b00 * us_v + b01 * us_w - dx * phi,
                yb + dy * hb + b10 * us_v + b11 * us_w - dy * phi,
                hb + tau * us_w,
            )
            phi, _, _, tx, ty, t00, t01, t10, t11, tw = linearization(th, v, w, a_v, a_w, tau)
            xt, yt, ht = (
                xt + tx * ht + t00 * us_v + t01 * us_w + tau * d_x - tx * phi,
                yt + ty * ht + t10 * us_v + t11 * us_w + tau * d_y - ty * phi,
                ht + tw * us_w,
            )
            out += (
                -dx, -dy, -b00, -b01, -b10, -b11,  # -A_j's heading column, -B_j
                -tx, -ty, -t00, -t01, -t10, -t11, -tw,  # the same of A~_j, B~_j
                xb, yb, hb, xt, yt, ht,  # zref_{j+1}, ztil_{j+1} at c = 0
                xt - rx, yt - ry, wrap(ht - rh),  # cost residual
            )  # fmt: skip
            ref.append((xt, yt))
        return ref

    def _set_stage_weights(self, weights: Sequence[float]) -> None:
        """Write the position weights of j = 1..M-1 (doubled) into `_w` when they changed."""
        if list(weights) != self._stage_weights:  # (a list, whatever sequence they came in)
            doubled = 2.0 * np.asarray(weights, float)
            self._w_steps[1 : self.M, 3:5] = doubled[:, None, None]
            self._stage_weights = list(weights)

    def _condense(self, d: QpData) -> None:
        """Fill T, Y and the bounds for this period (`_precompute` describes them)."""
        self._fill(d)
        self._Y[:, : 2 * self.M] = blas.dtrsm(1.0, self._T, self._E, lower=1, diag=1)

    def condense(self, d: QpData) -> tuple[np.ndarray, ...]:
        """Affine maps of c: (Sz, sz) nominal states, (St, st) learned states, Hu inputs.

        Shapes: Sz, St (M + 1, 3, 2M); sz, st (M + 1, 3); Hu (M, 2, 2M), whose constant part
        is u_s.
        """
        M, n = self.M, 2 * self.M
        self._condense(d)
        D = self._Y_steps[:, :n].reshape(M + 1, _BLOCK, n)
        x0 = self.x0
        return (
            D[:, :3].copy(),
            x0[:, :3].copy(),
            D[:, 3:6].copy(),
            x0[:, 3:].copy(),
            D[:M, 6:].copy(),
        )

    def assemble(self, d: QpData) -> None:
        """Build this period's QP values: P, q, A, l and u in OSQP's buffer (not yet handed to
        OSQP)."""
        self._condense(d)
        # Cost: [[P, q], [q', .]] = Y' W Y over the step rows (W doubled); A from Y's rows.
        np.multiply(self._w, self._Y_steps, out=self._WY)  # W's diagonal part
        np.dot(self._P_M, self._Y_terminal, out=self._WY_terminal)
        np.dot(self._Y_steps.T, self._WY, out=self._H)
        rho = self.settings.r_yaw_rate_change
        if rho:  # + rho sum_j (w_j - w_{j-1})^2, w_{-1} the yaw rate flown now
            n = 2 * self.M
            rows = self._Y.take(self._yaw_rows, axis=0)
            change = self._yaw_change
            change[:, :n] = rows[:, :n]
            change[:, n] = rows[:, n + 1]
            change[1:] -= change[:-1].copy()
            change[0, n] -= d.yaw_rate_now_rad_s
            self._H[: n + 1, : n + 1] += (2.0 * rho) * change.T.dot(change)
        self._buffer.take(self._qp_sources, out=self._qp_values)

    def predictions(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inputs (2M,), learned and nominal predictions (3 (M + 1),) at c = x, flat.

        The step rows of Y times [c; 0; 1], gathered by kind, so that each comes out as a
        contiguous array.
        """
        M, n = self.M, 2 * self.M
        self._x_ext[:n] = x
        y = self._Y_steps.dot(self._x_ext).take(self._by_kind)
        return y[:n], y[n : n + 3 * M + 3], y[n + 3 * M + 3 :]

    def constraint_rows(self, x: np.ndarray) -> np.ndarray:
        """A x: this period's constraint rows at c = x, in OSQP's order (its l and u bound them)."""
        return self._Y[self._a_rows, : 2 * self.M].dot(x)

    @staticmethod
    def _separation(d: QpData, ref: list[tuple[float, float]], out: list[float]) -> None:
        """Separation rows, for neighbour k and step j = 1..M: appends to `out` -n_kj (the
        system's entries) and the row's lower bound.

        The row is n_kj' ptil_j(c) >= b_kj, i.e. n_kj' dptil_j/dc c >= b_kj - n_kj' ptil_j(0),
        with `ref` the ptil_j(0). A row whose bound is not finite is off: zero normal, lower bound
        -infinity. Plain floats: N M is a handful of pairs.
        """
        isfinite = math.isfinite
        for planes in _rows(d.separation_planes):
            for (nx, ny, b), (rx, ry) in zip(planes, ref, strict=True):
                if isfinite(b):
                    out += (-nx, -ny, b - (nx * rx + ny * ry))
                else:
                    out += (0.0, 0.0, -INFINITY)

    def terminal_entries(self, yaw: float, scale: float) -> tuple[float, ...]:
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
