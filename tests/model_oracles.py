"""Independent array forms of the controller's model and tube, for the tests to check the
product's float forms against (`fleetmpc.onboard.core.unicycle`, `fleetmpc.onboard.core.tube`).

Importable from any test module as ``model_oracles`` (the tests folder is on the import path
through its conftest).
"""

import numpy as np

__all__ = [
    "continuous_jacobians",
    "heading_rotation",
    "input_tightening",
    "linearize",
    "oracle",
    "step",
    "step_jacobians",
    "tube_vertices_support",
]

NOMINAL = np.array([1.0, 1.0, 0.0, 0.0])


def continuous_jacobians(z: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_c = df/dz (3x3) and B_c = df/du (3x2) of the continuous unicycle at (z, u)."""
    th, v = z[2], u[0]
    s, c = np.sin(th), np.cos(th)
    A = np.array([[0.0, 0.0, -v * s], [0.0, 0.0, v * c], [0.0, 0.0, 0.0]])
    B = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
    return A, B


def step(z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """One discrete step of the learned model, broadcast over leading axes: z (..., 3),
    u (..., 2) -> (..., 3)."""
    a_v, a_w, d_x, d_y = (float(b) for b in beta)
    z, u = np.asarray(z, float), np.asarray(u, float)
    v, w = u[..., 0], u[..., 1]
    phi = z[..., 2] + 0.5 * tau * a_w * w
    out = np.empty(np.broadcast_shapes(np.shape(z), np.shape(v) + (3,)))
    out[..., 0] = z[..., 0] + tau * (a_v * v * np.cos(phi) + d_x)
    out[..., 1] = z[..., 1] + tau * (a_v * v * np.sin(phi) + d_y)
    out[..., 2] = z[..., 2] + tau * a_w * w
    return out


def oracle(z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """O(z, u; beta): what the learned model adds to the nominal one over one step (paper Eq. 6)."""
    return step(z, u, beta, tau) - step(z, u, NOMINAL, tau)


def step_jacobians(
    z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians of `step` w.r.t. z (..., 3, 3), u (..., 3, 2) and beta (..., 3, 4)."""
    a_v, a_w = float(beta[0]), float(beta[1])
    v, w = np.asarray(u)[..., 0], np.asarray(u)[..., 1]
    phi = np.asarray(z)[..., 2] + 0.5 * tau * a_w * w
    s, c = np.sin(phi), np.cos(phi)
    lead = np.shape(v)
    dx_dth, dy_dth = -tau * a_v * v * s, tau * a_v * v * c
    A = np.zeros(lead + (3, 3))
    A[..., 0, 0] = A[..., 1, 1] = A[..., 2, 2] = 1.0
    A[..., 0, 2], A[..., 1, 2] = dx_dth, dy_dth
    half = 0.5 * tau * a_w
    B = np.zeros(lead + (3, 2))
    B[..., 0, 0], B[..., 1, 0] = tau * a_v * c, tau * a_v * s
    B[..., 0, 1], B[..., 1, 1], B[..., 2, 1] = dx_dth * half, dy_dth * half, tau * a_w
    half_w = 0.5 * tau * w
    G = np.zeros(lead + (3, 4))
    G[..., 0, 0], G[..., 1, 0] = tau * v * c, tau * v * s
    G[..., 0, 1], G[..., 1, 1], G[..., 2, 1] = dx_dth * half_w, dy_dth * half_w, tau * w
    G[..., 0, 2] = G[..., 1, 3] = tau
    return A, B, G


def linearize(
    z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Affine model z+ ~= A z + B u + e around the points (z_j, u_j) of a trajectory:
    z (M, 3), u (M, 2) -> A (M, 3, 3), B (M, 3, 2), e (M, 3). The affine term in closed form:
    the speed terms cancel, leaving e = (tau d_x - dx/dth phi, tau d_y - dy/dth phi, 0)."""
    a_v, a_w, d_x, d_y = (float(b) for b in beta)
    A, B, _ = step_jacobians(z, u, beta, tau)
    phi = np.asarray(z)[:, 2] + 0.5 * tau * a_w * np.asarray(u)[:, 1]
    e = np.zeros((len(phi), 3))
    e[:, 0] = tau * d_x - A[:, 0, 2] * phi
    e[:, 1] = tau * d_y - A[:, 1, 2] * phi
    return A, B, e


def heading_rotation(yaw: float) -> np.ndarray:
    """T(yaw) = blockdiag(Rot(yaw), 1), 3x3."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def input_tightening(
    A: np.ndarray, B: np.ndarray, K: np.ndarray, w_bar: np.ndarray, horizon: int
) -> np.ndarray:
    """Margins (horizon, m) at one heading: margin[j, i] = sum_{l<j} |e_i' K Phi^l| w_bar,
    Phi = A + BK, for the box W = {|w| <= w_bar}."""
    Phi = A + B @ K
    out = np.zeros((horizon, K.shape[0]))
    M = K.copy()
    for j in range(1, horizon):
        out[j] = out[j - 1] + np.abs(M) @ w_bar
        M = M @ Phi
    return out


def tube_vertices_support(
    A: np.ndarray, B: np.ndarray, K: np.ndarray, w_bar: np.ndarray, j: int, h: np.ndarray
) -> float:
    """Brute-force support of h' K R_j over every vertex combination (small j)."""
    if j == 0:
        return 0.0
    Phi = A + B @ K
    n = A.shape[0]
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * n, indexing="ij")).reshape(n, -1).T * w_bar
    maps = [h @ K @ np.linalg.matrix_power(Phi, l) for l in range(j)]
    idx = np.array(np.meshgrid(*[np.arange(len(corners))] * j, indexing="ij")).reshape(j, -1).T
    return max(
        0.0, *(float(sum(maps[l] @ corners[c] for l, c in enumerate(combo))) for combo in idx)
    )
