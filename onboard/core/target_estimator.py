"""The target's track: an interacting-multiple-model (IMM) filter of two coordinated-turn models
on noisy position observations.

State (x, y, vx, vy, omega) in the world frame [m, m, m/s, m/s, rad/s]: the target flies a turn of
rate omega (straight when omega = 0), its velocity perturbed by white acceleration and its turn
rate by a random walk (docs/design.md, "Target"). Two models share that state and differ in
their process noise: *steady* (a straight line or a turn of constant rate: very little noise, so
its course is quiet) and *turning* (a turn that tightens or opens, a change of speed: enough
noise to follow a figure eight). The IMM (Bar-Shalom, Li and Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, Sec. 11.6) runs one extended Kalman filter per
model, mixes their estimates before each prediction by the models' probabilities and a Markov
chain of switches between them, weighs each model by how well it predicted the observation, and
reports the weighted combination. The turn rate is always estimated, so the prediction over the
horizon curves with the target; on a straight line omega stays near zero.

A sharp corner (a waypoint) is a turn neither model expects. The filter notices it by its
innovations: while their normalized square, averaged over the last few observations, stays above
what a target that keeps to the models would give (MANEUVER_NIS), the process noise of each
prediction is scaled up (MANEUVER_SCALE), so the velocity follows the new course within a couple
of observations instead of tens of seconds (Bar-Shalom et al. 2001, Sec. 11.2: maneuver
detection and process noise adjustment).
"""

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MotionModel", "TargetEstimator", "turn_motion"]

MANEUVER_NIS = 10.0
"""Averaged normalized innovation squared above which the target is taken to be manoeuvring (a
position innovation has 2 degrees of freedom: its mean is 2 while the model holds)."""

MANEUVER_AVERAGING = 0.5
"""Weight of the newest observation in the averaged normalized innovation squared."""

MANEUVER_SCALE = 1000.0
"""Factor on the process noise while the target manoeuvres (about 30x the standard deviations)."""

_SMALL_TURN = 1e-6
"""Below this |omega dt| [rad] the turn's formulas use their series expansions."""


def turn_motion(
    x: float, y: float, vx: float, vy: float, w: float, dt: float
) -> tuple[float, float, float, float]:
    """Position and velocity after dt of a coordinated turn at rate w (straight when w = 0)."""
    a = w * dt
    if abs(a) < _SMALL_TURN:
        sin_w, cos_w = dt, 0.5 * a * dt  # sin(w dt) / w and (1 - cos(w dt)) / w
    else:
        sin_w, cos_w = math.sin(a) / w, (1.0 - math.cos(a)) / w
    c, s = math.cos(a), math.sin(a)
    return (
        x + sin_w * vx - cos_w * vy,
        y + cos_w * vx + sin_w * vy,
        c * vx - s * vy,
        s * vx + c * vy,
    )


def _process_noise(dt: float, accel_std: float, turn_std: float) -> np.ndarray:
    """Process noise (5, 5) over dt: white acceleration of std accel_std on (x, y, vx, vy), and a
    random walk of std turn_std per sqrt(s) on omega."""
    q = accel_std**2
    a, b, c = q * dt**4 / 4, q * dt**3 / 2, q * dt**2
    Q = np.zeros((5, 5))
    Q[0, 0] = Q[1, 1] = a
    Q[0, 2] = Q[2, 0] = Q[1, 3] = Q[3, 1] = b
    Q[2, 2] = Q[3, 3] = c
    Q[4, 4] = turn_std**2 * dt
    return Q


def _turn_jacobian(vx: float, vy: float, w: float, dt: float) -> np.ndarray:
    """d turn_motion / d (x, y, vx, vy, omega), with omega kept (5, 5)."""
    a = w * dt
    s, c = math.sin(a), math.cos(a)
    if abs(a) < _SMALL_TURN:
        sw, cw = dt, 0.5 * a * dt
        dsw, dcw = -w * dt**3 / 3.0, 0.5 * dt * dt  # their derivatives in omega
    else:
        sw, cw = s / w, (1.0 - c) / w
        dsw, dcw = (dt * c - sw) / w, (dt * s - cw) / w
    return np.array(
        (
            1.0, 0.0, sw, -cw, dsw * vx - dcw * vy,
            0.0, 1.0, cw, sw, dcw * vx + dsw * vy,
            0.0, 0.0, c, -s, -dt * (s * vx + c * vy),
            0.0, 0.0, s, c, dt * (c * vx - s * vy),
            0.0, 0.0, 0.0, 0.0, 1.0,
        )
    ).reshape(5, 5)  # fmt: skip


@dataclass(frozen=True)
class MotionModel:
    """One model of the IMM: its process noise and how long the target keeps to it."""

    accel_std_m_s2: float
    """White acceleration on position and velocity [m/s^2]."""
    turn_accel_std_rad_s2: float
    """Random walk of the turn rate [rad/s per sqrt(s)]."""
    mean_duration_s: float
    """Mean time the target keeps to this model before switching to the other [s]."""


STEADY = MotionModel(accel_std_m_s2=0.001, turn_accel_std_rad_s2=1e-5, mean_duration_s=60.0)
"""A straight line or a turn of constant rate, at a constant speed."""

TURNING = MotionModel(accel_std_m_s2=0.02, turn_accel_std_rad_s2=0.003, mean_duration_s=20.0)
"""A turn that tightens or opens (a figure eight's lobes), a speed that changes (docs/design.md,
"Target": the turning model's acceleration)."""

_START_STD = (2.0, 0.1)
"""Standard deviations of the velocity [m/s] and turn rate [rad/s] at the first observation."""


def _mixed_covariance(
    weights: np.ndarray, xs: np.ndarray, Ps: np.ndarray, means: np.ndarray
) -> np.ndarray:
    """For each j, sum_i weights[i, j] (P_i + (x_i - m_j)(x_i - m_j)'): the covariance of the
    models' estimates (xs, Ps) mixed with weights (models, J) about the means (J, 5); (J, 5, 5)."""
    d = xs[:, None, :] - means[None, :, :]  # [i, j]: model i's state less mean j
    spread = d[..., :, None] * d[..., None, :]
    return (weights[:, :, None, None] * (Ps[:, None] + spread)).sum(axis=0)


class TargetEstimator:
    """Tracks the target from position observations; time is integer nanoseconds."""

    def __init__(
        self,
        *,
        observation_std_m: float,
        models: tuple[MotionModel, ...] = (STEADY, TURNING),
    ) -> None:
        self._R = np.eye(2) * max(observation_std_m, 1e-3) ** 2
        self.models = models
        n = len(models)
        if n < 2:
            raise ValueError(f"an IMM needs at least two models, got {n}")
        self._xs = np.zeros((n, 5))
        """Each model's state."""
        self._Ps = np.stack([np.eye(5)] * n)
        """Each model's covariance."""
        self._transitions: dict[tuple[int, bool], tuple[np.ndarray, np.ndarray]] = {}
        self.probabilities = np.full(n, 1.0 / n)
        """Each model's probability after the last observation."""
        self.x = np.zeros(5)
        """The combined state (x, y, vx, vy, omega)."""
        self._stamp_ns: int | None = None
        self._nis = 2.0
        """The averaged normalized innovation squared (its mean while the models hold)."""
        self.observations = 0
        self._velocity_std: float | None = None
        """`velocity_std_m_s` since the last observation, None until it is asked for."""

    @property
    def ready(self) -> bool:
        """True once at least one observation has been fused."""
        return self._stamp_ns is not None

    @property
    def P(self) -> np.ndarray:
        """The combined covariance (5, 5), the spread between the models' states included."""
        return _mixed_covariance(self.probabilities[:, None], self._xs, self._Ps, self.x[None])[0]

    def velocity_std_m_s(self) -> float:
        """Standard deviation of the velocity estimate (the larger axis's) [m/s]: the combined
        covariance's two velocity variances (`P`'s diagonal entries, each model's variance and
        its spread about the combined estimate), once per observation."""
        if self._velocity_std is None:
            spread = self._xs[:, 2:4] - self.x[2:4]
            own = self._Ps[:, (2, 3), (2, 3)]  # (models, 2): each model's velocity variances
            variances = self.probabilities.dot(own + spread * spread)
            self._velocity_std = math.sqrt(max(variances.tolist()))
        return self._velocity_std

    @property
    def manoeuvring(self) -> bool:
        """True while the innovations say the target leaves the models (a corner)."""
        return self._nis > MANEUVER_NIS

    def _transition(self, dt_ns: int, manoeuvring: bool) -> tuple[np.ndarray, np.ndarray]:
        """Over dt_ns: the Markov chain's switch probabilities ([i, j] from model i to j; a model
        left goes to each other one alike) and every model's process noise (models, 5, 5),
        cached (one period, mostly)."""
        key = (dt_ns, manoeuvring)
        found = self._transitions.get(key)
        if found is None:
            if len(self._transitions) >= 64:  # irregular stamps: do not grow without bound
                self._transitions.clear()
            dt = dt_ns * 1e-9
            n = len(self.models)
            leave = np.array([1.0 - math.exp(-dt / m.mean_duration_s) for m in self.models])
            switch = np.repeat(leave[:, None] / (n - 1), n, axis=1)
            np.fill_diagonal(switch, 1.0 - leave)
            scale = MANEUVER_SCALE if manoeuvring else 1.0
            Q = np.stack(
                [scale * _process_noise(dt, m.accel_std_m_s2, m.turn_accel_std_rad_s2)
                 for m in self.models]
            )  # fmt: skip
            found = self._transitions[key] = (switch, Q)
        return found

    def _start(self, stamp_ns: int, p: np.ndarray) -> None:
        """The first observation starts the track at rest, its velocity and turn rate wide."""
        r = self._R[0, 0]
        v, w = _START_STD
        self.x = np.array([p[0], p[1], 0.0, 0.0, 0.0])
        P = np.diag([r, r, v * v, v * v, w * w])
        self._xs = np.stack([self.x] * len(self.models))
        self._Ps = np.stack([P] * len(self.models))
        self._stamp_ns = stamp_ns
        self._velocity_std = None

    def observe(self, stamp_ns: int, position_m: np.ndarray) -> bool:
        """Fuse an observation taken at stamp_ns; non-finite or out-of-order ones are ignored."""
        p = np.asarray(position_m, float)
        if p.shape != (2,) or not all(map(math.isfinite, p.tolist())):
            return False
        if self._stamp_ns is None:
            self._start(stamp_ns, p)
            self.observations = 1
            return True
        if stamp_ns <= self._stamp_ns:
            return False
        dt_ns = stamp_ns - self._stamp_ns
        dt = dt_ns * 1e-9
        # Mixing: each model starts from the estimates of both, weighed by the chance that the
        # target kept to the other one and has switched since ([i, j]: i given j now).
        switch, Q = self._transition(dt_ns, self.manoeuvring)
        prior = self.probabilities.dot(switch)
        mix = switch * self.probabilities[:, None] / prior  # [i, j]
        xs, Ps = self._xs, self._Ps
        x0 = mix.T.dot(xs)
        P0 = _mixed_covariance(mix, xs, Ps, x0)
        # Each model's EKF: turn exactly, the covariance through the Jacobian; fuse p.
        F = np.array([_turn_jacobian(vx, vy, w, dt) for _, _, vx, vy, w in x0.tolist()])
        xs = np.array([(*turn_motion(*row[:4], row[4], dt), row[4]) for row in x0.tolist()])
        Ps = F @ P0 @ F.transpose(0, 2, 1) + Q
        innovation = (p - xs[:, :2])[:, :, None]  # (models, 2, 1)
        S = Ps[:, :2, :2] + self._R
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        S_inv = S[:, ::-1, ::-1] * np.array([[1.0, -1.0], [-1.0, 1.0]]) / det[:, None, None]
        K = Ps[:, :, :2] @ S_inv  # (models, 5, 2)
        self._xs = xs + (K @ innovation)[:, :, 0]
        Ps = Ps - K @ Ps[:, :2, :]
        self._Ps = 0.5 * (Ps + Ps.transpose(0, 2, 1))
        nis = (innovation.transpose(0, 2, 1) @ S_inv @ innovation)[:, 0, 0]
        likelihood = np.exp(-0.5 * nis) / (2.0 * math.pi * np.sqrt(det))
        # Each model's probability, and the combined estimate.
        posterior = prior * likelihood
        total = float(posterior.sum())
        # (Both likelihoods underflow only at an absurd observation: keep the prior then.)
        mu = np.clip(posterior / total if total > 0.0 else prior, 1e-9, None)
        self.probabilities = mu / mu.sum()
        self.x = self.probabilities.dot(self._xs)
        # Manoeuvre detection, on the innovation as the models together expected it.
        observed_nis = float(prior.dot(nis))
        self._nis += MANEUVER_AVERAGING * (observed_nis - self._nis)
        self._stamp_ns = stamp_ns
        self._velocity_std = None
        self.observations += 1
        return True

    def forget(self) -> None:
        """Drop the track: the next observation starts it afresh (a target back after long)."""
        self._stamp_ns = None
        self._nis = 2.0

    def predicted_track(
        self, stamp_ns: int, period_ns: int, count: int
    ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
        """Positions and velocities at stamp_ns + k period_ns, k = 0..count-1, as float pairs."""
        if self._stamp_ns is None:
            raise RuntimeError("no target observation yet")
        x, y, vx, vy, w = self.x.tolist()
        x, y, vx, vy = turn_motion(x, y, vx, vy, w, (stamp_ns - self._stamp_ns) * 1e-9)
        dt = period_ns * 1e-9
        positions, velocities = [(x, y)], [(vx, vy)]
        for _ in range(count - 1):
            x, y, vx, vy = turn_motion(x, y, vx, vy, w, dt)
            positions.append((x, y))
            velocities.append((vx, vy))
        return positions, velocities

    def predict(self, stamp_ns: int, period_ns: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Predicted positions and velocities (count, 2) at stamp_ns + k period_ns."""
        positions, velocities = self.predicted_track(stamp_ns, period_ns, count)
        return np.array(positions).reshape(count, 2), np.array(velocities).reshape(count, 2)
