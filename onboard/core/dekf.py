"""Dual Extended Kalman Filter (Wan & Nelson) learning the oracle parameters beta.

Two EKFs run side by side (paper Sec. V-A, Eqs. 7-10, with the corrections of docs/design.md,
"Learning": Eq. 7b reads P_p^-(t) = P_p(t-1) + R_p and Eq. 8a propagates from z^(t-1)):
    parameter prediction   beta^- = beta(t-1),            P_p^- = P_p(t-1) + Q_p
    state prediction       z^-    = f(z^(t-1), u, beta^-), P_s^- = J_s P_s J_s' + Q_s
    state correction       z^     = z^- + K_s (y - z^-)
    parameter correction   beta   = beta^- + K_p (y - z^-), H_p = df/dbeta at (z^(t-1), u, beta^-),
                           with innovation covariance H_p P_p^- H_p' + P_s^- + R
(the parameter filter's measurement noise is the state prediction's uncertainty plus the sensor's).
The measurement is the full state (H_s = I): position and heading from telemetry.

Excitation: a parameter whose Jacobian column is (nearly) zero gets no information from this
measurement, yet a plain update would still move it through its correlation with the others; such
parameters get a zero gain row (a Schmidt "consider" update, Joseph form keeps P consistent), so
a_V stays put while hovering and a_w while flying straight.

Safeguards: beta is clipped to its bounds and the parameter covariance is capped at its initial
value, so beta stays bounded and does not wander when excitation vanishes (a parameter whose
Jacobian column is zero, e.g. a_V at V = 0, is not updated); a non-finite result or an innovation
beyond the gate resets the state to the measurement (beta is kept if finite) and is counted.

`DualEkf` is built on filterpy's KalmanFilter objects (see the class for why not
ExtendedKalmanFilter); `dekf_step` is the same algorithm as a plain function on a `DekfState`, and
the tests check that the two agree.
"""

import math
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import KalmanFilter

from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.onboard.core.unicycle import (
    step,
    step_jacobians,
    step_with_jacobians,
    wrap,
    wrap_angle,
)

__all__ = ["DekfState", "DualEkf", "dekf_step", "initial_dekf_state"]


def _residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = a - b
    r[2] = wrap(float(r[2]))
    return r


def _all_finite(*arrays: np.ndarray) -> bool:
    """No inf or nan in any of the arrays: both propagate into the sum of squares (entries
    beyond 1e150 would overflow it too, which is divergence all the same)."""
    total = 0.0
    for a in arrays:
        flat = a.ravel()
        total += flat.dot(flat)
    return math.isfinite(total)


def _inverse_3x3(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a 3 x 3 innovation covariance (filterpy's `inv` hook).

    The adjugate over the determinant, in plain floats: about 2 us, against 6 us for
    numpy.linalg.inv and 20 us for scipy.linalg.inv (what ExtendedKalmanFilter.update calls) on a
    3 x 3. S is a covariance plus the sensor noise, well conditioned, so the cofactors lose
    nothing to cancellation.
    """
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


@dataclass(frozen=True)
class _Noise:
    Q_s: np.ndarray
    R_s: np.ndarray
    Q_p: np.ndarray
    P_p_cap: np.ndarray
    beta_min: np.ndarray
    beta_max: np.ndarray
    gate: float
    learn: bool
    excitation: np.ndarray
    lag_s: float = 0.0
    speed_excitation_m_s: float = 0.0
    beta_min_list: tuple[float, ...] = ()
    beta_max_list: tuple[float, ...] = ()
    P_p_cap_list: tuple[float, ...] = ()
    excitation_list: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        # Plain-float copies for the per-period bounds and excitation checks.
        for name in ("beta_min", "beta_max", "P_p_cap", "excitation"):
            object.__setattr__(self, f"{name}_list", tuple(getattr(self, name).tolist()))

    @classmethod
    def from_settings(cls, s: LearningSettings, tau: float) -> "_Noise":
        pos, head = (
            (s.process_position_std_m, s.process_heading_std_rad)
            if s.enabled
            else (s.fixed_model_position_std_m, s.fixed_model_heading_std_rad)
        )
        return cls(
            Q_s=np.diag([pos**2] * 2 + [head**2]),
            R_s=np.diag([s.measurement_position_std_m**2] * 2 + [s.measurement_heading_std_rad**2]),
            Q_p=np.diag(np.square(s.beta_random_walk) * tau),
            P_p_cap=np.square(np.array(s.beta_std_initial)),
            beta_min=np.array(s.beta_min),
            beta_max=np.array(s.beta_max),
            gate=s.innovation_gate,
            learn=s.enabled,
            excitation=np.array(s.excitation_min) * tau,
            lag_s=s.input_lag_s,
            speed_excitation_m_s=s.speed_excitation_m_s,
        )


def _bound(beta: np.ndarray, P_p: np.ndarray, noise: _Noise) -> tuple[np.ndarray, np.ndarray]:
    """beta clipped to its bounds (the same array when inside them, the usual case) and P_p
    with its diagonal capped, symmetrized."""
    values, bounds = beta.tolist(), (noise.beta_min_list, noise.beta_max_list)
    for b, lo, hi in zip(values, *bounds, strict=True):
        if b < lo or b > hi:  # (nan is neither: it passes through, as with min and max)
            clipped = zip(values, *bounds, strict=True)
            beta = np.array([lo if b < lo else hi if b > hi else b for b, lo, hi in clipped])
            break
    d = P_p.diagonal()
    for v, cap in zip(d.tolist(), noise.P_p_cap_list, strict=True):
        if v > cap:
            scale = np.sqrt(np.minimum(1.0, noise.P_p_cap / np.maximum(d, 1e-300)))
            P_p = P_p * np.outer(scale, scale)
            break
    # 0.5 (P_p + P_p') with the transpose copied first: numpy adds a transposed operand
    # through its strided path, twice the time of the copy and a contiguous sum on a 4 x 4.
    sym = P_p.T.copy()
    sym += P_p
    sym *= 0.5
    return beta, sym


def _unexcited(H_p: np.ndarray, noise: _Noise, velocity_means: np.ndarray) -> list[int]:
    """Parameters whose Jacobian column is too small to learn from, and a_V while the
    commanded velocity has not changed enough for a wind not to mimic it (`velocity_means`,
    its recent and slow means (2, 2))."""
    hold = []
    columns = zip(H_p.T.tolist(), noise.excitation_list, strict=True)
    for i, ((a, b, c), floor) in enumerate(columns):
        if math.sqrt(a * a + b * b + c * c) < floor:
            hold.append(i)
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


def velocity_means(means: np.ndarray, H_p: np.ndarray, tau: float) -> np.ndarray:
    """The recent and slow means (2, 2) of the commanded velocity (a_V's column of H_p over tau),
    moved on by one period."""
    v = H_p[:2, 0] / tau
    weights = np.array([[tau / VELOCITY_FAST_S], [tau / VELOCITY_SLOW_S]])
    return means + weights * (v - means)


def _consider_update(
    beta_m: np.ndarray,
    P_m: np.ndarray,
    K: np.ndarray,
    H: np.ndarray,
    R: np.ndarray,
    innov: np.ndarray,
    hold: list[int],
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update with the gain rows of the held parameters zeroed (Joseph form)."""
    K = K.copy()
    K[hold] = 0.0
    I_K = np.eye(len(beta_m)) - K.dot(H)
    return beta_m + K.dot(innov), I_K.dot(P_m).dot(I_K.T) + K.dot(R).dot(K.T)


@dataclass(frozen=True, eq=False)
class DekfState:
    """State of the dual filter: z (3,), P_s (3, 3), beta (4,), P_p (4, 4), resets (count)."""

    z: np.ndarray
    P_s: np.ndarray
    beta: np.ndarray
    P_p: np.ndarray
    resets: int = 0
    lag_end: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """Where the flown input stands (`flown_input`)."""
    velocity_means: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    """The commanded velocity's recent and slow means (`velocity_means`)."""


def initial_dekf_state(y: np.ndarray, settings: LearningSettings) -> DekfState:
    """Dual-filter state initialized at the first measurement y = (x, y, yaw)."""
    R = np.diag(
        [settings.measurement_position_std_m**2] * 2 + [settings.measurement_heading_std_rad**2]
    )
    return DekfState(
        z=np.array(y, dtype=float),
        P_s=R.copy(),
        beta=np.array(settings.beta_initial, dtype=float),
        P_p=np.diag(np.square(settings.beta_std_initial)),
    )


def dekf_step(
    state: DekfState, y: np.ndarray, u: np.ndarray, *, settings: LearningSettings, tau: float
) -> DekfState:
    """One DEKF period as a plain function: input u applied over the last tau, measurement y now."""
    n = _Noise.from_settings(settings, tau)
    u, lag_end = flown_input(np.asarray(u, float), state.lag_end, lag_s=n.lag_s, tau=tau)
    beta_m = state.beta
    P_p_m = state.P_p + n.Q_p if n.learn else state.P_p
    J_s, _, H_p = step_jacobians(state.z, u, beta_m, tau)
    z_m = step(state.z, u, beta_m, tau)
    P_own = J_s @ state.P_s @ J_s.T + n.Q_s
    P_s_m = P_own + H_p @ P_p_m @ H_p.T if n.learn else P_own
    means = velocity_means(state.velocity_means, H_p, tau)
    innov = _residual(np.asarray(y, float), z_m)
    S = P_s_m + n.R_s
    K_s = P_s_m @ np.linalg.inv(S)
    z = z_m + K_s @ innov
    I_K = np.eye(3) - K_s
    P_s = I_K @ P_s_m @ I_K.T + K_s @ n.R_s @ K_s.T
    beta, P_p = beta_m, P_p_m
    if n.learn:
        R_p = P_own + n.R_s
        S_p = H_p @ P_p_m @ H_p.T + R_p
        K_p = P_p_m @ H_p.T @ np.linalg.inv(S_p)
        hold = _unexcited(H_p, n, means)
        beta, P_p = _consider_update(beta_m, P_p_m, K_p, H_p, R_p, innov, hold)
        beta, P_p = _bound(beta, P_p, n)
    z[2] = wrap_angle(z[2])
    nis = float(innov @ np.linalg.solve(S, innov))
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(P_s)) and nis <= n.gate**2):
        fresh = initial_dekf_state(y, settings)
        keep = np.all(np.isfinite(beta)) and np.all(np.isfinite(P_p))
        return DekfState(
            fresh.z,
            fresh.P_s,
            beta if keep else fresh.beta,
            P_p if keep else fresh.P_p,
            state.resets + 1,
            lag_end,
            means,
        )
    return DekfState(z, P_s, beta, P_p, state.resets, lag_end, means)


class DualEkf:
    """The DEKF as two filterpy KalmanFilters (state and parameters).

    Both filters linearize their measurement model, so filterpy's linear KalmanFilter.update (with
    H passed in each period) performs the EKF update; unlike ExtendedKalmanFilter.update it takes
    an `inv` hook, set to a closed-form 3 x 3 inverse (`_inverse_3x3`), and needs no Jacobian and
    measurement callbacks. The residual it forms is z - H x, so each filter is handed the
    measurement that makes this the DEKF's innovation y ⊖ z^- (heading wrapped):
        state filter       H = I, z = y with its heading unwrapped to within pi of z^-;
        parameter filter   H = H_p, z = (y ⊖ z^-) + H_p beta^-: the measurement less the affine
                           part of the linearized model h(beta) ~ z^- + H_p (beta - beta^-).
    The state prediction z^- = f(z^, u, beta^-) and its covariance are written straight into the
    state filter (the model is nonlinear); the parameter filter's predict (F = I, no input) is
    P_p + Q_p, written out rather than called. The model step and its Jacobians come from one
    plain-float call.
    """

    def __init__(self, settings: LearningSettings, *, tau: float) -> None:
        self.settings = settings
        self.tau = tau
        self._noise = _Noise.from_settings(settings, tau)
        self.resets = 0
        self.state_filter = KalmanFilter(dim_x=3, dim_z=3)
        self.param_filter = KalmanFilter(dim_x=4, dim_z=3)
        self.state_filter.Q = self._noise.Q_s
        self.state_filter.R = self._noise.R_s
        self.param_filter.Q = self._noise.Q_p
        for f in (self.state_filter, self.param_filter):
            f.inv = _inverse_3x3
        self._H_s = np.eye(3)
        self._gate_sq = self._noise.gate**2
        self._initialized = False
        self._lag_end = np.zeros(2)
        """Where the flown input stands (`flown_input`)."""
        self._velocity_means = np.zeros((2, 2))
        """The commanded velocity's recent and slow means (`velocity_means`)."""

    @property
    def initialized(self) -> bool:
        return self._initialized

    def reset(self, y: np.ndarray, *, keep_beta: bool = True) -> None:
        """Restart the state filter at measurement y; keep the learned beta unless told not to."""
        s = initial_dekf_state(y, self.settings)
        self.state_filter.x = s.z
        self.state_filter.P = s.P_s
        if not keep_beta or not self._initialized:
            self.param_filter.x = s.beta
            self.param_filter.P = s.P_p
        self._initialized = True

    @property
    def z(self) -> np.ndarray:
        """Current state estimate (x, y, yaw)."""
        return self.state_filter.x

    @property
    def beta(self) -> np.ndarray:
        """Current parameter estimate (a_V, a_w, d_x, d_y)."""
        return self.param_filter.x

    def step(self, y: np.ndarray, u: np.ndarray, *, known_beta: np.ndarray | None = None) -> None:
        """Advance one period: input u was applied over the last tau; y is the new measurement.

        `known_beta`: the true parameters (a known-model run): the state filter predicts with
        them, and the parameter filter holds them instead of learning."""
        y = np.asarray(y, float)
        u = self._fly(u)
        first = not self._initialized
        if first:
            self.reset(y)
        sf, pf, n = self.state_filter, self.param_filter, self._noise
        if known_beta is not None:
            pf.x = np.array(known_beta, dtype=float)
        if first:
            return
        learn = n.learn and known_beta is None
        if learn:
            pf.P = pf.P + n.Q_p  # predict: beta^- = beta, P_p^- = P_p + Q_p  (F = I)
        z_m, J_s, H_p = step_with_jacobians(sf.x, u, pf.x, self.tau)
        sf.x = z_m
        P_own = J_s.dot(sf.P).dot(J_s.T) + n.Q_s  # the prediction's uncertainty but beta's
        sf.P = P_own + H_p.dot(pf.P).dot(H_p.T) if learn else P_own
        self._velocity_means = velocity_means(self._velocity_means, H_p, self.tau)
        (y_x, y_y, y_th), th_m = y.tolist(), float(z_m[2])
        th = th_m + wrap(y_th - th_m)  # near th_m
        sf.update(np.array((y_x, y_y, th)), H=self._H_s)
        if learn:
            # Innovation y ⊖ z^- (sf.y) as the state filter formed it; its covariance less
            # beta's part, which the parameter filter adds itself: R_p = P_s^- + R.
            beta_prior, P_p_prior, R_p = pf.x, pf.P, P_own + n.R_s
            pf.R = R_p  # (as an attribute: an R argument costs filterpy an isscalar check)
            pf.update(sf.y + H_p.dot(beta_prior), H=H_p)
            hold = _unexcited(H_p, n, self._velocity_means)
            if hold:
                pf.x, pf.P = _consider_update(beta_prior, P_p_prior, pf.K, H_p, R_p, pf.y, hold)
            pf.x, pf.P = _bound(pf.x, pf.P, n)
        x = sf.x
        x[2] = wrap(x.item(2))
        nis = float(sf.y.dot(sf.SI).dot(sf.y))  # innovation and its inverse covariance
        if not (_all_finite(x, sf.P) and nis <= self._gate_sq):
            self.resets += 1
            finite_beta = _all_finite(pf.x, pf.P)
            self.reset(y, keep_beta=finite_beta)
            if not finite_beta:
                s = initial_dekf_state(y, self.settings)
                pf.x, pf.P = s.beta, s.P_p

    def _fly(self, u: np.ndarray) -> np.ndarray:
        """The input flown over the last period for the command u (`flown_input`)."""
        flown, self._lag_end = flown_input(
            np.asarray(u, float), self._lag_end, lag_s=self._noise.lag_s, tau=self.tau
        )
        return flown

    def propagate(self, u: np.ndarray) -> None:
        """Predict one period without a measurement (telemetry missed this period)."""
        u = self._fly(u)
        sf = self.state_filter
        sf.x, J_s, _ = step_with_jacobians(sf.x, u, self.beta, self.tau)
        sf.P = J_s.dot(sf.P).dot(J_s.T) + self._noise.Q_s
