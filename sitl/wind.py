"""The wind every simulated vehicle of a fleet flies in: one field over space and time.

A wind is a mean, an optional slow sinusoid (the older scenarios' "gust"), continuous turbulence
and discrete gusts (docs/design.md, "Wind"):

- **Turbulence** is a frozen field of von Kármán spectrum carried along by the mean wind, whose
  eddies also decay over a time scale: the random Fourier modes of Kraichnan (1970), each mode's
  wavenumber drawn from the von Kármán energy spectrum of MIL-HDBK-1797 (integral length scale
  L, intensity sigma per horizontal axis) and its frequency from a Cauchy law of scale
  1/time_scale_s, so that a point fixed in the moving air sees a first-order Gauss-Markov
  decorrelation exp(-|dt| / time_scale_s). Two vehicles a distance r apart feel winds correlated
  as the von Kármán spectrum says (0.70 at r = L/4, 0.35 at r = L, 0.15 at r = 2 L,
  along their line).
- **Discrete gusts** have the "1 - cosine" shape of MIL-F-8785C: a front moving at
  front_speed_m_s along the gust's direction, passing the local origin at onset_s; behind it the
  wind rises to the amplitude over half the gust's length and falls back over the other half.

The field is a pure function of its description and a seed, so every process that builds it
(the lockstep, each `fleetmpc sitl` vehicle) evaluates the same wind at the same place and time.
Pure code: no clocks, no I/O.
"""

import math
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.validate import finite, positive, vector

__all__ = ["Gust", "Turbulence", "Wind", "WindField", "von_karman_correlation"]

WIND_STREAM = 0x57494E44
"""Mixed into the scenario's seed for the wind's random numbers ("WIND"), so the wind does not
share a stream with the noise or the target."""

MODES = 128
"""Fourier modes of the turbulence field: enough for its spectrum and its statistics within a few
per cent over a flight, few enough for a plant tick."""

VON_KARMAN_SCALE = 1.339
"""The constant of the von Kármán spectra (MIL-HDBK-1797): L' = 1.339 L in the energy spectrum."""


@dataclass(frozen=True)
class Turbulence:
    """Continuous turbulence: intensity, length scale, and how fast its eddies decay."""

    sigma_m_s: float = 0.0
    """Standard deviation of each horizontal component at the vehicle [m/s]; 0: none."""
    length_scale_m: float = 20.0
    """Integral length scale L of the von Kármán spectrum [m]."""
    time_scale_s: float = 5.0
    """Correlation time of the field seen from a point moving with the mean wind [s]."""

    def __post_init__(self) -> None:
        positive("turbulence.sigma_m_s", self.sigma_m_s, allow_zero=True)
        positive("turbulence.length_scale_m", self.length_scale_m)
        positive("turbulence.time_scale_s", self.time_scale_s)

    def correlation_time_s(self, airspeed_m_s: float) -> float:
        """Time over which a vehicle moving at `airspeed_m_s` through the air sees the wind
        change: 1 / (1/time_scale + airspeed / L) [s]."""
        return 1.0 / (1.0 / self.time_scale_s + abs(airspeed_m_s) / self.length_scale_m)


@dataclass(frozen=True)
class Gust:
    """One discrete "1 - cosine" gust."""

    onset_s: float
    """When the gust's front passes the local origin [s]."""
    amplitude_m_s: tuple[float, float]
    """Peak wind added (North, East) [m/s]; the front moves along it."""
    length_m: float = 20.0
    """The gust's whole length along its direction, rise and fall [m]."""
    front_speed_m_s: float = 2.0
    """Speed of the front over the ground [m/s]: a vehicle in the gust feels it for
    length_m / front_speed_m_s seconds."""

    def __post_init__(self) -> None:
        finite("gust.onset_s", self.onset_s)
        object.__setattr__(
            self, "amplitude_m_s", vector("gust.amplitude_m_s", self.amplitude_m_s, 2)
        )
        if math.hypot(*self.amplitude_m_s) == 0.0:
            raise ConfigError("gust.amplitude_m_s", "must not be zero")
        positive("gust.length_m", self.length_m)
        positive("gust.front_speed_m_s", self.front_speed_m_s)

    @property
    def duration_s(self) -> float:
        """How long a vehicle standing still feels the gust [s]."""
        return self.length_m / self.front_speed_m_s

    def at(self, t_s: float, x_m: float, y_m: float) -> tuple[float, float]:
        """The gust's wind (North, East) at (x_m, y_m) and time t_s [m/s]."""
        a_n, a_e = self.amplitude_m_s
        norm = math.hypot(a_n, a_e)
        along = (a_n * x_m + a_e * y_m) / norm
        s = self.front_speed_m_s * (t_s - self.onset_s) - along  # distance behind the front
        if not 0.0 < s < self.length_m:
            return 0.0, 0.0
        shape = 0.5 * (1.0 - math.cos(2.0 * math.pi * s / self.length_m))
        return a_n * shape, a_e * shape


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
    turbulence: Turbulence = Turbulence()
    """Continuous turbulence (none by default)."""
    gusts: tuple[Gust, ...] = field(default=())
    """Discrete "1 - cosine" gusts."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "mean_m_s", vector("wind.mean_m_s", self.mean_m_s, 2))
        positive("wind.gust_amplitude_m_s", self.gust_amplitude_m_s, allow_zero=True)
        positive("wind.gust_period_s", self.gust_period_s)
        object.__setattr__(
            self, "gust_phase_rad", vector("wind.gust_phase_rad", self.gust_phase_rad, 2)
        )
        if not isinstance(self.turbulence, Turbulence):
            raise ConfigError("wind.turbulence", "must be a table of turbulence settings")
        object.__setattr__(self, "gusts", tuple(self.gusts))
        if not all(isinstance(g, Gust) for g in self.gusts):
            raise ConfigError("wind.gusts", "must be a list of gust tables")

    @property
    def is_steady(self) -> bool:
        """True if the wind is its mean everywhere and always."""
        return self.gust_amplitude_m_s == 0.0 and not self.varies_in_space

    @property
    def varies_in_space(self) -> bool:
        """True if the wind has turbulence or gusts (parts that depend on where one is)."""
        return self.turbulence.sigma_m_s > 0.0 or bool(self.gusts)

    def rate_m_s(self, airspeed_m_s: float) -> float:
        """How fast the wind a vehicle flying at `airspeed_m_s` through the air feels changes,
        as the intensity of a random walk that would follow it [m/s per sqrt(s)]: the root sum
        of squares of sigma sqrt(2 / T_c) for the turbulence (its Gauss-Markov increments),
        A sqrt(2 pi / period) for the sinusoid and A sqrt(pi / (2 D)) for a gust of D seconds
        (each part's slope squared over its angular frequency); 0 for a steady wind."""
        parts = [0.0]
        turb = self.turbulence
        if turb.sigma_m_s > 0.0:
            parts.append(turb.sigma_m_s * math.sqrt(2.0 / turb.correlation_time_s(airspeed_m_s)))
        if self.gust_amplitude_m_s > 0.0:
            parts.append(self.gust_amplitude_m_s * math.sqrt(2.0 * math.pi / self.gust_period_s))
        for gust in self.gusts:
            parts.append(
                math.hypot(*gust.amplitude_m_s) * math.sqrt(math.pi / (2 * gust.duration_s))
            )
        return math.sqrt(sum(p * p for p in parts))

    def change_m_s(self, airspeed_m_s: float, lag_s: float) -> float:
        """How much the wind a vehicle flying at `airspeed_m_s` through the air feels changes
        over `lag_s`, RMS on each axis [m/s]: the square root of the structure function
        D(s) = 2 sigma^2 (1 - f(V s / L) e^(-s / T)) of the turbulence (its von Kármán
        correlation along the flight, f, and its eddies' decay) plus A^2 (1 - cos(2 pi s / P))
        of the sinusoid; the discrete gusts, which blow once, are left out."""
        turb, square = self.turbulence, 0.0
        if turb.sigma_m_s > 0.0:
            along = float(
                von_karman_correlation(np.array(airspeed_m_s * lag_s / turb.length_scale_m))
            )
            kept = along * math.exp(-lag_s / turb.time_scale_s)
            square += 2.0 * turb.sigma_m_s**2 * (1.0 - kept)
        a = self.gust_amplitude_m_s
        square += a * a * (1.0 - math.cos(2.0 * math.pi * lag_s / self.gust_period_s))
        return math.sqrt(square)

    def gust_std_m_s(self) -> float:
        """Standard deviation on each axis of the wind's changing parts [m/s]: the turbulence's
        sigma, the sinusoid's A / sqrt(2) and a quarter of the largest gust's peak (a 1 - cos
        gust's mean square over its length is 3/8 of the peak's square; a quarter counts that
        it blows once)."""
        gust = max((math.hypot(*g.amplitude_m_s) for g in self.gusts), default=0.0)
        parts = (self.turbulence.sigma_m_s, self.gust_amplitude_m_s / math.sqrt(2.0), gust / 4)
        return math.sqrt(sum(p * p for p in parts))

    def at(self, t_s: float) -> tuple[float, float]:
        """The mean and the sinusoid (North, East) at time t_s [m/s]: the wind everywhere,
        but for turbulence and gusts (`WindField.local`)."""
        if self.gust_amplitude_m_s == 0.0:
            return self.mean_m_s
        w = 2.0 * math.pi / self.gust_period_s
        a = self.gust_amplitude_m_s
        return (
            self.mean_m_s[0] + a * math.sin(w * t_s + self.gust_phase_rad[0]),
            self.mean_m_s[1] + a * math.sin(w * t_s + self.gust_phase_rad[1]),
        )


def _von_karman_wavenumbers(rng: np.random.Generator, count: int, length_m: float) -> np.ndarray:
    """`count` wavenumber magnitudes [rad/m] drawn from the von Kármán energy spectrum
    E(k) ~ (L'k)^4 / (1 + (L'k)^2)^(17/6), L' = 1.339 L, by its inverse distribution function."""
    y = np.geomspace(1e-3, 1e3, 4001)  # L'k
    density = y**4 / (1.0 + y * y) ** (17.0 / 6.0)
    cdf = np.concatenate(([0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(y))))
    y_drawn = np.interp(rng.uniform(0.0, cdf[-1], count), cdf, y)
    return y_drawn / (VON_KARMAN_SCALE * length_m)


def _isotropic_unit_vectors(rng: np.random.Generator, count: int) -> np.ndarray:
    v = rng.standard_normal((count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


class WindField:
    """One realization of a `Wind`, the same for every vehicle that builds it with one seed."""

    def __init__(self, wind: Wind, *, seed: int) -> None:
        self.wind = wind
        turb = wind.turbulence
        rng = np.random.default_rng([seed, WIND_STREAM])
        k_hat = _isotropic_unit_vectors(rng, MODES)
        k = k_hat * _von_karman_wavenumbers(rng, MODES, turb.length_scale_m)[:, None]
        self._k = k[:, :2]  # the horizontal plane of the vehicles: z = 0
        self._omega = rng.standard_cauchy(MODES) / turb.time_scale_s
        # Kraichnan: each mode's amplitude is perpendicular to its wavenumber (incompressible);
        # sqrt(3 / (2 N)) makes each horizontal component's variance sigma^2.
        scale = turb.sigma_m_s * math.sqrt(3.0 / (2.0 * MODES))
        self._a = scale * np.cross(rng.standard_normal((MODES, 3)), k_hat)[:, :2]
        self._b = scale * np.cross(rng.standard_normal((MODES, 3)), k_hat)[:, :2]
        self._mean = np.array(wind.mean_m_s)

    def turbulence(self, t_s: float, positions_m: np.ndarray) -> np.ndarray:
        """The turbulent part (N, 2) [m/s] at `positions_m` (N, 2) and time t_s."""
        if self.wind.turbulence.sigma_m_s == 0.0:
            return np.zeros((len(positions_m), 2))
        carried = positions_m - self._mean * t_s  # where each point was in the air at t = 0
        phase = carried @ self._k.T + self._omega * t_s  # (N, modes)
        return np.cos(phase) @ self._a + np.sin(phase) @ self._b

    def local(self, t_s: float, x_m: float, y_m: float) -> tuple[float, float]:
        """Turbulence and gusts at (x_m, y_m) and time t_s [m/s]: what `Wind.at` leaves out."""
        n = e = 0.0
        if self.wind.turbulence.sigma_m_s > 0.0:
            n, e = self.turbulence(t_s, np.array([[x_m, y_m]]))[0].tolist()
        for gust in self.wind.gusts:
            gn, ge = gust.at(t_s, x_m, y_m)
            n, e = n + gn, e + ge
        return n, e

    def at(self, t_s: float, x_m: float, y_m: float) -> tuple[float, float]:
        """The whole wind (North, East) at (x_m, y_m) and time t_s [m/s]."""
        base_n, base_e = self.wind.at(t_s)
        if not self.wind.varies_in_space:
            return base_n, base_e
        n, e = self.local(t_s, x_m, y_m)
        return base_n + n, base_e + e


def von_karman_correlation(r_over_l: np.ndarray) -> np.ndarray:
    """Longitudinal correlation f(r) of von Kármán turbulence at separation r / L:
    2^(2/3) / Gamma(1/3) * x^(1/3) K_(1/3)(x), x = r / (1.339 L) (what `check` reports)."""
    from scipy.special import gamma, kv

    x = np.maximum(np.asarray(r_over_l, dtype=float), 1e-12) / VON_KARMAN_SCALE
    return 2.0 ** (2.0 / 3.0) / gamma(1.0 / 3.0) * x ** (1.0 / 3.0) * kv(1.0 / 3.0, x)
