"""A vehicle's assumed trajectory, as broadcast to its neighbours (Dunbar & Murray's scheme)."""

from dataclasses import dataclass

import numpy as np

__all__ = ["Plan"]


@dataclass(frozen=True, eq=False)
class Plan:
    """The assumed trajectory of one vehicle over the horizon.

    states[j] is the planned state (x_m, y_m, yaw_rad) at stamp_ns + j * period_ns,
    j = 0..M; inputs[j] is the planned (speed_m_s, yaw_rate_rad_s) over step j, j = 0..M-1.
    """

    vehicle_id: int
    """System id of the vehicle that made the plan (1..255)."""
    stamp_ns: int
    """Simulated time of states[0], integer nanoseconds."""
    period_ns: int
    """Time between consecutive states, integer nanoseconds."""
    states: np.ndarray
    """Planned states, shape (M + 1, 3): x North [m], y East [m], yaw [rad]."""
    inputs: np.ndarray
    """Planned inputs, shape (M, 2): forward speed [m/s], yaw rate [rad/s]."""

    @property
    def horizon(self) -> int:
        return int(self.inputs.shape[0])

    def positions_at(self, stamp_ns: int, count: int, *, max_extrapolation_s: float) -> np.ndarray:
        """Positions at stamp_ns + k * period_ns, k = 0..count-1, shape (count, 2).

        Interpolates linearly inside the plan and extrapolates at the last planned velocity
        beyond its end, for at most `max_extrapolation_s` past the last state (held after that).
        """
        out = self.position_list(stamp_ns, count, max_extrapolation_s=max_extrapolation_s)
        return np.array(out).reshape(count, 2)

    def position_list(
        self, stamp_ns: int, count: int, *, max_extrapolation_s: float
    ) -> list[tuple[float, float]]:
        """`positions_at` as (x, y) pairs of plain floats."""
        k0 = (stamp_ns - self.stamp_ns) / self.period_ns  # in periods
        M = self.horizon
        period_s = self.period_ns * 1e-9
        pos = self.states[:, :2].tolist()
        (x_a, y_a), (x_b, y_b) = pos[M - 1], pos[M]
        vx, vy = (x_b - x_a) / period_s, (y_b - y_a) / period_s
        max_periods = max_extrapolation_s / period_s
        end = float(M)
        out = []
        for j in range(count):  # plain floats: count is a horizon, a handful of points
            k = k0 + j
            inside = 0.0 if k < 0.0 else end if k > end else k  # clip to [0, M]
            i = int(inside)
            i = M - 1 if i > M - 1 else i
            frac = inside - i
            (x0, y0), (x1, y1) = pos[i], pos[i + 1]
            beyond = k - M
            beyond_s = (
                0.0 if beyond < 0.0 else max_periods if beyond > max_periods else beyond
            ) * period_s
            out.append(
                (
                    x0 * (1.0 - frac) + x1 * frac + beyond_s * vx,
                    y0 * (1.0 - frac) + y1 * frac + beyond_s * vy,
                )
            )
        return out
