"""Target lost, target back: what the formation follows when the target's observations stop.

States, on the time since the last observation fused (docs/design.md, "Target lost"):
- "tracking": observations come; the formation follows the estimator's prediction;
- "predicting": none for `lost_s`: the prediction is flown on, for up to `predict_s` after the
  last observation;
- "holding": the prediction is no longer trusted: the target followed brakes at `brake_m_s2`
  from where it was predicted at `predict_s` and stands, so every vehicle stops at its slot
  about it and the formation, its separation constraints as ever, holds where it is;
- "reacquiring": the first observation after a loss; after a hold it restarts the estimator
  (the old track says nothing of where the target went). The target the formation follows
  glides from where it was following it (the prediction, or the held point) to the new
  estimate, over `reacquire_s` or as long as `glide_speed_m_s` needs, whichever is longer: the
  reference does not jump. Then "tracking" again.
A slow (1 Hz) or bursty stream stays "tracking" while no gap exceeds `lost_s`.
"""

import math

import numpy as np

from fleetmpc.onboard.core.target_estimator import TargetEstimator

__all__ = ["HOLDING", "PREDICTING", "REACQUIRING", "TRACKING", "TargetWatch"]

TRACKING, PREDICTING, HOLDING, REACQUIRING = "tracking", "predicting", "holding", "reacquiring"

Track = tuple[list[tuple[float, float]], list[tuple[float, float]]]


class TargetWatch:
    """Decides what target track the formation follows, from the estimator and the time since
    its last observation; time is integer nanoseconds."""

    def __init__(
        self,
        *,
        lost_s: float,
        predict_s: float,
        reacquire_s: float,
        glide_speed_m_s: float,
        brake_m_s2: float,
    ) -> None:
        self._lost_ns = round(lost_s * 1e9)
        self._predict_ns = round(max(predict_s, lost_s) * 1e9)
        self._reacquire_s = reacquire_s
        self._glide_speed = glide_speed_m_s
        self._brake = brake_m_s2
        self.state = TRACKING
        self.losses = 0
        """Times the target was lost."""
        self._last_ns: int | None = None
        self._hold: tuple[int, tuple[float, float], tuple[float, float], int] | None = None
        """(start ns, position [m], velocity [m/s], braking time ns) of a hold."""
        self._glide: tuple[int, int, float, float] | None = None
        """(start ns, length ns, North, East offset at the start [m]) of a glide."""

    def observe(self, estimator: TargetEstimator, stamp_ns: int, position_m: np.ndarray) -> bool:
        """Fuse an observation into `estimator` (restarted first if the target was held);
        True if it was fused. The first one after a loss starts a glide from where the
        formation was following the target to the new estimate."""
        p = np.asarray(position_m, float)
        fresh = self._last_ns is None or stamp_ns > self._last_ns
        valid = fresh and p.shape == (2,) and bool(np.isfinite(p).all())
        lost = self.state in (PREDICTING, HOLDING) and valid
        followed = None
        if lost:
            followed = self._followed_at(estimator, stamp_ns)[0]
        if self.state == HOLDING and valid:
            estimator.forget()
        if not estimator.observe(stamp_ns, p):
            return False
        self._last_ns = stamp_ns if self._last_ns is None else max(self._last_ns, stamp_ns)
        if followed is not None:
            ((ex, ey),) = estimator.predicted_track(stamp_ns, 1, 1)[0]
            dx, dy = followed[0] - ex, followed[1] - ey
            length_s = max(self._reacquire_s, math.hypot(dx, dy) / self._glide_speed)
            self._glide = (stamp_ns, round(length_s * 1e9), dx, dy)
            self.state = REACQUIRING
        return True

    def track(self, estimator: TargetEstimator, stamp_ns: int, period_ns: int, count: int) -> Track:
        """The target's positions and velocities at stamp_ns + k period_ns, k < count, that the
        formation follows now."""
        self._update(estimator, stamp_ns)
        if self.state == HOLDING:
            held = [self._held_at(stamp_ns + k * period_ns) for k in range(count)]
            return [p for p, _ in held], [v for _, v in held]
        positions, velocities = estimator.predicted_track(stamp_ns, period_ns, count)
        if self._glide is None:
            return positions, velocities
        start_ns, length_ns, dx, dy = self._glide
        out_p, out_v = [], []
        for k, ((x, y), (vx, vy)) in enumerate(zip(positions, velocities, strict=True)):
            left = 1.0 - (stamp_ns + k * period_ns - start_ns) / length_ns
            if left > 0.0:
                rate = 1e9 / length_ns
                x, y, vx, vy = x + left * dx, y + left * dy, vx - rate * dx, vy - rate * dy
            out_p.append((x, y))
            out_v.append((vx, vy))
        return out_p, out_v

    def _update(self, estimator: TargetEstimator, now_ns: int) -> None:
        if self._glide is not None and now_ns >= self._glide[0] + self._glide[1]:
            self._glide = None
            if self.state == REACQUIRING:
                self.state = TRACKING
        if self._last_ns is None:
            return
        age_ns = now_ns - self._last_ns
        if self.state in (TRACKING, REACQUIRING) and age_ns > self._lost_ns:
            self.state = PREDICTING
            self.losses += 1
        if self.state == PREDICTING and age_ns > self._predict_ns:
            start_ns = self._last_ns + self._predict_ns
            position, velocity = self._followed_at(estimator, start_ns)
            brake_ns = round(math.hypot(*velocity) / self._brake * 1e9)
            self._hold = (start_ns, position, velocity, brake_ns)
            self._glide = None
            self.state = HOLDING

    def _followed_at(
        self, estimator: TargetEstimator, stamp_ns: int
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """Where the followed target is at stamp_ns and its velocity ([m], [m/s])."""
        if self.state == HOLDING:
            return self._held_at(stamp_ns)
        (x, y), (vx, vy) = (a[0] for a in estimator.predicted_track(stamp_ns, 1, 1))
        if self._glide is not None:
            start_ns, length_ns, dx, dy = self._glide
            left = 1.0 - (stamp_ns - start_ns) / length_ns
            if left > 0.0:
                rate = 1e9 / length_ns
                x, y, vx, vy = x + left * dx, y + left * dy, vx - rate * dx, vy - rate * dy
        return (x, y), (vx, vy)

    def _held_at(self, stamp_ns: int) -> tuple[tuple[float, float], tuple[float, float]]:
        """The held target at stamp_ns: braking at a constant rate from where the prediction
        was let go, then standing."""
        start_ns, (x, y), (vx, vy), brake_ns = self._hold
        tau = min(max(stamp_ns - start_ns, 0), brake_ns) * 1e-9
        left = 1.0 - tau / (brake_ns * 1e-9) if brake_ns > 0 else 0.0
        gone = tau - 0.5 * tau * tau / (brake_ns * 1e-9) if brake_ns > 0 else 0.0
        return (x + vx * gone, y + vy * gone), (vx * left, vy * left)
