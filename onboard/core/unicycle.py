"""The controller's unicycle model: the learned step, its one linearization, and angle wrapping.

State z = (x, y, theta): x North [m], y East [m], theta yaw [rad]. Input u = (V, omega):
forward speed [m/s], yaw rate [rad/s]. Continuous dynamics (paper Eq. 2):
    xdot = V cos(theta), ydot = V sin(theta), thetadot = omega.
(docs/design.md, "Model": the paper's Eq. 14 misplaces -sin(theta) in B.)

Discretization at period tau uses the midpoint heading phi = theta + tau*omega/2, exact on straight
lines and second-order accurate in turns. The learned model adds the oracle
O(z, u; beta) = F(beta) z + H(beta) u + d(beta) of paper Eq. 5 in its nonlinear form, with
beta = (a_V, a_w, d_x, d_y): speed effectiveness, yaw-rate effectiveness and a drift (wind) in the
world frame [m/s]:
    x+ = x + tau (a_V V cos(phi) + d_x),  y+ = y + tau (a_V V sin(phi) + d_y),
    theta+ = theta + tau a_w omega,  phi = theta + tau a_w omega / 2.
The nominal model is the learned model at beta = NOMINAL_BETA.

Its Jacobians at (z, u), the one linearization every user reads (`linearization`):
    A = I + (dx/dth, dy/dth, 0) e3',  dx/dth = -tau a_V V sin phi,  dy/dth = tau a_V V cos phi,
    B = [[tau a_V cos phi, dx/dth tau a_w / 2], [tau a_V sin phi, dy/dth tau a_w / 2],
         [0, tau a_w]],
and the affine term of z+ ~= A z + B u + e is e = (tau d_x - dx/dth phi, tau d_y - dy/dth phi, 0).
Plain floats throughout: the model is evaluated a handful of times per period.
"""

import math

import numpy as np

__all__ = [
    "NOMINAL_BETA",
    "Linearization",
    "advance",
    "linearization",
    "rollout",
    "step_with_jacobians",
    "wrap",
]

NOMINAL_BETA = (1.0, 1.0, 0.0, 0.0)
"""beta of the nominal model: unit effectiveness, no drift."""

Linearization = tuple[float, float, float, float, float, float, float, float, float, float]
"""(phi, sin phi, cos phi, dx/dth, dy/dth, B00, B01, B10, B11, B21) of `linearization`."""


def wrap(angle_rad: float | np.ndarray) -> float | np.ndarray:
    """Angles wrapped to [-pi, pi): a float for a float, an array for an array."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


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


def linearization(
    th: float, v: float, w: float, a_v: float, a_w: float, tau: float
) -> Linearization:
    """The step's Jacobians at heading th and input (v, w) of a model of effectiveness (a_v,
    a_w) (module docstring): the midpoint heading phi with its sine and cosine, A's heading
    column (dx/dth, dy/dth) and B's varying entries, row-major (B20 is 0)."""
    half = 0.5 * tau * a_w
    phi = th + half * w
    s, c = math.sin(phi), math.cos(phi)
    tv = tau * a_v
    dx, dy = -tv * v * s, tv * v * c
    return phi, s, c, dx, dy, tv * c, dx * half, tv * s, dy * half, tau * a_w


def step_with_jacobians(
    z: np.ndarray, u: np.ndarray, beta: np.ndarray, tau: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The learned step and its Jacobians w.r.t. z (3, 3) and beta (3, 4) at one point (the
    DEKF's prediction)."""
    a_v, a_w, d_x, d_y = np.asarray(beta, float).tolist()
    x, y, th = np.asarray(z, float).tolist()
    v, w = np.asarray(u, float).tolist()
    _, s, c, dx_dth, dy_dth, *_ = linearization(th, v, w, a_v, a_w, tau)
    half_w = 0.5 * tau * w
    z_next = np.array(advance(x, y, th, v, w, (a_v, a_w, d_x, d_y), tau))
    A = np.eye(3)
    A[0, 2], A[1, 2] = dx_dth, dy_dth
    G = np.array(
        (
            tau * v * c, dx_dth * half_w, tau, 0.0,
            tau * v * s, dy_dth * half_w, 0.0, tau,
            0.0, tau * w, 0.0, 0.0,
        )
    ).reshape(3, 4)  # fmt: skip
    return z_next, A, G


def rollout(z0: np.ndarray, inputs: np.ndarray, beta: np.ndarray, tau: float) -> np.ndarray:
    """States (M + 1, 3) of the learned model from z0 under inputs (M, 2)."""
    b = np.asarray(beta, float).tolist()
    z = tuple(np.asarray(z0, float).tolist())
    out = [z]
    for v, w in np.asarray(inputs, dtype=float).tolist():
        z = advance(*z, v, w, b, tau)
        out.append(z)
    return np.array(out)
