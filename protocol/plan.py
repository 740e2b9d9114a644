"""A vehicle's assumed trajectory, as broadcast to its neighbours (Dunbar & Murray's scheme)."""

from dataclasses import dataclass
from functools import cached_property

import numpy as np

__all__ = ["Plan", "WindSample"]


@dataclass(frozen=True)
class WindSample:
    """The wind a vehicle measured across its heading as it made its plan, where the plan
    starts: its ground velocity's component along (-sin heading, cos heading), where its own
    speed adds nothing, so that no learned effectiveness enters it (docs/design.md, "The
    fleet's wind"). The neighbours fuse it into their own drift."""

    heading_rad: float
    """The vehicle's estimated heading when it measured."""
    across_m_s: float
    """The wind across that heading [m/s], positive to the vehicle's right (East heading North)."""
    std_m_s: float
    """Its 1-sigma error: the sensor's and the heading's (> 0)."""


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
    wind: WindSample | None = None
    """The wind its vehicle measured this period, if it measured one."""

    @property
    def horizon(self) -> int:
        return int(self.inputs.shape[0])

    @cached_property
    def holds(self) -> bool:
        """Every state at the same place: the plan of a vehicle its autopilot holds where it is
        (what a runner broadcasts while its vehicle is out of its agent's hands: the measured
        pose over the horizon). A planned stop still moves with the learned drift; a held
        vehicle does not. (Computed once per plan: every agent that hears it asks.)"""
        xy = self.states[:, :2]
        return bool(np.all(xy == xy[0]))

    def position_at(self, stamp_ns: int) -> tuple[float, float]:
        """The planned position at stamp_ns (its first before the plan, held after its end)."""
        return self.position_list(stamp_ns, 1, max_extrapolation_s=0.0)[0]

    def position_list(
        self, stamp_ns: int, count: int, *, max_extrapolation_s: float
    ) -> list[tuple[float, float]]:
        """Positions at stamp_ns + k * period_ns, k = 0..count-1, as (x, y) pairs of floats.

        Interpolates linearly inside the plan and extrapolates at the last planned velocity
        beyond its end, for at most `max_extrapolation_s` past the last state (held after that).
        """
        k0 = (stamp_ns - self.stamp_ns) / self.period_ns  # in periods
        M = len(self.inputs)
        period_s = self.period_ns * 1e-9
        pos = self.states.tolist()
        (x_a, y_a, _), (x_m, y_m, _) = pos[M - 1], pos[M]
        vx, vy = (x_m - x_a) / period_s, (y_m - y_a) / period_s
        max_periods = max_extrapolation_s / period_s
        out = []
        for j in range(count):  # plain floats: count is a horizon, a handful of points
            k = k0 + j
            if k <= 0.0:  # before the plan: its first position
                out.append((pos[0][0], pos[0][1]))
            elif k >= M:  # beyond its end: extrapolated, for at most max_periods
                beyond_s = (max_periods if k - M > max_periods else k - M) * period_s
                out.append((x_m + beyond_s * vx, y_m + beyond_s * vy))
            else:
                i = int(k)
                frac = k - i
                (x0, y0, _), (x1, y1, _) = pos[i], pos[i + 1]
                out.append((x0 * (1.0 - frac) + x1 * frac, y0 * (1.0 - frac) + y1 * frac))
        return out
