import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from model_oracles import heading_rotation, input_tightening, tube_vertices_support

from fleetmpc.errors import InfeasibleError
from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.tube import cruise_linearization, dare_gain


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.integers(1, 3),
)
def test_tightening_matches_brute_force_vertex_enumeration(seed, j):
    rng = np.random.default_rng(seed)
    A = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    B = rng.standard_normal((3, 2))
    K = 0.3 * rng.standard_normal((2, 3))
    w_bar = rng.uniform(0.01, 0.5, 3)
    margins = input_tightening(A, B, K, w_bar, j + 1)
    for i in range(2):
        h = np.eye(2)[i]
        brute = tube_vertices_support(A, B, K, w_bar, j, h)
        assert margins[j, i] == pytest.approx(brute, rel=1e-9, abs=1e-12)
        # The box U is symmetric: the lower bound tightens by the support in -h, the same number.
        assert tube_vertices_support(A, B, K, w_bar, j, -h) == pytest.approx(
            brute, rel=1e-9, abs=1e-12
        )


@settings(max_examples=40, deadline=None)
@given(
    speed=st.floats(0.1, 3.0),
    tau=st.floats(0.05, 0.5),
    q=st.floats(0.1, 100.0),
    qh=st.floats(0.01, 10.0),
    r=st.floats(0.01, 10.0),
    yaw=st.floats(-np.pi, np.pi),
)
def test_dare_gain_stabilizes_at_any_heading(speed, tau, q, qh, r, yaw):
    A0, B0 = cruise_linearization(speed, tau)
    K0, P0 = dare_gain(A0, B0, np.diag([q, q, qh]), np.diag([r, r]))
    T = heading_rotation(yaw)
    A, B, K = T @ A0 @ T.T, T @ B0, K0 @ T.T
    assert max(abs(np.linalg.eigvals(A + B @ K))) < 1.0
    # K0 T' is the DARE gain of the rotated system (rotation invariance used online).
    K_rot, P_rot = dare_gain(A, B, np.diag([q, q, qh]), np.diag([r, r]))
    np.testing.assert_allclose(K_rot, K, atol=1e-6 * (1 + abs(K).max()))
    # P solves the standard DARE, P = A'PA - A'PB (R + B'PB)^-1 B'PA + Q.
    Q, R = np.diag([q, q, qh]), np.diag([r, r])
    rhs = A0.T @ P0 @ A0 - A0.T @ P0 @ B0 @ np.linalg.solve(R + B0.T @ P0 @ B0, B0.T @ P0 @ A0) + Q
    np.testing.assert_allclose(P0, rhs, rtol=1e-6, atol=1e-8)


def test_linearization_at_standstill_is_refused():
    with pytest.raises(ValueError, match="speed"):
        cruise_linearization(0.0, 0.2)


def test_empty_tightened_set_is_a_startup_error_naming_the_field():
    with pytest.raises(InfeasibleError) as err:
        TubeLbmpc(ControllerSettings(w_position_m=2.0, horizon=10), n_neighbours=2)
    assert "controller.w_position_m" in str(err.value)
    assert "empty" in str(err.value)
