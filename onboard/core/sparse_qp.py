"""An OSQP problem with a sparsity pattern fixed at setup, updated in place every period.

    minimize  1/2 x'Px + q'x   subject to  l <= Ax <= u,   x in R^n, A in R^(m x n).

The pattern of P (upper triangle) and A is given once as boolean masks; every masked entry is a
structural nonzero (zeros are kept), so the nonzero count never changes and OSQP accepts every
update (docs/design.md, "Controller"). Each period the caller computes P and A densely and
copies the masked entries into OSQP's CSC order through flat index maps computed at setup
(`value_sources`; no scipy.sparse object is built per period), and writes q, l and u straight
into their views. A's rows may be read from a larger array whose rows come in another order
(`a_rows`), so that a caller whose constraint rows are interleaved with other rows needs no copy
to gather them.

All five value arrays live in one buffer, so one check (`finite`) covers the whole problem before
the solver sees it. Infinite bounds are written as +-OSQP_INFTY (1e30, what OSQP treats as
infinity), which keeps the buffer finite; any inf or nan left in it is bad data.

The solver is OSQP's compiled binding (`osqp.ext_builtin.OSQPSolver`), the object that
`osqp.OSQP` itself wraps, set up with the same settings. The wrapper's `update` and `solve` add
about 20 us of Python per period (a module look-up of OSQP_INFTY on every update, a namespace of
every info field on every solve), as much as the solve of this small QP. The binding is not
OSQP's public API: pyproject.toml keeps osqp below its next major release, and
tests/onboard/test_sparse_qp.py fails, saying so, when a release no longer takes these calls.
"""

import math

import numpy as np
import osqp
import osqp.ext_builtin as _ext
import scipy.sparse as sp

__all__ = ["CHECK_TERMINATION", "INFINITY", "FixedPatternQp"]

INFINITY = float(_ext.OSQP_INFTY)
"""What OSQP treats as an infinite bound."""

_SOLVED = int(osqp.SolverStatus.OSQP_SOLVED)

CHECK_TERMINATION = 5
"""OSQP checks termination every this many iterations (its default is 25): a solve that
converges between two checks stops up to 20 iterations sooner (paper.toml: mean 54 -> 46
iterations, median 25 either way), and a check on a problem this small costs less than the
iterations it saves."""


def _csc_pattern(
    mask: np.ndarray, rows: np.ndarray | None = None, row_length: int | None = None
) -> tuple[sp.csc_matrix, np.ndarray]:
    """Zero CSC matrix holding every entry of `mask`, and each entry's flat (row-major) index.

    The index is into a dense array of rows of `row_length` entries (default: the mask's own
    shape) where row i of the mask is row rows[i] (default: i).
    """
    m = sp.csc_matrix(mask.astype(float))
    m.sort_indices()
    cols = np.repeat(np.arange(mask.shape[1]), np.diff(m.indptr))
    source_rows = m.indices if rows is None else np.asarray(rows)[m.indices]
    flat = source_rows * (mask.shape[1] if row_length is None else row_length) + cols
    m.data[:] = 0.0
    return m, flat.astype(np.intp)


class FixedPatternQp:
    """OSQP on a fixed pattern: write values, check, `update`, `solve`."""

    def __init__(
        self,
        p_mask: np.ndarray,
        a_mask: np.ndarray,
        *,
        eps: float,
        max_iter: int,
        a_rows: np.ndarray | None = None,
        a_row_length: int | None = None,
        data: np.ndarray | None = None,
    ) -> None:
        """`a_rows[i]` is the row, in the caller's dense array that holds A, of A's row i, and
        `a_row_length` that array's row length (defaults: A itself, (m, n)). `data`, if given,
        is the zero 1-D array of `data_size(p_mask, a_mask)` entries to hold the values (a view
        of a caller's buffer, so that the caller can write them and values of its own through
        one scatter); by default the problem allocates its own."""
        n, m = p_mask.shape[0], a_mask.shape[0]
        if p_mask.shape != (n, n) or a_mask.shape[1] != n:
            raise ValueError("p_mask must be (n, n) and a_mask (m, n)")
        if np.tril(p_mask, -1).any():
            raise ValueError("p_mask must cover the upper triangle of P only")
        if a_rows is not None and len(a_rows) != m:
            raise ValueError("a_rows must name one source row per row of a_mask")
        self.n, self.m = n, m
        P, self._p_flat = _csc_pattern(p_mask)
        A, self._a_flat = _csc_pattern(a_mask, a_rows, a_row_length)
        n_p, n_a = self._p_flat.size, self._a_flat.size
        # One buffer, five views: P's and A's CSC values, then q, l, u.
        size = self.data_size(p_mask, a_mask)
        if data is None:
            data = np.zeros(size)
        elif data.shape != (size,) or data.any():
            raise ValueError(f"data must be a zero 1-D array of {size} entries")
        self.data = data
        ends = np.cumsum([0, n_p, n_a, n, m, m]).tolist()
        names = ("Px", "Ax", "q", "l", "u")
        self.layout = {
            name: slice(a, b) for name, a, b in zip(names, ends[:-1], ends[1:], strict=True)
        }
        """Where each of the five value vectors sits in `data`."""
        self.Px, self.Ax, self.q, self.l, self.u = (data[part] for part in self.layout.values())
        P.data[:] = np.eye(n).ravel()[self._p_flat]  # P = I and A = 0 until the first update
        settings = _ext.OSQPSettings()
        _ext.osqp_set_default_settings(settings)
        settings.verbose = False
        settings.eps_abs = settings.eps_rel = eps
        settings.max_iter = max_iter
        settings.warm_starting = True
        settings.polishing = False
        settings.check_termination = CHECK_TERMINATION
        self._solver = _ext.OSQPSolver(
            _ext.CSC(P), np.zeros(n), _ext.CSC(A), -np.ones(m), np.ones(m), m, n, settings
        )

    @staticmethod
    def data_size(p_mask: np.ndarray, a_mask: np.ndarray) -> int:
        """Entries of the value buffer: P's and A's pattern entries, then q, l and u."""
        n, m = p_mask.shape[0], a_mask.shape[0]
        return int(np.count_nonzero(p_mask)) + int(np.count_nonzero(a_mask)) + n + 2 * m

    def value_sources(
        self, P_index: np.ndarray, A_index: np.ndarray, q_index: np.ndarray
    ) -> np.ndarray:
        """Where Px, Ax and q (the head of `data`, in order) come from in a caller's buffer.

        Given the flat buffer position of every entry of dense P (n, n), of the array holding A
        (A itself, or the array that `a_rows` and `a_row_length` describe) and of q (n,), returns
        the position of each value in `data[:Px + Ax + q]`: a caller whose P, A and q live in one
        buffer then gathers them all with one take.
        """
        return np.concatenate(
            [
                np.asarray(P_index).ravel()[self._p_flat],
                np.asarray(A_index).ravel()[self._a_flat],
                np.asarray(q_index).ravel(),
            ]
        ).astype(np.intp)

    def finite(self) -> bool:
        """True when P, A, q, l and u hold no inf or nan (infinite bounds are +-INFINITY).

        One dot product: inf and nan propagate into it; entries beyond 1e150 (absurd for a QP
        whose bounds are 1e30) would overflow it and also count as bad data.
        """
        return math.isfinite(self.data.dot(self.data))

    def update(self) -> None:
        """Hand this period's values to OSQP (it refactors its KKT matrix)."""
        s = self._solver
        # Positional (q, l, u) and (P_x, P_i, A_x, A_i): the binding's keyword matching costs
        # about as much as the vector update itself.
        s.update_data_vec(self.q, self.l, self.u)
        s.update_data_mat(self.Px, None, self.Ax, None)

    def warm_start(self, x: np.ndarray) -> None:
        """Start the next solve's primal iterate at x (the dual keeps its last value)."""
        self._solver.warm_start(x, None)

    def solve(self) -> tuple[bool, str, np.ndarray, int]:
        """Solve: (solved, OSQP's status text, x, iterations); x is a fresh array."""
        s = self._solver
        s.solve()
        info = s.info
        return info.status_val == _SOLVED, info.status, s.solution.x, info.iter
