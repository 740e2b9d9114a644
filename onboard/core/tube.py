"""Feedback gain and tube of the tube MPC (paper Sec. V-B; docs/design.md, "Controller").

K comes from the standard discrete algebraic Riccati equation
    P = A'PA - A'PB (R + B'PB)^-1 B'PA + Q,  K = -(R + B'PB)^-1 B'PA,
at a cruise linearization (speed > 0: at V = 0 the lateral mode is uncontrollable).
The tube is R_0 = {0}, R_j = sum_{l<j} (A + BK)^l W for a box W; each input bound of the box U is
tightened by the support function of K R_j: sum_{l<j} |h' K (A+BK)^l| w_bar.

Rotation: the unicycle linearized at heading th is the heading-0 one seen through
T(th) = blockdiag(Rot(th), 1): A(th) = T A0 T', B(th) = T B0, so K(th) = K0 T(th)' and
P(th) = T P0 T'. W is a box in the world frame, so the tube depends on heading; the tightening used
online is the maximum over headings.
"""

import numpy as np
import scipy.linalg

from fleetmpc.onboard.core.unicycle import NOMINAL_BETA, step_jacobians

__all__ = [
    "cruise_linearization",
    "dare_gain",
    "heading_rotation",
    "input_tightening",
    "position_tube_radius",
    "robust_input_tightening",
    "tube_vertices_support",
]


def dare_gain(
    A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """K (m x n) and P (n x n) of the infinite-horizon discrete LQR; u = K z stabilizes."""
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    return K, P


def cruise_linearization(speed_m_s: float, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Discrete (A, B) of the nominal model flying straight North at `speed_m_s` (must be > 0)."""
    if not speed_m_s > 0:
        raise ValueError(f"speed_m_s: a linearization point needs speed > 0, got {speed_m_s}")
    A, B, _ = step_jacobians(np.zeros(3), np.array([speed_m_s, 0.0]), NOMINAL_BETA, tau)
    return A, B


def heading_rotation(yaw: float) -> np.ndarray:
    """T(yaw) = blockdiag(Rot(yaw), 1), 3x3."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def input_tightening(
    A: np.ndarray, B: np.ndarray, K: np.ndarray, w_bar: np.ndarray, horizon: int
) -> np.ndarray:
    """Margins (horizon, m): how much each input bound of U shrinks at step j, U ⊖ K R_j.

    margin[j, i] = sum_{l<j} |e_i' K Phi^l| w_bar, Phi = A + BK, for the box W = {|w| <= w_bar}.
    """
    Phi = A + B @ K
    out = np.zeros((horizon, K.shape[0]))
    M = K.copy()
    for j in range(1, horizon):
        out[j] = out[j - 1] + np.abs(M) @ w_bar
        M = M @ Phi
    return out


def robust_input_tightening(
    A0: np.ndarray,
    B0: np.ndarray,
    K0: np.ndarray,
    w_bar: np.ndarray,
    horizon: int,
    *,
    headings: int = 72,
) -> np.ndarray:
    """Largest input tightening over `headings` evenly spaced headings (world-frame box W).

    `input_tightening` at every heading at once: the rotated A, B, K are stacked over headings.
    """
    th = np.linspace(0.0, 2.0 * np.pi, headings, endpoint=False)
    c, s = np.cos(th), np.sin(th)
    T = np.zeros((headings, 3, 3))
    T[:, 0, 0] = T[:, 1, 1] = c
    T[:, 0, 1], T[:, 1, 0] = -s, s
    T[:, 2, 2] = 1.0
    Tt = T.transpose(0, 2, 1)
    K = K0 @ Tt
    Phi = T @ A0 @ Tt + (T @ B0) @ K
    out = np.zeros((headings, horizon, K0.shape[0]))
    KPhi = K
    for j in range(1, horizon):
        out[:, j] = out[:, j - 1] + np.abs(KPhi) @ w_bar
        KPhi = KPhi @ Phi
    return out.max(axis=0)


def position_tube_radius(
    A: np.ndarray, B: np.ndarray, K: np.ndarray, w_bar: np.ndarray, horizon: int
) -> np.ndarray:
    """Radius (horizon + 1,) of a disc containing the position part of R_j, j = 0..horizon.

    Uses sum_{l<j} || |Phi^l_xy| w_bar ||_2, an upper bound of the support in every direction,
    valid at every heading (the bound is rotation invariant for rotated A, B, K).
    """
    Phi = A + B @ K
    out = np.zeros(horizon + 1)
    M = np.eye(A.shape[0])
    for j in range(1, horizon + 1):
        out[j] = out[j - 1] + np.linalg.norm(np.abs(M[:2]) @ w_bar) * np.sqrt(2.0)
        M = Phi @ M
    return out


def tube_vertices_support(
    A: np.ndarray, B: np.ndarray, K: np.ndarray, w_bar: np.ndarray, j: int, h: np.ndarray
) -> float:
    """Brute-force support of h' K R_j over every vertex combination (for tests; small j)."""
    Phi = A + B @ K
    n = A.shape[0]
    corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * n, indexing="ij")).reshape(n, -1).T * w_bar
    best = 0.0
    if j == 0:
        return 0.0
    maps = [h @ K @ np.linalg.matrix_power(Phi, l) for l in range(j)]
    # Sum over l of max over vertices; verify by enumerating all combinations.
    idx = np.array(np.meshgrid(*[np.arange(len(corners))] * j, indexing="ij")).reshape(j, -1).T
    for combo in idx:
        best = max(best, float(sum(maps[l] @ corners[c] for l, c in enumerate(combo))))
    return best
