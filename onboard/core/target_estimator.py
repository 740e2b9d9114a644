"""The target's track: a coordinated-turn extended Kalman filter on noisy position observations.

State (x, y, vx, vy, omega) in the world frame [m, m, m/s, m/s, rad/s]: the target flies a turn of
rate omega (straight when omega = 0), its velocity perturbed by white acceleration and its turn
rate by a random walk (docs/design.md, "Target"). The turn rate is always estimated, so the
prediction over the horizon curves with the target; on a straight line omega stays near zero.
Observations are positions, a linear measurement: filterpy's KalmanFilter updates the state, and
the nonlinear predict (the exact turn, its Jacobian for the covariance) is this module's.

A sharp corner (a waypoint) is not a turn this model expects. The filter notices it by its
innovations: while their normalized square, averaged over the last few observations, stays above
what a target that keeps to the model would give (MANEUVER_NIS), the process noise of each
prediction is scaled up (MANEUVER_SCALE), so the velocity follows the new course within a couple
of observations instead of tens of seconds; on a steady path the noise stays low and the
estimate quiet (Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, 2001, Sec. 11.2: maneuver detection and process noise adjustment).
"""

import math

import numpy as np
from filterpy.kalman import KalmanFilter

__all__ = ["TargetEstimator", "turn_motion"]

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


def _inverse_2x2(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of the 2 x 2 innovation covariance (filterpy's `inv` hook)."""
    (a, b), (c, d) = S.tolist()
    det = a * d - b * c
    return np.array((d / det, -b / det, -c / det, a / det)).reshape(2, 2)


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


class TargetEstimator:
    """Tracks the target from position observations; time is integer nanoseconds."""

    def __init__(
        self,
        *,
        observation_std_m: float,
        accel_std_m_s2: float = 0.01,
        turn_accel_std_rad_s2: float = 0.002,
    ) -> None:
        self._kf = KalmanFilter(dim_x=5, dim_z=2)
        self._kf.H = self._H = np.array([[1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0]])
        self._kf.R = np.eye(2) * max(observation_std_m, 1e-3) ** 2
        self._kf.inv = _inverse_2x2
        self._accel_std, self._turn_std = accel_std_m_s2, turn_accel_std_rad_s2
        self._noise: dict[int, np.ndarray] = {}
        self._stamp_ns: int | None = None
        self._nis = 2.0
        """The averaged normalized innovation squared (its mean while the model holds)."""
        self.observations = 0

    @property
    def ready(self) -> bool:
        """True once at least one observation has been fused."""
        return self._stamp_ns is not None

    @property
    def turn_rate_rad_s(self) -> float:
        """The estimated turn rate [rad/s]."""
        return float(self._kf.x[4])

    def velocity_std_m_s(self) -> float:
        """Standard deviation of the velocity estimate (the larger axis's) [m/s]."""
        P = self._kf.P
        return math.sqrt(max(P[2, 2], P[3, 3]))

    @property
    def manoeuvring(self) -> bool:
        """True while the innovations say the target leaves the model (a corner)."""
        return self._nis > MANEUVER_NIS

    def _predict_to(self, stamp_ns: int) -> None:
        """The filter's predict: the state turned exactly, the covariance through the Jacobian
        (with the process noise scaled up while the target manoeuvres)."""
        dt_ns = stamp_ns - self._stamp_ns
        dt = dt_ns * 1e-9
        Q = self._noise.get(dt_ns)
        if Q is None:  # (one period almost always: cached by step)
            if len(self._noise) >= 64:  # irregular stamps: do not grow without bound
                self._noise.clear()
            Q = self._noise[dt_ns] = _process_noise(dt, self._accel_std, self._turn_std)
        kf = self._kf
        x, y, vx, vy, w = kf.x.tolist()
        F = _turn_jacobian(vx, vy, w, dt)
        kf.x = np.array((*turn_motion(x, y, vx, vy, w, dt), w))
        kf.P = F.dot(kf.P).dot(F.T) + (MANEUVER_SCALE * Q if self.manoeuvring else Q)
        self._stamp_ns = stamp_ns

    def observe(self, stamp_ns: int, position_m: np.ndarray) -> bool:
        """Fuse an observation taken at stamp_ns; non-finite or out-of-order ones are ignored."""
        p = np.asarray(position_m, float)
        if p.shape != (2,) or not all(map(math.isfinite, p.tolist())):
            return False
        if self._stamp_ns is None:
            r = self._kf.R[0, 0]
            self._kf.x = np.array([p[0], p[1], 0.0, 0.0, 0.0])
            self._kf.P = np.diag([r, r, 4.0, 4.0, 0.01])
            self._stamp_ns = stamp_ns
            self.observations = 1
            return True
        if stamp_ns <= self._stamp_ns:
            return False
        self._predict_to(stamp_ns)
        self._kf.update(p, H=self._H)  # H given: p is used as it is (no reshape_z)
        innovation, S_inv = self._kf.y, self._kf.SI
        nis = float(innovation.dot(S_inv).dot(innovation))
        self._nis += MANEUVER_AVERAGING * (nis - self._nis)
        self.observations += 1
        return True

    def predicted_track(
        self, stamp_ns: int, period_ns: int, count: int
    ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
        """Positions and velocities at stamp_ns + k period_ns, k = 0..count-1, as float pairs."""
        if self._stamp_ns is None:
            raise RuntimeError("no target observation yet")
        x, y, vx, vy, w = self._kf.x.tolist()
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
