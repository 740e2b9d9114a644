"""Constant-velocity Kalman filter on noisy target observations, predicting over the horizon.

State (x, y, vx, vy) in the world frame [m, m/s]; white-acceleration process noise. The
transition and process noise depend only on the time step, which is one control period almost
always: they are cached by step (in integer nanoseconds), as are the prediction offsets.
"""

import math

import numpy as np
from filterpy.kalman import KalmanFilter

__all__ = ["TargetEstimator"]


class TargetEstimator:
    """Tracks the target from position observations; time is integer nanoseconds."""

    def __init__(self, *, observation_std_m: float, accel_std_m_s2: float = 0.3) -> None:
        self._kf = KalmanFilter(dim_x=4, dim_z=2)
        self._H = self._kf.H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
        self._kf.R = np.eye(2) * max(observation_std_m, 1e-3) ** 2
        self._q = accel_std_m_s2**2
        self._stamp_ns: int | None = None
        self.observations = 0
        self._models: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._offsets: dict[tuple[int, int], list[float]] = {}
        self._kf.inv = _inverse_2x2

    @property
    def ready(self) -> bool:
        """True once at least one observation has been fused."""
        return self._stamp_ns is not None

    def _model(self, dt_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """F and Q over a step of dt_ns nanoseconds (cached; a handful of distinct steps)."""
        model = self._models.get(dt_ns)
        if model is None:
            dt = dt_ns * 1e-9
            F = np.eye(4)
            F[0, 2] = F[1, 3] = dt
            q = self._q
            Q1 = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]]) * q
            Q = np.zeros((4, 4))
            Q[np.ix_([0, 2], [0, 2])] = Q1
            Q[np.ix_([1, 3], [1, 3])] = Q1
            if len(self._models) >= 64:  # irregular stamps: do not grow without bound
                self._models.clear()
            model = self._models[dt_ns] = (F, Q)
        return model

    def _predict_to(self, stamp_ns: int) -> None:
        if self._stamp_ns is None or stamp_ns <= self._stamp_ns:
            return
        # F and Q as attributes, not arguments: a Q argument costs filterpy an isscalar check.
        self._kf.F, self._kf.Q = self._model(stamp_ns - self._stamp_ns)
        self._kf.predict()
        self._stamp_ns = stamp_ns

    def observe(self, stamp_ns: int, position_m: np.ndarray) -> bool:
        """Fuse an observation taken at stamp_ns; non-finite or out-of-order ones are ignored."""
        p = np.asarray(position_m, float)
        if p.shape != (2,) or not all(map(math.isfinite, p.tolist())):
            return False
        if self._stamp_ns is None:
            self._kf.x = np.array([p[0], p[1], 0.0, 0.0])
            self._kf.P = np.diag([self._kf.R[0, 0], self._kf.R[1, 1], 4.0, 4.0])
            self._stamp_ns = stamp_ns
            self.observations = 1
            return True
        if stamp_ns < self._stamp_ns:
            return False
        self._predict_to(stamp_ns)
        self._kf.update(p, H=self._H)  # H given: p is used as it is (no reshape_z)
        self.observations += 1
        return True

    def predicted_track(
        self, stamp_ns: int, period_ns: int, count: int
    ) -> tuple[list[tuple[float, float]], tuple[float, float]]:
        """Positions at stamp_ns + k period_ns (count pairs) and the velocity, as plain floats."""
        if self._stamp_ns is None:
            raise RuntimeError("no target observation yet")
        px, py, vx, vy = self._kf.x.tolist()
        offsets = self._offsets.get((period_ns, count))
        if offsets is None:
            offsets = (period_ns * 1e-9 * np.arange(count)).tolist()
            self._offsets[period_ns, count] = offsets
        dt0 = (stamp_ns - self._stamp_ns) * 1e-9
        return [(px + (dt0 + t) * vx, py + (dt0 + t) * vy) for t in offsets], (vx, vy)

    def predict(self, stamp_ns: int, period_ns: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Predicted positions (count, 2) at stamp_ns + k period_ns, and the velocity (2,)."""
        positions, velocity = self.predicted_track(stamp_ns, period_ns, count)
        return np.array(positions).reshape(count, 2), np.array(velocity)


def _inverse_2x2(S: np.ndarray) -> np.ndarray:
    """Closed-form inverse of the 2 x 2 innovation covariance (filterpy's `inv` hook)."""
    (a, b), (c, d) = S.tolist()
    det = a * d - b * c
    return np.array((d / det, -b / det, -c / det, a / det)).reshape(2, 2)
