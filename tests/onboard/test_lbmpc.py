import cvxpy as cp
import numpy as np
import pytest
from model_oracles import linearize

from fleetmpc.bench.step import _input_bounds
from fleetmpc.onboard.core.condensed_qp import QpData
from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.unicycle import NOMINAL_BETA, rollout

SETTINGS = ControllerSettings(reference_speed_m_s=1.4, solver_eps=1e-8, solver_max_iter=20000)


def _random_data(rng: np.random.Generator, mpc: TubeLbmpc, *, separation: bool = True) -> QpData:
    M, N = mpc.M, mpc.n_neighbours
    z0 = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
    lin_u = np.column_stack([rng.uniform(0.3, 1.8, M), rng.uniform(-0.4, 0.4, M)])
    beta = np.array([rng.uniform(0.8, 1.2), rng.uniform(0.8, 1.2), *rng.uniform(-0.3, 0.3, 2)])
    lin_z = rollout(z0, lin_u, beta, mpc.tau)
    u_s = lin_u + 0.1 * rng.standard_normal((M, 2))
    targets = lin_z[1:] + np.column_stack([rng.normal(0, 1.0, (M, 2)), rng.normal(0, 0.2, M)])
    # Half-planes 1-3 m beside the linearization path, facing it.
    angle = rng.uniform(-np.pi, np.pi, (N, 1))
    normals = np.concatenate([np.cos(angle), np.sin(angle)], axis=1)  # (N, 2)
    offsets = rng.uniform(1.0, 3.0, (N, 1))
    bounds = lin_z[None, 1:, :2] @ normals[:, :, None]  # (N, M, 1)
    bounds = bounds[..., 0] - offsets if separation else np.full((N, M), np.inf)
    planes = np.concatenate([np.repeat(normals[:, None, :], M, axis=1), bounds[..., None]], axis=2)
    return QpData(
        z0=z0,
        lin_states=lin_z,
        lin_inputs=lin_u,
        beta=beta,
        u_s=u_s,
        targets=targets,
        position_weights=np.full(M, 6.0),
        terminal_scale=1.0,
        separation_planes=planes,
        speed_now_m_s=float(lin_u[0, 0]),
        yaw_rate_now_rad_s=float(lin_u[0, 1]),
    )


def _reference_solution(mpc: TubeLbmpc, d: QpData) -> np.ndarray:
    """The same QP written out independently in cvxpy and solved by Clarabel."""
    M = mpc.M
    Sz, sz, St, st, Hu = mpc.problem.condense(d)
    c = cp.Variable(2 * M)
    cost = 0
    for j in range(1, M + 1):
        z = St[j] @ c + st[j]
        err = z - d.targets[j - 1]
        if j < M:
            Q = np.diag([d.position_weights[j - 1]] * 2 + [SETTINGS.q_heading])
        else:
            Q = d.terminal_scale * mpc.terminal_weight(float(d.targets[-1, 2]))
        cost += cp.quad_form(err, Q)
    cons = []
    step, speed, yaw_rate = (
        SETTINGS.speed_rate_max_m_s2 * mpc.tau,
        d.speed_now_m_s,
        d.yaw_rate_now_rad_s,
    )
    for j in range(M):
        u = Hu[j] @ c + d.u_s[j]
        cost += cp.quad_form(u - d.u_s[j], np.diag([SETTINGS.r_speed, SETTINGS.r_yaw_rate]))
        cost += SETTINGS.r_yaw_rate_change * cp.square(u[1] - yaw_rate)
        lower, upper = _input_bounds(mpc, d, j)
        cons += [u <= upper, u >= lower, cp.abs(u[0] - speed) <= step]
        speed, yaw_rate = u[0], u[1]
    for k in range(mpc.n_neighbours):
        for j in range(1, M + 1):
            nx, ny, b = d.separation_planes[k, j - 1]
            if np.isfinite(b):
                cons.append(np.array([nx, ny]) @ (St[j, :2] @ c + st[j, :2]) >= b)
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver=cp.CLARABEL)
    assert prob.status == cp.OPTIMAL
    return np.asarray(c.value).reshape(M, 2)


@pytest.mark.parametrize("seed", range(12))
def test_osqp_matches_an_independent_solver(seed):
    rng = np.random.default_rng(seed)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    for _ in range(3):  # several periods on one solver object: update + warm start
        d = _random_data(rng, mpc, separation=bool(seed % 2))
        sol = mpc.solve(d)
        assert sol.ok, sol.status
        np.testing.assert_allclose(sol.c, _reference_solution(mpc, d), atol=1e-3)


def test_zero_c_reproduces_the_steady_inputs():
    rng = np.random.default_rng(0)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    d = _random_data(rng, mpc)
    Sz, sz, St, st, Hu = mpc.problem.condense(d)
    nominal = rollout(d.z0, d.u_s, np.array([1.0, 1.0, 0.0, 0.0]), mpc.tau)
    # With c = 0 the inputs are u_s exactly and the nominal prediction is close to u_s's rollout.
    np.testing.assert_allclose(Hu @ np.zeros(2 * mpc.M) + d.u_s, d.u_s)
    np.testing.assert_allclose(sz, nominal, atol=0.05)


def test_nan_data_gives_a_checked_failure_not_a_nan_input():
    rng = np.random.default_rng(1)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    d = _random_data(rng, mpc)
    bad = QpData(**{**d.__dict__, "targets": np.full_like(d.targets, np.nan)})
    sol = mpc.solve(bad)
    assert not sol.ok
    # A good period afterwards still solves (the solver object is not poisoned).
    assert mpc.solve(_random_data(rng, mpc)).ok


def test_infeasible_separation_gives_failure_and_fallback_stays_in_u():
    rng = np.random.default_rng(2)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    d = _random_data(rng, mpc)
    # Two half-planes facing each other, 50 m apart across the vehicle's path: no plan fits.
    planes = np.zeros((2, mpc.M, 3))
    planes[0, :, :2], planes[0, :, 2] = (1.0, 0.0), d.lin_states[1:, 0] + 25.0
    planes[1, :, :2], planes[1, :, 2] = (-1.0, 0.0), -(d.lin_states[1:, 0] + 25.0) + 50.0
    bad = QpData(**{**d.__dict__, "separation_planes": planes})
    sol = mpc.solve(bad)
    assert not sol.ok
    assert np.all(np.isfinite(sol.inputs))
    u = mpc.fallback_input(d.z0, np.array([1e3, -1e3, 3.0]), np.array([5.0, 2.0]))
    assert np.all(u <= mpc.box.upper) and np.all(u >= mpc.box.lower)
    u = mpc.fallback_input(d.z0, np.array([np.nan, 0.0, 0.0]), np.array([0.5, 0.0]))
    assert np.all(np.isfinite(u)) and np.all(u <= mpc.box.upper) and np.all(u >= mpc.box.lower)


def test_the_plan_flies_forward_keeps_the_yaw_rate_trust_region_and_its_speed_rate():
    rng = np.random.default_rng(4)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    for _ in range(5):
        d = _random_data(rng, mpc)
        # Steady inputs that ask for flying backwards and turning hard the other way.
        u_s = np.column_stack([np.full(mpc.M, -1.0), -np.sign(d.lin_inputs[:, 1]) * 0.5])
        sol = mpc.solve(QpData(**{**d.__dict__, "u_s": u_s}))
        assert sol.ok, sol.status
        assert np.all(sol.inputs[:, 0] >= -1e-6)
        trust = [SETTINGS.yaw_rate_trust(v) for v in d.lin_inputs[:, 0]]
        np.testing.assert_array_less(
            np.abs(sol.inputs[:, 1] - d.lin_inputs[:, 1]), np.array(trust) + 1e-5
        )
        speeds = np.concatenate([[d.speed_now_m_s], sol.inputs[:, 0]])
        step = SETTINGS.speed_rate_max_m_s2 * mpc.tau
        np.testing.assert_array_less(np.abs(np.diff(speeds)), step + 1e-5)


def test_the_trust_region_is_wider_about_a_slow_linearization():
    """The linearized position's error from a heading dth off the linearization's grows as
    v dth^2: at a quarter of the reference speed the yaw rate may go twice as far from it. A
    vehicle holding station in a wind it does not know, linearized at 0.3 m/s while it barely
    moves, had its yaw rate held 0.25 rad/s from seeds that turned opposite ways, one period
    after the other (5 yaw-rate reversals per vehicle-minute)."""
    v_ref = SETTINGS.reference_speed_m_s
    assert SETTINGS.yaw_rate_trust(v_ref) == pytest.approx(SETTINGS.yaw_rate_trust_rad_s)
    assert SETTINGS.yaw_rate_trust(v_ref / 4) == pytest.approx(2 * SETTINGS.yaw_rate_trust_rad_s)
    assert SETTINGS.yaw_rate_trust(2 * v_ref) < SETTINGS.yaw_rate_trust_rad_s
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    d = _random_data(np.random.default_rng(5), mpc, separation=False)
    lin_u = np.column_stack([np.full(mpc.M, 0.3), np.full(mpc.M, 0.4)])
    # Steady inputs that turn hard the other way: the plan turns as far as the region lets it.
    u_s = np.column_stack([np.full(mpc.M, 0.3), np.full(mpc.M, -0.5)])
    lin_z = rollout(d.z0, lin_u, d.beta, mpc.tau)
    d = QpData(**{**d.__dict__, "lin_inputs": lin_u, "lin_states": lin_z, "u_s": u_s})
    sol = mpc.solve(d)
    assert sol.ok, sol.status
    w = sol.inputs[:, 1]
    assert w.min() < 0.4 - SETTINGS.yaw_rate_trust_rad_s - 0.05  # beyond the old region
    assert np.all(w >= 0.4 - SETTINGS.yaw_rate_trust(0.3) - 1e-5)


def test_terminal_weight_is_the_rotated_dare_solution():
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    for yaw in np.linspace(-4.0, 4.0, 9):
        c, s = np.cos(yaw), np.sin(yaw)
        T = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(mpc.terminal_weight(yaw), T @ mpc.P0 @ T.T, atol=1e-12)


def test_condensed_maps_match_the_linearized_closed_loop():
    """Sz, St, Hu against a step-by-step simulation of both linearized models for a random c."""
    rng = np.random.default_rng(3)
    mpc = TubeLbmpc(SETTINGS, n_neighbours=2)
    d = _random_data(rng, mpc)
    Sz, sz, St, st, Hu = mpc.problem.condense(d)
    c = rng.normal(0.0, 0.3, 2 * mpc.M)
    zbar, ztil = d.z0.copy(), d.z0.copy()
    zref = d.z0.copy()
    for j in range(mpc.M):
        A, B, e = linearize(d.lin_states[j : j + 1], d.lin_inputs[j : j + 1], NOMINAL_BETA, mpc.tau)
        At, Bt, et = linearize(d.lin_states[j : j + 1], d.lin_inputs[j : j + 1], d.beta, mpc.tau)
        u = mpc.feedback_gain(d.lin_states[j, 2]) @ (zbar - zref) + d.u_s[j] + c[2 * j : 2 * j + 2]
        np.testing.assert_allclose(Hu[j] @ c + d.u_s[j], u, atol=1e-12)
        zbar = A[0] @ zbar + B[0] @ u + e[0]
        ztil = At[0] @ ztil + Bt[0] @ u + et[0]
        zref = A[0] @ zref + B[0] @ d.u_s[j] + e[0]
        np.testing.assert_allclose(Sz[j + 1] @ c + sz[j + 1], zbar, atol=1e-12)
        np.testing.assert_allclose(St[j + 1] @ c + st[j + 1], ztil, atol=1e-12)
