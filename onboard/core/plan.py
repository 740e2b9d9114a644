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
        period_s = self.period_ns * 1e-9
        t_s = (stamp_ns - self.stamp_ns) * 1e-9 + period_s * np.arange(count)
        pos = self.states[:, :2]
        end_s = period_s * self.horizon
        vel = (pos[-1] - pos[-2]) / period_s if self.horizon >= 1 else np.zeros(2)
        inside = np.clip(t_s, 0.0, end_s)
        out = np.column_stack(
            [
                np.interp(inside, period_s * np.arange(self.horizon + 1), pos[:, 0]),
                np.interp(inside, period_s * np.arange(self.horizon + 1), pos[:, 1]),
            ]
        )
        beyond = np.clip(t_s - end_s, 0.0, max_extrapolation_s)
        return out + beyond[:, None] * vel[None, :]
