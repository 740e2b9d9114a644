"""Truth plant of one simulated quadrotor, seen from above as a unicycle.

This is deliberately *not* the controller's model (onboard/core/unicycle.py). It carries what the
controller does not know: per-vehicle effectiveness errors on speed and yaw rate, a first-order
actuator lag, the wind (sitl/wind.py: a mean, turbulence and gusts, one field for the whole
fleet) and bounded measurement noise. Time is an integer tick in nanoseconds; integration is RK4
per tick. Pure code: no clocks, no I/O.
"""

import math
from dataclasses import dataclass

import numpy as np

from fleetmpc.sitl.wind import Wind, WindField
from fleetmpc.validate import finite, in_range, positive

__all__ = ["TruthParams", "TruthPlant"]


@dataclass(frozen=True)
class TruthParams:
    """What the simulated vehicle really is; the controller learns or tolerates all of it."""

    speed_effectiveness: float = 1.0
    """Achieved forward speed per commanded forward speed [-]."""
    yaw_rate_effectiveness: float = 1.0
    """Achieved yaw rate per commanded yaw rate [-]."""
    actuator_lag_s: float = 0.0
    """Time constant of the first-order lag on both inputs [s]; 0 means none."""
    wind: Wind = Wind()
    """Wind drift."""
    position_noise_m: float = 0.0
    """Standard deviation of the position measurement noise [m] (truncated at 3 sigma)."""
    heading_noise_rad: float = 0.0
    """Standard deviation of the heading measurement noise [rad] (truncated at 3 sigma)."""
    velocity_noise_m_s: float = 0.0
    """Standard deviation of each ground-velocity component's measurement noise [m/s]
    (truncated at 3 sigma)."""
    speed_limit_m_s: float = 2.0
    """Largest forward speed command the vehicle accepts [m/s]; larger commands are clamped."""
    yaw_rate_limit_rad_s: float = 0.5
    """Largest yaw-rate command the vehicle accepts [rad/s]; larger commands are clamped."""

    def __post_init__(self) -> None:
        in_range("speed_effectiveness", self.speed_effectiveness, 0.1, 3.0)
        in_range("yaw_rate_effectiveness", self.yaw_rate_effectiveness, 0.1, 3.0)
        positive("actuator_lag_s", self.actuator_lag_s, allow_zero=True)
        if not isinstance(self.wind, Wind):
            raise TypeError("wind must be a Wind")
        positive("position_noise_m", self.position_noise_m, allow_zero=True)
        positive("heading_noise_rad", self.heading_noise_rad, allow_zero=True)
        positive("velocity_noise_m_s", self.velocity_noise_m_s, allow_zero=True)
        positive("speed_limit_m_s", self.speed_limit_m_s)
        positive("yaw_rate_limit_rad_s", self.yaw_rate_limit_rad_s)


POSITION_TIME_CONSTANT_S = 1.0
"""Time constant of the simulated autopilot's horizontal position hold [s]."""


class TruthPlant:
    """One vehicle's true horizontal motion.

    State: x North [m], y East [m], yaw [rad], achieved speed [m/s], achieved yaw rate [rad/s].
    """

    def __init__(
        self,
        params: TruthParams,
        *,
        x_m: float,
        y_m: float,
        yaw_rad: float,
        wind: WindField | None = None,
        wind_clock_offset_ns: int = 0,
    ) -> None:
        """`wind`: the fleet's wind field (one realization of `params.wind` shared by every
        vehicle); None builds the realization of seed 0. `wind_clock_offset_ns`: what the
        wind's clock reads when this plant's reads 0 (a live fleet's vehicles, each timed from
        its own boot, fly one wind)."""
        self.params = params
        self.wind = WindField(params.wind, seed=0) if wind is None else wind
        self._s = [finite("x_m", x_m), finite("y_m", y_m), finite("yaw_rad", yaw_rad), 0.0, 0.0]
        self._cmd = (0.0, 0.0)
        self._held_velocity: tuple[float, float] | None = None  # set by fly_to, cleared by advance
        self.time_ns = 0
        self._wind_offset_s = wind_clock_offset_ns * 1e-9

    @property
    def state(self) -> np.ndarray:
        """True (x_m, y_m, yaw_rad), yaw wrapped to (-pi, pi]."""
        return np.array(self.pose)

    @property
    def pose(self) -> tuple[float, float, float]:
        """`state` as plain floats."""
        x, y, th = self._s[0], self._s[1], self._s[2]
        return x, y, math.atan2(math.sin(th), math.cos(th))

    @property
    def position_m(self) -> tuple[float, float]:
        """True (x_m, y_m) as plain floats."""
        return self._s[0], self._s[1]

    @property
    def achieved_input(self) -> tuple[float, float]:
        """Achieved (speed_m_s, yaw_rate_rad_s) after effectiveness and lag."""
        return self._s[3], self._s[4]

    @property
    def ground_velocity_m_s(self) -> tuple[float, float]:
        """True ground velocity (North, East) [m/s], wind included."""
        if self._held_velocity is not None:
            return self._held_velocity
        wx, wy = self.wind_m_s
        v, th = self._s[3], self._s[2]
        return v * math.cos(th) + wx, v * math.sin(th) + wy

    @property
    def wind_m_s(self) -> tuple[float, float]:
        """The wind (North, East) where the vehicle is now [m/s]."""
        return self.wind.at(self.time_ns * 1e-9 + self._wind_offset_s, self._s[0], self._s[1])

    def command(self, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        """Set the commanded input, held until the next command; clamped to the vehicle's limits.

        Non-finite commands are ignored (the last valid command holds).
        """
        if not (math.isfinite(speed_m_s) and math.isfinite(yaw_rate_rad_s)):
            return
        p = self.params
        self._cmd = (
            min(max(speed_m_s, -p.speed_limit_m_s), p.speed_limit_m_s),
            min(max(yaw_rate_rad_s, -p.yaw_rate_limit_rad_s), p.yaw_rate_limit_rad_s),
        )

    def advance(
        self, tick_ns: int, ticks: int = 1, *, track: list[tuple[float, float]] | None = None
    ) -> None:
        """Integrate `ticks` RK4 steps of `tick_ns` nanoseconds each.

        With `track`, the (x_m, y_m) after every tick is appended to it.

        State derivative: (v cos th + wind_x, v sin th + wind_y, w, (a_V V_cmd - v) / lag,
        (a_w w_cmd - w) / lag); without lag (v, w) jump to the commanded values at each tick.
        The wind's mean and sinusoid enter at each RK4 stage's time; its turbulence and gusts
        are held over a tick at their value where the tick starts (their fastest changes take
        tenths of a second; a tick is a few hundredths). Unrolled on plain floats (this runs
        ten times per control period per vehicle).
        """
        p = self.params
        h = tick_ns * 1e-9
        h2, h6 = h / 2, h / 6
        wind = p.wind
        steady_wind = wind.is_steady
        wx0, wy0 = wxm, wym = wx1, wy1 = wind.mean_m_s
        cos, sin = math.cos, math.sin
        v_cmd = p.speed_effectiveness * self._cmd[0]
        w_cmd = p.yaw_rate_effectiveness * self._cmd[1]
        lag = p.actuator_lag_s
        x, y, th, v, w = self._s
        for _ in range(ticks):
            if lag == 0:
                v, w = v_cmd, w_cmd
            if not steady_wind:
                (wx0, wy0), (wxm, wym), (wx1, wy1) = self._stage_winds(h, x, y)
            # k1 .. k4: derivatives at the start, twice at the midpoint, at the end.
            x1, y1, th1 = v * cos(th) + wx0, v * sin(th) + wy0, w
            v1, w1 = ((v_cmd - v) / lag, (w_cmd - w) / lag) if lag > 0 else (0.0, 0.0)
            th_, v_, w_ = th + h2 * th1, v + h2 * v1, w + h2 * w1
            x2, y2, th2 = v_ * cos(th_) + wxm, v_ * sin(th_) + wym, w_
            v2, w2 = ((v_cmd - v_) / lag, (w_cmd - w_) / lag) if lag > 0 else (0.0, 0.0)
            th_, v_, w_ = th + h2 * th2, v + h2 * v2, w + h2 * w2
            x3, y3, th3 = v_ * cos(th_) + wxm, v_ * sin(th_) + wym, w_
            v3, w3 = ((v_cmd - v_) / lag, (w_cmd - w_) / lag) if lag > 0 else (0.0, 0.0)
            th_, v_, w_ = th + h * th3, v + h * v3, w + h * w3
            x4, y4, th4 = v_ * cos(th_) + wx1, v_ * sin(th_) + wy1, w_
            v4, w4 = ((v_cmd - v_) / lag, (w_cmd - w_) / lag) if lag > 0 else (0.0, 0.0)
            x += h6 * (x1 + 2 * x2 + 2 * x3 + x4)
            y += h6 * (y1 + 2 * y2 + 2 * y3 + y4)
            th += h6 * (th1 + 2 * th2 + 2 * th3 + th4)
            v += h6 * (v1 + 2 * v2 + 2 * v3 + v4)
            w += h6 * (w1 + 2 * w2 + 2 * w3 + w4)
            self.time_ns += tick_ns
            if track is not None:
                track.append((x, y))
        self._s = [x, y, th, v, w]
        self._held_velocity = None

    def _stage_winds(self, h: float, x: float, y: float) -> tuple[tuple[float, float], ...]:
        """The wind at the start, middle and end of the tick of `h` seconds starting now at
        (x, y): the mean and sinusoid at each time, turbulence and gusts held from the start."""
        t0 = self.time_ns * 1e-9 + self._wind_offset_s
        wind = self.params.wind
        stages = wind.at(t0), wind.at(t0 + h / 2), wind.at(t0 + h)
        if not wind.varies_in_space:
            return stages
        n, e = self.wind.local(t0, x, y)
        return tuple((wn + n, we + e) for wn, we in stages)

    def fly_to(
        self,
        target_m: tuple[float, float],
        tick_ns: int,
        *,
        speed_m_s: float,
        time_constant_s: float = POSITION_TIME_CONSTANT_S,
    ) -> None:
        """One tick of the autopilot's position controller: straight towards `target_m`.

        A multicopter holding a point is not a unicycle: it moves sideways, rejects the wind and
        keeps its heading. The approach is first order (`time_constant_s`), at most `speed_m_s`;
        the unicycle's achieved speed and yaw rate are zero afterwards.
        """
        h = tick_ns * 1e-9
        x, y, th = self._s[0], self._s[1], self._s[2]
        dx, dy = target_m[0] - x, target_m[1] - y
        distance = math.hypot(dx, dy)
        move = min(distance * -math.expm1(-h / time_constant_s), speed_m_s * h)
        vx = vy = 0.0
        if distance > 0.0:
            vx, vy = dx * move / (distance * h), dy * move / (distance * h)
            x, y = x + vx * h, y + vy * h
        self._held_velocity = (vx, vy)
        self._s = [x, y, th, 0.0, 0.0]
        self._cmd = (0.0, 0.0)
        self.time_ns += tick_ns

    def measure(self, rng: np.random.Generator) -> np.ndarray:
        """A noisy measurement of (x_m, y_m, yaw_rad, v_north_m_s, v_east_m_s), the velocity
        over ground as `ground_velocity_m_s`; noise is Gaussian truncated at 3 sigma."""
        p = self.params
        nx, ny, nh, nvx, nvy = (min(max(n, -3.0), 3.0) for n in rng.standard_normal(5).tolist())
        x, y, th = self._s[0], self._s[1], self._s[2]
        th = math.atan2(math.sin(th), math.cos(th)) + p.heading_noise_rad * nh
        vx, vy = self.ground_velocity_m_s
        return np.array(
            [
                x + p.position_noise_m * nx,
                y + p.position_noise_m * ny,
                math.atan2(math.sin(th), math.cos(th)),
                vx + p.velocity_noise_m_s * nvx,
                vy + p.velocity_noise_m_s * nvy,
            ]
        )
