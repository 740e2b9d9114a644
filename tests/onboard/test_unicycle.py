import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from model_oracles import (
    continuous_jacobians,
    linearize,
    oracle,
    step,
    step_jacobians,
)

from fleetmpc.onboard.core.unicycle import (
    NOMINAL_BETA,
    linearization,
    rollout,
    step_with_jacobians,
    wrap,
)

finite = st.floats(-5, 5, allow_nan=False)
states = st.tuples(finite, finite, st.floats(-4, 4)).map(np.array)
inputs = st.tuples(st.floats(-2, 2), st.floats(-0.5, 0.5)).map(np.array)
betas = st.tuples(st.floats(0.5, 1.5), st.floats(0.5, 1.5), st.floats(-1, 1), st.floats(-1, 1)).map(
    np.array
)


def _fd(f, x, h=1e-6):
    cols = []
    for i in range(len(x)):
        e = np.zeros(len(x))
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2 * h))
    return np.column_stack(cols)


@given(states, inputs)
def test_continuous_jacobians_match_finite_differences(z, u):
    def f(z, u):
        return np.array([u[0] * np.cos(z[2]), u[0] * np.sin(z[2]), u[1]])

    A, B = continuous_jacobians(z, u)
    np.testing.assert_allclose(A, _fd(lambda x: f(x, u), z), atol=1e-6)
    np.testing.assert_allclose(B, _fd(lambda x: f(z, x), u), atol=1e-6)


def test_continuous_b_matrix_is_the_corrected_one():
    # The paper's Eq. 14 prints -sin(theta) in B[1, 1]; the correct B has sin(theta) in B[1, 0].
    _, B = continuous_jacobians(np.array([0.0, 0.0, 0.3]), np.array([1.0, 0.0]))
    np.testing.assert_allclose(B, [[np.cos(0.3), 0], [np.sin(0.3), 0], [0, 1]])


@given(states, inputs, betas)
def test_discrete_jacobians_match_finite_differences(z, u, beta):
    tau = 0.2
    A, B, G = step_jacobians(z, u, beta, tau)
    np.testing.assert_allclose(A, _fd(lambda x: step(x, u, beta, tau), z), atol=1e-6)
    np.testing.assert_allclose(B, _fd(lambda x: step(z, x, beta, tau), u), atol=1e-6)
    np.testing.assert_allclose(G, _fd(lambda x: step(z, u, x, tau), beta), atol=1e-6)


@given(states, inputs, betas)
def test_float_step_with_jacobians_is_step_and_its_jacobians_exactly(z, u, beta):
    z_next, A, G = step_with_jacobians(z, u, beta, 0.2)
    A2, _, G2 = step_jacobians(z, u, beta, 0.2)
    np.testing.assert_array_equal(z_next, step(z, u, beta, 0.2))
    np.testing.assert_array_equal(A, A2)
    np.testing.assert_array_equal(G, G2)


@settings(max_examples=50)
@given(st.lists(st.tuples(states, inputs), min_size=1, max_size=6), betas)
def test_linearization_is_exact_at_its_points(points, beta):
    z = np.array([p[0] for p in points])
    u = np.array([p[1] for p in points])
    A, B, e = linearize(z, u, beta, 0.2)
    affine = np.einsum("mij,mj->mi", A, z) + np.einsum("mij,mj->mi", B, u) + e
    np.testing.assert_allclose(affine, step(z, u, beta, 0.2), atol=1e-12)
    A2, B2, _ = step_jacobians(z, u, beta, 0.2)
    np.testing.assert_allclose(A, A2, atol=1e-15)
    np.testing.assert_allclose(B, B2, atol=1e-15)


def test_straight_flight_is_exact_and_oracle_is_the_model_difference():
    z0 = np.array([1.0, 2.0, 0.4])
    u = np.tile([1.5, 0.0], (10, 1))
    traj = rollout(z0, u, NOMINAL_BETA, 0.2)
    np.testing.assert_allclose(
        traj[-1, :2], z0[:2] + 1.5 * 2.0 * np.array([np.cos(0.4), np.sin(0.4)])
    )
    beta = np.array([0.8, 1.2, 0.3, -0.2])
    o = oracle(z0, u[0], beta, 0.2)
    np.testing.assert_allclose(
        o[:2], 0.2 * (-0.2 * 1.5 * np.array([np.cos(0.4), np.sin(0.4)]) + [0.3, -0.2])
    )


@given(st.floats(-100, 100))
def test_wrap_range_and_equivalence(a):
    w = wrap(a)
    assert -np.pi <= w < np.pi
    assert abs(np.sin(w) - np.sin(a)) < 1e-9 and abs(np.cos(w) - np.cos(a)) < 1e-9


@given(states, inputs, betas)
def test_the_one_linearization_is_the_array_jacobians_exactly(z, u, beta):
    phi, s, c, dx, dy, b00, b01, b10, b11, b21 = linearization(
        float(z[2]), float(u[0]), float(u[1]), float(beta[0]), float(beta[1]), 0.2
    )
    A, B, _ = step_jacobians(z, u, beta, 0.2)
    assert (s, c) == (np.sin(phi), np.cos(phi))
    np.testing.assert_array_equal(A[:2, 2], [dx, dy])
    np.testing.assert_array_equal(B, [[b00, b01], [b10, b11], [0.0, b21]])
