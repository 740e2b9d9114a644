"""The controller's unicycle model: nominal, learned (with the oracle), and their Jacobians.

State z = (x, y, theta): x North [m], y East [m], theta yaw [rad]. Input u = (V, omega):
forward speed [m/s], yaw rate [rad/s]. Continuous dynamics (paper Eq. 2):
    xdot = V cos(theta), ydot = V sin(theta), thetadot = omega.
Continuous Jacobians (docs/design.md, "Model"; the paper's Eq. 14 misplaces -sin(theta) in B):
    A_c = [[0, 0, -V sin th], [0, 0, V cos th], [0, 0, 0]],
    B_c = [[cos th, 0], [sin th, 0], [0, 1]].

Discretization at period tau uses the midpoint heading phi = theta + tau*omega/2, exact on straight
lines and second-order accurate in turns:
    x+ = x + tau V cos(phi),  y+ = y + tau V sin(phi),  theta+ = theta + tau omega.

The learned model adds the oracle O(z, u; beta) = F(beta) z + H(beta) u + d(beta) of paper Eq. 5 in
its nonlinear form, with beta = (a_V, a_w, d_x, d_y): speed effectiveness, yaw-rate
effectiveness and a drift (wind) in the world frame [m/s]:
    x+ = x + tau (a_V V cos(phi~) + d_x),  y+ = y + tau (a_V V sin(phi~) + d_y),
    theta+ = theta + tau a_w omega,  phi~ = theta + tau a_w omega / 2.
The nominal model is the learned model at beta = NOMINAL_BETA.
"""

import math

import numpy as np

__all__ = [
    "NOMINAL_BETA",
    "NOMINAL_BETA_FLOATS",
    "advance",
    "wrap",
    "continuous_jacobians",
    "linearize",
    "oracle",
    "rollout",
    "step",
    "step_jacobians",
    "step_with_jacobians",
    "unwrap",
    "wrap_angle",
]

NOMINAL_BETA = np.array([1.0, 1.0, 0.0, 0.0])
"""beta of the nominal model: unit effectiveness, no drift."""

NOMINAL_BETA_FLOATS = (1.0, 1.0, 0.0, 0.0)
"""NOMINAL_BETA as plain floats (for `advance`)."""

_EYE3 = np.eye(3)


def _floats(a: np.ndarray | tuple[float, ...]) -> list[float]:
    """The entries of a short vector as Python floats."""
    return np.asarray(a, float).tolist()  # (dtype by position: numpy parses keywords slowly)


def wrap(angle_rad: float) -> float:
    """One angle wrapped to [-pi, pi), as a float."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Angles (an array) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def advance(
    x: float,
    y: float,
    th: float,
    v: float,
    w: float,
    beta: tuple[float, float, float, float] | list[float],
    tau: float,
) -> tuple[float, float, float]:
    """One step of the learned model in plain floats: the unicycle step every rollout uses."""
    a_v, a_w, d_x, d_y = beta
    phi = th + 0.5 * tau * a_w * w
    return (
        x + tau * (a_v * v * math.cos(phi) + d_x),
        y + tau * (a_v * v * math.sin(phi) + d_y),
        th + tau * a_w * w,
    )


def continuous_jacobians(z: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_c = df/dz (3x3) and B_c = df/du (3x2) of the continuous unicycle at (z, u)."""
    th, v = z[2], u[0]
    s, c = np.sin(th), np.cos(th)
    A = np.array([[0.0, 0.0, -v * s], [0.0, 0.0, v * c], [0.0, 0.0, 0.0]])
    B = np.array([[c, 0.0], [s, 0.0], [0.0, 1.0]])
    return A, B


def step(z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """One discrete step of the learned model; beta = NOMINAL_BETA gives the nominal model.

    Broadcasts over leading axes: z (..., 3), u (..., 2), returns (..., 3).
    """
    if np.ndim(z) == 1 and np.ndim(u) == 1:
        return np.array(advance(*_floats(z), *_floats(u), _floats(beta), tau))
    a_v, a_w, d_x, d_y = (float(b) for b in beta)
    v, w = u[..., 0], u[..., 1]
    phi = z[..., 2] + 0.5 * tau * a_w * w
    out = np.empty(np.broadcast_shapes(np.shape(z), np.shape(v) + (3,)))
    out[..., 0] = z[..., 0] + tau * (a_v * v * np.cos(phi) + d_x)
    out[..., 1] = z[..., 1] + tau * (a_v * v * np.sin(phi) + d_y)
    out[..., 2] = z[..., 2] + tau * a_w * w
    return out


def oracle(z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """O(z, u; beta): what the learned model adds to the nominal one over one step (paper Eq. 6)."""
    return step(z, u, beta, tau) - step(z, u, NOMINAL_BETA, tau)


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


def step_with_jacobians(
    z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`step` and the Jacobians w.r.t. z (3, 3) and beta (3, 4) at one point, in plain floats.

    The same numbers as `step` and `step_jacobians` (same operations in the same order), for the
    DEKF's once-per-period call, where a dozen numpy calls on 3-vectors cost more than the maths.
    """
    a_v, a_w, d_x, d_y = _floats(beta)
    x, y, th = _floats(z)
    v, w = _floats(u)
    phi = th + 0.5 * tau * a_w * w
    s, c = math.sin(phi), math.cos(phi)
    dx_dth, dy_dth = -tau * a_v * v * s, tau * a_v * v * c
    half_w = 0.5 * tau * w
    z_next = np.array(advance(x, y, th, v, w, (a_v, a_w, d_x, d_y), tau))
    A = _EYE3.copy()
    A[0, 2], A[1, 2] = dx_dth, dy_dth
    G = np.array(
        (
            tau * v * c, dx_dth * half_w, tau, 0.0,
            tau * v * s, dy_dth * half_w, 0.0, tau,
            0.0, tau * w, 0.0, 0.0,
        )
    ).reshape(3, 4)  # fmt: skip
    return z_next, A, G


def linearize(
    z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Affine model z+ ~= A z + B u + e around the points (z_j, u_j) of a trajectory.

    z (M, 3), u (M, 2) -> A (M, 3, 3), B (M, 3, 2), e (M, 3). The affine term has a closed form:
    the speed terms cancel, leaving e = (tau d_x - dx/dth phi, tau d_y - dy/dth phi, 0).
    """
    a_v, a_w, d_x, d_y = (float(b) for b in beta)
    v, w = u[:, 0], u[:, 1]
    phi = z[:, 2] + 0.5 * tau * a_w * w
    s, c = np.sin(phi), np.cos(phi)
    m = v.shape[0]
    tv = tau * a_v
    dx_dth, dy_dth = -tv * v * s, tv * v * c
    A = np.zeros((m, 3, 3))
    A[:, 0, 0] = A[:, 1, 1] = A[:, 2, 2] = 1.0
    A[:, 0, 2], A[:, 1, 2] = dx_dth, dy_dth
    half = 0.5 * tau * a_w
    B = np.zeros((m, 3, 2))
    B[:, 0, 0], B[:, 1, 0] = tv * c, tv * s
    B[:, 0, 1], B[:, 1, 1], B[:, 2, 1] = dx_dth * half, dy_dth * half, tau * a_w
    e = np.zeros((m, 3))
    e[:, 0] = tau * d_x - dx_dth * phi
    e[:, 1] = tau * d_y - dy_dth * phi
    return A, B, e


def rollout(z0: np.ndarray, inputs: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """States (M + 1, 3) of the nonlinear model from z0 under inputs (M, 2).

    A plain-float loop: for a handful of steps it is several times faster than numpy calls.
    """
    b = _floats(beta)
    z = tuple(_floats(z0))
    out = [z]
    for v, w in np.asarray(inputs, dtype=float).tolist():
        z = advance(*z, v, w, b, tau)
        out.append(z)
    return np.array(out)


def unwrap(angles: np.ndarray) -> np.ndarray:
    """Remove 2 pi jumps along the first axis of a 1-D array of angles (like np.unwrap)."""
    a = np.asarray(angles, dtype=float)
    if a.size < 2:
        return a.copy()
    d = wrap_angle(np.diff(a))
    out = np.empty_like(a)
    out[0] = a[0]
    np.cumsum(d, out=out[1:])
    out[1:] += a[0]
    return out
