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

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from fleetmpc.errors import InfeasibleError
from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.unicycle import linearization

__all__ = [
    "InputBox",
    "Tube",
    "cruise_linearization",
    "dare_gain",
    "position_tube_radius",
    "robust_input_tightening",
    "vehicle_tube",
]


@dataclass(frozen=True)
class InputBox:
    """The input set U and its tube-tightened boxes U ⊖ K R_j (docs/design.md, "Input set")."""

    lower: tuple[float, float]
    """U's lower corner (speed [m/s], yaw rate [rad/s]): the vehicle flies forward."""
    upper: tuple[float, float]
    """U's upper corner (speed [m/s], yaw rate [rad/s])."""
    steps: tuple[tuple[float, float, float, float], ...]
    """The tightened box of each step j = 0..M-1: (v_min, w_min, v_max, w_max). The speed's
    lower bound 0 is not tightened: a plan may stop, and a feedback that would take the speed
    below it is clipped there."""

    @classmethod
    def tightened(cls, settings: ControllerSettings, tightening: np.ndarray) -> "InputBox":
        """U of the settings and its boxes shrunk by the tube's margins (M, 2)."""
        u_max = np.array([settings.speed_max_m_s, settings.yaw_rate_max_rad_s])
        u_min = np.array([0.0, -settings.yaw_rate_max_rad_s])
        lower = (u_min[None, :] + tightening * [0.0, 1.0]).tolist()
        upper = (u_max[None, :] - tightening).tolist()
        steps = tuple((*lo, *hi) for lo, hi in zip(lower, upper, strict=True))
        return cls(lower=tuple(u_min.tolist()), upper=tuple(u_max.tolist()), steps=steps)

    def clip(self, u: np.ndarray) -> np.ndarray:
        """Inputs (..., 2) clipped to U."""
        return np.minimum(np.maximum(u, self.lower), self.upper)

    def admits(self, v: float, w: float, *, relative_tolerance: float) -> bool:
        """True when (v, w) lies in U widened by relative_tolerance of its upper bounds (and
        1e-6): a solver's answer may stand that far outside."""
        (v_lo, w_lo), (v_hi, w_hi) = self.lower, self.upper
        slack_v = relative_tolerance * v_hi + 1e-6
        slack_w = relative_tolerance * w_hi + 1e-6
        return v_lo - slack_v <= v <= v_hi + slack_v and w_lo - slack_w <= w <= w_hi + slack_w

    def corners(self) -> list[tuple[float, float]]:
        """Stop, half and full speed, each turning either way at U's yaw-rate bound or not."""
        v_max, w_max = self.upper
        return [(v, w) for v in (0.0, 0.5 * v_max, v_max) for w in (-w_max, 0.0, w_max)]

    @property
    def last(self) -> tuple[float, float]:
        """The tightened upper bounds (speed, yaw rate) of the last step."""
        return self.steps[-1][2], self.steps[-1][3]


@dataclass(frozen=True, eq=False)
class Tube:
    """The tube of one vehicle's MPC: the DARE gain and terminal weight at heading 0, the
    input margins and tightened input set, and the position tube's radius."""

    A0: np.ndarray
    """The nominal model's A at the cruise linearization (3, 3)."""
    B0: np.ndarray
    """Its B (3, 2)."""
    K0: np.ndarray
    """The DARE gain at heading 0 (2, 3)."""
    P0: np.ndarray
    """The DARE solution at heading 0, the terminal weight (3, 3)."""
    tightening: np.ndarray
    """How much each input bound shrinks at step j (M, 2), the maximum over headings."""
    radius_m: np.ndarray
    """Radius of a disc holding the position part of R_j, j = 0..M (M + 1,) [m]."""
    box: InputBox
    """U and its tightened boxes."""


def vehicle_tube(settings: ControllerSettings, *, formation_terms: int) -> Tube:
    """The tube of a vehicle whose stage weight holds `formation_terms` formation terms;
    InfeasibleError, naming the field, when a tightened input set is empty."""
    s, M = settings, settings.horizon
    A0, B0 = cruise_linearization(s.reference_speed_m_s, s.period_s)
    q_pos = s.q_position + formation_terms * s.q_formation
    Q0 = np.diag([q_pos, q_pos, s.q_heading])
    K0, P0 = dare_gain(A0, B0, Q0, np.diag([s.r_speed, s.r_yaw_rate]))
    w_bar = np.array([s.w_position_m, s.w_position_m, s.w_heading_rad])
    tightening = robust_input_tightening(A0, B0, K0, w_bar, M)
    box = InputBox.tightened(s, tightening)
    worst = tightening / np.array(box.upper)
    if np.any(worst >= 1.0):
        j, i = np.unravel_index(int(np.argmax(worst)), worst.shape)
        name = ("speed", "yaw rate")[i]
        raise InfeasibleError(
            "controller.w_position_m",
            f"the tightened input set U ⊖ K R_j is empty: the {name} bound "
            f"{box.upper[i]:g} shrinks by {tightening[j, i]:.3g} at step {j}; "
            "reduce the disturbance box W or the horizon, or raise the input bounds",
        )
    radius_m = position_tube_radius(A0, B0, K0, w_bar, M)
    return Tube(A0=A0, B0=B0, K0=K0, P0=P0, tightening=tightening, radius_m=radius_m, box=box)


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
    _, _, _, dx, dy, b00, b01, b10, b11, b21 = linearization(0.0, speed_m_s, 0.0, 1.0, 1.0, tau)
    A = np.eye(3)
    A[0, 2], A[1, 2] = dx, dy
    return A, np.array([[b00, b01], [b10, b11], [0.0, b21]])


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

    At each heading the margin of step j is sum_{l<j} |e_i' K Phi^l| w_bar, Phi = A + BK (the
    support of K R_j in the box W = {|w| <= w_bar}); the rotated A, B, K are stacked over headings.
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
