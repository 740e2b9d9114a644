"""Truth plant of one simulated quadrotor, seen from above as a unicycle.

This is deliberately *not* the controller's model (onboard/core/unicycle.py). It carries what the
controller does not know: per-vehicle effectiveness errors on speed and yaw rate, a first-order
actuator lag, a wind drift (constant plus an optional slow sinusoidal variation) and bounded
measurement noise. Time is an integer tick in nanoseconds; integration is RK4 per tick.
Pure code: no clocks, no I/O.
"""

import math
from dataclasses import dataclass

import numpy as np

from onboard.core.validate import finite, in_range, positive, vector

__all__ = ["TruthParams", "TruthPlant", "Wind"]


@dataclass(frozen=True)
class Wind:
    """Wind drift added to the vehicle's ground velocity, in the world (NED) frame."""

    mean_m_s: tuple[float, float] = (0.0, 0.0)
    """Constant part (North, East) [m/s]."""
    gust_amplitude_m_s: float = 0.0
    """Amplitude of the slow sinusoidal variation on each axis [m/s]; 0 disables it."""
    gust_period_s: float = 60.0
    """Period of the slow variation [s]."""
    gust_phase_rad: tuple[float, float] = (0.0, 1.5707963267948966)
    """Phase of the variation on North and East [rad]."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "mean_m_s", vector("wind.mean_m_s", self.mean_m_s, 2))
        positive("wind.gust_amplitude_m_s", self.gust_amplitude_m_s, allow_zero=True)
        positive("wind.gust_period_s", self.gust_period_s)
        object.__setattr__(
            self, "gust_phase_rad", vector("wind.gust_phase_rad", self.gust_phase_rad, 2)
        )

    def at(self, t_s: float) -> tuple[float, float]:
        """Wind (North, East) [m/s] at time t_s."""
        if self.gust_amplitude_m_s == 0.0:
            return self.mean_m_s
        w = 2.0 * math.pi / self.gust_period_s
        a = self.gust_amplitude_m_s
        return (
            self.mean_m_s[0] + a * math.sin(w * t_s + self.gust_phase_rad[0]),
            self.mean_m_s[1] + a * math.sin(w * t_s + self.gust_phase_rad[1]),
        )


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
        positive("speed_limit_m_s", self.speed_limit_m_s)
        positive("yaw_rate_limit_rad_s", self.yaw_rate_limit_rad_s)


class TruthPlant:
    """One vehicle's true horizontal motion.

    State: x North [m], y East [m], yaw [rad], achieved speed [m/s], achieved yaw rate [rad/s].
    """

    def __init__(self, params: TruthParams, *, x_m: float, y_m: float, yaw_rad: float) -> None:
        self.params = params
        self._s = [finite("x_m", x_m), finite("y_m", y_m), finite("yaw_rad", yaw_rad), 0.0, 0.0]
        self._cmd = (0.0, 0.0)
        self.time_ns = 0

    @property
    def state(self) -> np.ndarray:
        """True (x_m, y_m, yaw_rad), yaw wrapped to (-pi, pi]."""
        x, y, th = self._s[0], self._s[1], self._s[2]
        return np.array([x, y, math.atan2(math.sin(th), math.cos(th))])

    @property
    def achieved_input(self) -> tuple[float, float]:
        """Achieved (speed_m_s, yaw_rate_rad_s) after effectiveness and lag."""
        return self._s[3], self._s[4]

    @property
    def ground_velocity_m_s(self) -> tuple[float, float]:
        """True ground velocity (North, East) [m/s], wind included."""
        wx, wy = self.params.wind.at(self.time_ns * 1e-9)
        v, th = self._s[3], self._s[2]
        return v * math.cos(th) + wx, v * math.sin(th) + wy

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

    def _deriv(self, s: list[float], wind: tuple[float, float]) -> list[float]:
        p = self.params
        v_target = p.speed_effectiveness * self._cmd[0]
        w_target = p.yaw_rate_effectiveness * self._cmd[1]
        lag = p.actuator_lag_s
        dv = (v_target - s[3]) / lag if lag > 0 else 0.0
        dw = (w_target - s[4]) / lag if lag > 0 else 0.0
        return [s[3] * math.cos(s[2]) + wind[0], s[3] * math.sin(s[2]) + wind[1], s[4], dv, dw]

    def advance(self, tick_ns: int, ticks: int = 1) -> None:
        """Integrate `ticks` RK4 steps of `tick_ns` nanoseconds each."""
        p = self.params
        h = tick_ns * 1e-9
        for _ in range(ticks):
            if p.actuator_lag_s == 0:
                self._s[3] = p.speed_effectiveness * self._cmd[0]
                self._s[4] = p.yaw_rate_effectiveness * self._cmd[1]
            t0 = self.time_ns * 1e-9
            w0, wm, w1 = p.wind.at(t0), p.wind.at(t0 + h / 2), p.wind.at(t0 + h)
            s = self._s
            k1 = self._deriv(s, w0)
            k2 = self._deriv([a + h / 2 * b for a, b in zip(s, k1, strict=True)], wm)
            k3 = self._deriv([a + h / 2 * b for a, b in zip(s, k2, strict=True)], wm)
            k4 = self._deriv([a + h * b for a, b in zip(s, k3, strict=True)], w1)
            self._s = [
                a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4)
                for a, b1, b2, b3, b4 in zip(s, k1, k2, k3, k4, strict=True)
            ]
            self.time_ns += tick_ns

    def measure(self, rng: np.random.Generator) -> np.ndarray:
        """A noisy measurement of (x_m, y_m, yaw_rad); noise is Gaussian truncated at 3 sigma."""
        p = self.params
        n = np.clip(rng.standard_normal(3), -3.0, 3.0)
        z = self.state
        z[:2] += p.position_noise_m * n[:2]
        th = z[2] + p.heading_noise_rad * n[2]
        z[2] = math.atan2(math.sin(th), math.cos(th))
        return z
