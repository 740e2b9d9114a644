"""Dual Extended Kalman Filter (Wan & Nelson) learning the oracle parameters beta.

Two EKFs run side by side (paper Sec. V-A, Eqs. 7-10, with the corrections of docs/design.md,
"Learning": Eq. 7b reads P_p^-(t) = P_p(t-1) + R_p and Eq. 8a propagates from z^(t-1)):
    parameter prediction   theta^- = F theta(t-1),        P_p^- = F P_p(t-1) F' + Q_p
    state prediction       z^-     = f(z^(t-1), u, beta^-), P_s^- = J_s P_s J_s' + Q_s
    state correction       z^      = z^- + K_s (y - z^-)
    parameter correction   theta   = theta^- + K_p (y - z^-), H_p = df/dtheta at (z^(t-1), u),
                           with innovation covariance H_p P_p^- H_p' + P_s^- + R
(the parameter filter's measurement noise is the state prediction's uncertainty plus the sensor's).
The measurement is the full state (H_s = I): position and heading from telemetry; where the
autopilot also reports its ground velocity (every GNSS-aided one does), that velocity is a second
measurement of the parameters alone: v = a_V V (cos th, sin th) + d at the period's end. It sees
the wind within a period, where position sees only its integral.

The wind has two parts in the parameter filter (docs/design.md, "Learning", "The wind's two
parts"): theta = (a_V, a_w, m_x, m_y, g_x, g_y), the drift d = m + g. m is the slow mean (a random
walk); g the gust, a first-order Gauss-Markov process of the site's intensity sigma and time
constant T (F = e^(-tau/T) on it, Q = sigma^2 (1 - e^(-2 tau/T))). A gust is expected to die out,
a change of a_V is not: a change of the velocity that lasts through many gust time constants, in a
direction that turns with the heading, is learned as a_V; the gust takes the rest.

The fleet's wind (docs/design.md, "The fleet's wind"): each period the filter keeps the wind its
ground velocity measured across its heading (`wind_sample`, which the agent puts on its plan),
and takes the neighbours' samples, pooled (`fleet_wind.WindPool`), as one more measurement of
the drift across its own heading, in an update that holds a_V and a_w.

Excitation: a parameter whose Jacobian column is (nearly) zero gets no information from this
measurement, yet a plain update would still move it through its correlation with the others; such
parameters get a zero gain row (a Schmidt "consider" update, Joseph form keeps P consistent), so
a_V stays put while hovering and a_w while flying straight.

Safeguards: beta is clipped to its bounds and the parameter covariance is capped at its initial
value, so beta stays bounded and does not wander when excitation vanishes; a non-finite result or
an innovation beyond the gate resets the state to the measurement (beta is kept if finite) and is
counted.

filterpy's `predict` does the parameters' linear prediction. The corrections are written out:
the parameters' is a consider update over both measurements at once, which filterpy lacks, and
the state's reuses the inverse of its innovation covariance for the gate.
"""

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import predict

from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.onboard.core.fleet_wind import PooledWind
from fleetmpc.onboard.core.unicycle import step_with_jacobians, wrap
from fleetmpc.protocol.plan import WindSample

__all__ = ["DualEkf", "flown_input"]


@dataclass(frozen=True)
class _Noise:
    """The filter's matrices and bounds, over theta (6) where not said otherwise."""

    Q_s: np.ndarray
    R_s: np.ndarray
    F_p: np.ndarray
    Q_p: np.ndarray
    P_p_initial: np.ndarray
    P_p_cap: np.ndarray
    beta_min: tuple[float, ...]
    """Bounds of beta (4)."""
    beta_max: tuple[float, ...]
    gate: float
    learn: bool
    excitation: tuple[float, ...]
    lag_s: float
    speed_excitation_m_s: float
    R_velocity: np.ndarray
    """The ground velocity's measurement noise (2, 2)."""
    velocity_weights: np.ndarray
    """How far the commanded velocity's recent and slow means move per period (2, 1)."""

    @classmethod
    def from_settings(cls, s: LearningSettings, tau: float) -> "_Noise":
        pos, head = (
            (s.process_position_std_m, s.process_heading_std_rad)
            if s.enabled
            else (s.fixed_model_position_std_m, s.fixed_model_heading_std_rad)
        )
        fade = math.exp(-tau / s.gust_time_constant_s) if s.gust_time_constant_s > 0 else 0.0
        gust_var = s.gust_std_m_s**2
        walk = np.square(s.beta_random_walk) * tau
        initial = np.square(s.beta_std_initial)
        return cls(
            Q_s=np.diag([pos**2] * 2 + [head**2]),
            R_s=np.diag([s.measurement_position_std_m**2] * 2 + [s.measurement_heading_std_rad**2]),
            F_p=np.diag([1.0] * 4 + [fade] * 2),
            Q_p=np.diag([*walk, *[gust_var * (1.0 - fade * fade)] * 2]),
            P_p_initial=np.diag([*initial, gust_var, gust_var]),
            P_p_cap=np.array([*initial, gust_var, gust_var]),
            beta_min=s.beta_min,
            beta_max=s.beta_max,
            gate=s.innovation_gate,
            learn=s.enabled,
            excitation=tuple(e * tau for e in s.excitation_min) + (0.0, 0.0),
            lag_s=s.input_lag_s,
            speed_excitation_m_s=s.speed_excitation_m_s,
            R_velocity=np.eye(2) * s.measurement_velocity_std_m_s**2,
            velocity_weights=np.array([[tau / VELOCITY_FAST_S], [tau / VELOCITY_SLOW_S]]),
        )


def beta_of(theta: np.ndarray) -> np.ndarray:
    """beta = (a_V, a_w, d_x, d_y) of the parameters theta, the drift the mean plus the gust."""
    return np.array((theta[0], theta[1], theta[2] + theta[4], theta[3] + theta[5]))


def _with_gust(G: np.ndarray) -> np.ndarray:
    """A Jacobian w.r.t. beta (.., 4) extended to theta (.., 6): d is m + g."""
    return np.concatenate((G, G[:, 2:4]), axis=1)


def _bound(theta: np.ndarray, P_p: np.ndarray, noise: _Noise) -> tuple[np.ndarray, np.ndarray]:
    """theta with beta inside its bounds (the mean moved so that the drift is) and P_p with its
    diagonal capped, symmetrized. (Plain floats: in bounds, the usual case, it costs little.)"""
    a_v, a_w, m_x, m_y, g_x, g_y = theta.tolist()
    beta = (a_v, a_w, m_x + g_x, m_y + g_y)
    bounds = zip(beta, noise.beta_min, noise.beta_max, strict=True)
    if not all(lo <= b <= hi for b, lo, hi in bounds):
        a_v, a_w, d_x, d_y = np.clip(beta, noise.beta_min, noise.beta_max).tolist()
        theta = np.array((a_v, a_w, d_x - g_x, d_y - g_y, g_x, g_y))
    caps = zip(P_p.diagonal().tolist(), noise.P_p_cap.tolist(), strict=True)
    if any(v > cap for v, cap in caps):
        scale = np.sqrt(np.minimum(1.0, noise.P_p_cap / np.maximum(P_p.diagonal(), 1e-300)))
        P_p = P_p * np.outer(scale, scale)
    sym = P_p.T.copy()  # (a contiguous copy: numpy adds a transposed operand slowly)
    sym += P_p
    sym *= 0.5
    return theta, sym


def _unexcited(H_p: np.ndarray, noise: _Noise, velocity_means: np.ndarray) -> list[int]:
    """Parameters whose Jacobian column is too small to learn from, and a_V while the
    commanded velocity has not changed enough for a wind not to mimic it (`velocity_means`,
    its recent and slow means (2, 2))."""
    norms = np.sqrt(np.square(H_p).sum(axis=0)).tolist()
    hold = [
        i for i, (n, floor) in enumerate(zip(norms, noise.excitation, strict=True)) if n < floor
    ]
    (fx, fy), (sx, sy) = velocity_means.tolist()
    if 0 not in hold and math.hypot(fx - sx, fy - sy) < noise.speed_excitation_m_s:
        hold.insert(0, 0)
    return hold


VELOCITY_FAST_S = 1.0
"""The recent mean of the commanded velocity is over about this long [s]."""
VELOCITY_SLOW_S = 5.0
"""Its slow mean, against which a change of the command is measured, over about this long [s]:
about how long the wind a vehicle feels in moderate turbulence takes to change (docs/design.md,
"Wind")."""


def flown_input(
    u: np.ndarray, lag_end: np.ndarray, *, lag_s: float, tau: float
) -> tuple[np.ndarray, np.ndarray]:
    """The input a first-order lag of time constant `lag_s` flies over a period of `tau` from
    `lag_end` (where it stood as the period began) toward the command u: its mean over the
    period, and where it stands at the end."""
    if lag_s <= 0.0:
        return u, u
    fade = math.exp(-tau / lag_s)
    gap = lag_end - u
    return u + gap * (lag_s / tau * (1.0 - fade)), u + gap * fade


def _velocity_means(means: np.ndarray, velocity: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The recent and slow means (2, 2) of the commanded velocity, moved on by one period
    (`_Noise.velocity_weights`)."""
    return means + weights * (velocity - means)


_H_DRIFT = np.array(((0.0, 0.0, 1.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0, 0.0, 1.0)))
"""A measurement of the drift d = m + g w.r.t. theta."""


_EYE3 = np.eye(3)
_EYE6 = np.eye(6)


def _inverse_3x3(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a 3 x 3 innovation covariance: the adjugate over the determinant,
    in plain floats (a third of numpy.linalg.inv's time on a 3 x 3). S is a covariance plus the
    sensor noise, well conditioned, so the cofactors lose nothing to cancellation."""
    (a, b, c), (d, e, f), (g, h, i) = S.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    return np.array(
        (
            A / det, (c * h - b * i) / det, (b * f - c * e) / det,
            B / det, (a * i - c * g) / det, (c * d - a * f) / det,
            C / det, (b * g - a * h) / det, (a * e - b * d) / det,
        )
    ).reshape(3, 3)  # fmt: skip


def _consider_update(
    theta: np.ndarray,
    P: np.ndarray,
    innovation: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    hold: list[int],
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the gain rows of the held parameters zeroed (Joseph form)."""
    PHt = P.dot(H.T)  # (P H' twice: in S and in the gain)
    K = PHt.dot(np.linalg.inv(H.dot(PHt) + R))
    K[hold] = 0.0
    I_K = _EYE6 - K.dot(H)
    return theta + K.dot(innovation), I_K.dot(P).dot(I_K.T) + K.dot(R).dot(K.T)


def _velocity_model(
    theta: np.ndarray, speed: float, heading: float, heading_var: float, noise: _Noise
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ground velocity the parameters predict at the period's end, flying `speed` along
    `heading`: its value (2,), Jacobian w.r.t. theta (2, 6) and noise covariance (2, 2).

    v = a_V V (cos th, sin th) + m + g is linear in theta; the heading's uncertainty enters
    across the course: R_v = sigma_v^2 I + (a_V V)^2 var(th) n n', n = (-sin th, cos th)."""
    c, s = math.cos(heading), math.sin(heading)
    a_v = float(theta[0])
    d_x, d_y = float(theta[2] + theta[4]), float(theta[3] + theta[5])
    H_v = np.array(((speed * c, 0.0, 1.0, 0.0, 1.0, 0.0), (speed * s, 0.0, 0.0, 1.0, 0.0, 1.0)))
    across = (a_v * speed) ** 2 * heading_var
    R_v = np.array(((s * s, -s * c), (-s * c, c * c))) * across + noise.R_velocity
    return np.array((a_v * speed * c + d_x, a_v * speed * s + d_y)), H_v, R_v


class DualEkf:
    """The DEKF of one vehicle: the state z = (x, y, yaw) with covariance P_s, and the
    parameters theta (see the module) with covariance P_p."""

    def __init__(self, settings: LearningSettings, *, tau: float) -> None:
        self.settings = settings
        self.tau = tau
        self._noise = _Noise.from_settings(settings, tau)
        self.resets = 0
        self.z = np.zeros(3)
        """Current state estimate (x, y, yaw)."""
        self.P_s = np.zeros((3, 3))
        self.theta = np.array([*settings.beta_initial, 0.0, 0.0])
        """Current parameters (a_V, a_w, m_x, m_y, g_x, g_y)."""
        self.P_p = self._noise.P_p_initial.copy()
        self._initialized = False
        self._lag_end = np.zeros(2)
        """Where the flown input stands (`flown_input`)."""
        self._velocity_means = np.zeros((2, 2))
        """The commanded velocity's recent and slow means (`_velocity_means`)."""
        self.wind_sample: WindSample | None = None
        """The wind this period's ground velocity measured, for the neighbours (None when none
        was measured or nothing is learned)."""

    @property
    def initialized(self) -> bool:
        return self._initialized

    @property
    def beta(self) -> np.ndarray:
        """Current parameter estimate (a_V, a_w, d_x, d_y)."""
        return beta_of(self.theta)

    def reset(self, y: np.ndarray, *, keep_beta: bool = True) -> None:
        """Restart the state filter at measurement y; keep the learned beta unless told not to."""
        self.z = np.array(y[:3], dtype=float)
        self.P_s = self._noise.R_s.copy()
        if not keep_beta or not self._initialized:
            self.theta = np.array([*self.settings.beta_initial, 0.0, 0.0])
            self.P_p = self._noise.P_p_initial.copy()
        self._initialized = True

    def step(
        self,
        y: np.ndarray,
        u: np.ndarray,
        *,
        known_beta: np.ndarray | None = None,
        shared: PooledWind | None = None,
    ) -> None:
        """Advance one period: input u was applied over the last tau; y is the new measurement,
        (x, y, yaw) or (x, y, yaw, v_North, v_East) with the ground velocity.

        `known_beta`: the true parameters (a known-model run): the state filter predicts with
        them, and the parameter filter holds them instead of learning. `shared`: the
        neighbours' wind samples pooled (`fleet_wind.WindPool.pool`), a measurement of the drift."""
        y = np.asarray(y, float)
        u = self._fly(u)
        first = not self._initialized
        if first:
            self.reset(y)
        if known_beta is not None:
            self.theta = np.array([*np.asarray(known_beta, float), 0.0, 0.0])
        if first:
            return
        n = self._noise
        learn = n.learn and known_beta is None
        if learn:
            self.theta, self.P_p = predict(self.theta, self.P_p, F=n.F_p, Q=n.Q_p)
        z_m, J_s, G = step_with_jacobians(self.z, u, self.beta, self.tau)
        H_p = _with_gust(G)
        P_own = J_s.dot(self.P_s).dot(J_s.T) + n.Q_s  # the prediction's uncertainty but beta's
        P_s_m = P_own + H_p.dot(self.P_p).dot(H_p.T) if learn else P_own
        self._velocity_means = _velocity_means(
            self._velocity_means, G[:2, 0] / self.tau, n.velocity_weights
        )
        innovation = y[:3] - z_m
        innovation[2] = wrap(innovation.item(2))
        S_inv = _inverse_3x3(P_s_m + n.R_s)
        self._correct_state(z_m, P_s_m, innovation, S_inv)
        if learn:
            self._learn(innovation, H_p, P_own + n.R_s, y[3:], shared)
        nis = float(innovation.dot(S_inv).dot(innovation))
        if not (_finite(self.z, self.P_s) and nis <= n.gate**2):
            self.resets += 1
            self.reset(y, keep_beta=_finite(self.theta, self.P_p))

    def _correct_state(
        self, z_m: np.ndarray, P_m: np.ndarray, innovation: np.ndarray, S_inv: np.ndarray
    ) -> None:
        """The state's Kalman correction (H_s = I, Joseph form), heading wrapped."""
        K = P_m.dot(S_inv)
        self.z = z_m + K.dot(innovation)
        self.z[2] = wrap(self.z.item(2))
        I_K = _EYE3 - K
        self.P_s = I_K.dot(P_m).dot(I_K.T) + K.dot(self._noise.R_s).dot(K.T)

    def _learn(
        self,
        innovation: np.ndarray,
        H_p: np.ndarray,
        R_p: np.ndarray,
        velocity: np.ndarray,
        shared: PooledWind | None,
    ) -> None:
        """The parameters' correction on the position innovation and, when measured, the
        ground velocity, in one consider update that holds the unexcited parameters; then on the
        neighbours' pooled wind when heard, in one that holds a_V and a_w."""
        n = self._noise
        hold = _unexcited(H_p, n, self._velocity_means)
        H, R = H_p, R_p
        self.wind_sample = None
        if len(velocity) == 2:
            heading, heading_var = self.z.item(2), self.P_s.item(2, 2)
            speed = self._lag_end.item(0)
            v_m, H_v, R_v = _velocity_model(self.theta, speed, heading, heading_var, n)
            H = np.concatenate((H_p, H_v))
            R = np.zeros((5, 5))
            R[:3, :3], R[3:, 3:] = R_p, R_v
            innovation = np.concatenate((innovation, velocity - v_m))
            self.wind_sample = self._wind_sample(velocity, R_v)
        theta, P_p = _consider_update(self.theta, self.P_p, innovation, H, R, hold)
        if shared is not None:  # (the neighbours' wind says nothing of this vehicle's a_V, a_w)
            across = np.array(shared.direction)
            innovation = np.array((shared.across_m_s - across.dot(beta_of(theta)[2:]),))
            H, R = across.dot(_H_DRIFT)[None, :], np.array(((shared.variance,),))
            theta, P_p = _consider_update(theta, P_p, innovation, H, R, [0, 1])
        self.theta, self.P_p = _bound(theta, P_p, n)

    def _wind_sample(self, velocity: np.ndarray, R_v: np.ndarray) -> WindSample:
        """The wind measured across the heading this period, for the neighbours: the ground
        velocity along n = (-sin th, cos th), where a_V V adds nothing, with the sensor's and
        the heading's error (n' R_v n)."""
        heading = self.z.item(2)
        n = np.array((-math.sin(heading), math.cos(heading)))
        across = float(n.dot(velocity))
        return WindSample(heading, across, math.sqrt(float(n.dot(R_v).dot(n))))

    def _fly(self, u: np.ndarray) -> np.ndarray:
        """The input flown over the last period for the command u (`flown_input`)."""
        flown, self._lag_end = flown_input(
            np.asarray(u, float), self._lag_end, lag_s=self._noise.lag_s, tau=self.tau
        )
        return flown

    def propagate(self, u: np.ndarray) -> None:
        """Predict one period without a measurement (telemetry missed this period)."""
        u = self._fly(u)
        self.z, J_s, _ = step_with_jacobians(self.z, u, self.beta, self.tau)
        self.P_s = J_s.dot(self.P_s).dot(J_s.T) + self._noise.Q_s


def _finite(*arrays: np.ndarray) -> bool:
    """No inf or nan in any of the arrays."""
    return all(bool(np.isfinite(a).all()) for a in arrays)
