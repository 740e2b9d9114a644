"""Scripted aerial target: a point moving on a line, a circle, a figure eight or through waypoints.

Positions are pure functions of time, so every process that flies or watches the target agrees.
The default target source (`fleetmpc.targets`).
"""

import math
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.validate import finite, positive, vector

__all__ = ["ScriptFeed", "TargetScript"]

_KINDS = ("line", "circle", "figure_eight", "waypoints")


@dataclass(frozen=True)
class TargetScript:
    """How the target moves and how it is observed."""

    kind: str = "line"
    """One of "line", "circle", "figure_eight", "waypoints"."""
    start_m: tuple[float, float] = (0.0, 0.0)
    """line: position at t = 0 (North, East) [m]."""
    velocity_m_s: tuple[float, float] = (1.0, 0.0)
    """line: constant velocity (North, East) [m/s]."""
    center_m: tuple[float, float] = (0.0, 0.0)
    """circle and figure_eight: centre (North, East) [m]."""
    radius_m: float = 20.0
    """circle: radius; figure_eight: half-length a of the eight along North [m]."""
    speed_m_s: float = 1.0
    """circle and waypoints: speed along the path [m/s]."""
    start_angle_rad: float = 0.0
    """circle: polar angle of the start point about the centre (0 = North of it) [rad];
    figure_eight: phase phi_0 at t = 0 (0 = at the centre, heading North-East) [rad]."""
    clockwise: bool = True
    """circle: direction seen from above with North up (clockwise = turning right in NED)."""
    period_s: float = 120.0
    """figure_eight: time to fly the whole eight once [s]."""
    waypoints_m: tuple[tuple[float, float], ...] = field(default_factory=tuple)
    """waypoints: points visited in order at speed_m_s, then held at the last one [m]."""
    observation_noise_m: float = 0.0
    """Standard deviation of the noise on published target positions [m] (truncated at 3 sigma)."""
    observation_rate_hz: float = 5.0
    """Rate at which the target's position is published [Hz]."""

    def __post_init__(self) -> None:
        if self.kind not in _KINDS:
            raise ConfigError("target.kind", f"must be one of {_KINDS}, got {self.kind!r}")
        object.__setattr__(self, "start_m", vector("target.start_m", self.start_m, 2))
        object.__setattr__(
            self, "velocity_m_s", vector("target.velocity_m_s", self.velocity_m_s, 2)
        )
        object.__setattr__(self, "center_m", vector("target.center_m", self.center_m, 2))
        positive("target.radius_m", self.radius_m)
        positive("target.speed_m_s", self.speed_m_s, allow_zero=True)
        finite("target.start_angle_rad", self.start_angle_rad)
        positive("target.period_s", self.period_s)
        wps = tuple(
            vector(f"target.waypoints_m[{i}]", w, 2) for i, w in enumerate(self.waypoints_m)
        )
        if self.kind == "waypoints" and len(wps) < 2:
            raise ConfigError("target.waypoints_m", "needs at least 2 waypoints")
        object.__setattr__(self, "waypoints_m", wps)
        positive("target.observation_noise_m", self.observation_noise_m, allow_zero=True)
        positive("target.observation_rate_hz", self.observation_rate_hz)

    def state_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """True position and velocity (North, East) at time t_s [m], [m/s]."""
        if self.kind == "waypoints":
            return self._waypoint_state(t_s)
        (x, y), (vx, vy) = self.state_floats(t_s)
        return np.array((x, y)), np.array((vx, vy))

    def state_floats(self, t_s: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """`state_at` as plain floats ((x, y), (vx, vy))."""
        if self.kind == "line":
            (x0, y0), (vx, vy) = self.start_m, self.velocity_m_s
            return (x0 + vx * t_s, y0 + vy * t_s), (vx, vy)
        if self.kind == "circle":
            sign = 1.0 if self.clockwise else -1.0
            w = sign * self.speed_m_s / self.radius_m
            a = self.start_angle_rad + w * t_s
            r, (cx, cy) = self.radius_m, self.center_m
            c, s = math.cos(a), math.sin(a)
            return (cx + r * c, cy + r * s), (r * w * -s, r * w * c)
        if self.kind == "figure_eight":
            return self._figure_eight_state(t_s)
        pos, vel = self._waypoint_state(t_s)
        return (float(pos[0]), float(pos[1])), (float(vel[0]), float(vel[1]))

    def _figure_eight_state(self, t_s: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """The lemniscate of Gerono x = a sin(phi), y = a sin(phi) cos(phi), phi = phi_0 + w t.

        It crosses the centre heading North-East and South-East alternately, turns right on one
        lobe and left on the other, and its speed a w sqrt(cos^2 phi + cos^2 2 phi) varies from
        0.66 a w (in the lobes) to 1.41 a w (at the centre).
        """
        a, (cx, cy) = self.radius_m, self.center_m
        w = 2.0 * math.pi / self.period_s
        phi = self.start_angle_rad + w * t_s
        s, c = math.sin(phi), math.cos(phi)
        return (cx + a * s, cy + a * s * c), (a * w * c, a * w * (c * c - s * s))

    def _waypoint_state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        pts = np.array(self.waypoints_m)
        travelled = self.speed_m_s * max(t_s, 0.0)
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            seg = float(np.linalg.norm(b - a))
            if seg == 0.0:
                continue
            if travelled <= seg:
                u = (b - a) / seg
                return a + u * travelled, u * self.speed_m_s
            travelled -= seg
        return pts[-1].copy(), np.zeros(2)

    def observe(self, t_s: float, rng: np.random.Generator) -> np.ndarray:
        """A noisy observation of the target's position at t_s [m]."""
        (x, y), _ = self.state_floats(t_s)
        nx, ny = (
            -3.0 if n < -3.0 else 3.0 if n > 3.0 else n for n in rng.standard_normal(2).tolist()
        )
        sigma = self.observation_noise_m
        return np.array((x + sigma * nx, y + sigma * ny))

    def feed(self, rng: np.random.Generator) -> "ScriptFeed":
        """The observations a lockstep run publishes: one at every observation period."""
        return ScriptFeed(self, rng)


class ScriptFeed:
    """A scripted target's observations in a lockstep run: at the first period at or after each
    observation's due time, one noisy position stamped with that period's time."""

    def __init__(self, script: TargetScript, rng: np.random.Generator) -> None:
        self._script = script
        self._rng = rng
        self._period_ns = round(1e9 / script.observation_rate_hz)
        self._next_ns = 0

    def due(self, t_ns: int) -> list[tuple[int, np.ndarray]]:
        """The observations due by t_ns [ns] not handed out yet, as (stamp_ns, (North, East))."""
        if t_ns < self._next_ns:
            return []
        self._next_ns += self._period_ns
        return [(t_ns, self._script.observe(t_ns * 1e-9, self._rng))]
