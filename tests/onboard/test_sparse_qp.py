"""FixedPatternQp against OSQP's private binding (`osqp.ext_builtin`), which it calls directly:
a test that fails, saying what to do, when an OSQP release drops the binding or changes it."""

import importlib
from importlib.metadata import version

import numpy as np
import pytest

BINDING_CALLS = (
    "OSQP_INFTY, OSQPSettings(), osqp_set_default_settings(settings), CSC(matrix), "
    "OSQPSolver(P, q, A, l, u, m, n, settings), update_data_vec(q, l, u), "
    "update_data_mat(Px, None, Ax, None), warm_start(x, None), solve(), "
    "info.status_val / .status / .iter, solution.x"
)


def _fail(error: BaseException) -> None:
    pytest.fail(
        f"osqp {version('osqp')}: its private binding osqp.ext_builtin no longer takes the calls "
        f"fleetmpc.onboard.core.sparse_qp makes ({BINDING_CALLS}): {error!r}. Keep osqp below "
        "this release in pyproject.toml, or move FixedPatternQp to osqp.OSQP's public API.",
        pytrace=False,
    )


def test_the_private_osqp_binding_takes_our_calls_and_solves():
    """minimize 1/2 |x|^2 - x_0 - 2 x_1 subject to x_0 + x_1 <= 1 and x_0 >= 0.25: the answer
    is (0.25, 0.75); solved again after an update of q (then (1, 0)) and a warm start."""
    try:
        sparse_qp = importlib.import_module("fleetmpc.onboard.core.sparse_qp")
        qp = sparse_qp.FixedPatternQp(
            np.triu(np.ones((2, 2), dtype=bool)),
            np.array([[True, True], [True, False]]),
            eps=1e-9,
            max_iter=10000,
        )
        qp.Px[:] = [1.0, 0.0, 1.0]  # P = I, upper triangle by columns: (0,0), (0,1), (1,1)
        qp.Ax[:] = [1.0, 1.0, 1.0]  # A = [[1, 1], [1, 0]] by columns: (0,0), (1,0), (0,1)
        qp.q[:] = [-1.0, -2.0]
        qp.l[:] = [-sparse_qp.INFINITY, 0.25]
        qp.u[:] = [1.0, sparse_qp.INFINITY]
        qp.update()
        first = qp.solve()
        qp.q[:] = [-2.0, -1.0]  # now (1, 0)
        qp.update()
        qp.warm_start(np.array(first[2]))
        second = qp.solve()
    except (ImportError, AttributeError, TypeError, RuntimeError) as error:
        _fail(error)
    for (ok, status, x, iterations), want in zip(
        (first, second), ([0.25, 0.75], [1.0, 0.0]), strict=True
    ):
        assert ok, status
        assert iterations > 0
        np.testing.assert_allclose(x, want, atol=1e-6)
