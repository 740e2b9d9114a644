"""The fleet's wind: the neighbours' wind samples pooled into one measurement of this vehicle's
drift (docs/design.md, "The fleet's wind").

Every learning agent broadcasts, with its plan, the wind it measured this period across its
heading: its ground velocity's component along n = (-sin heading, cos heading), where its own
airspeed adds nothing (`protocol.plan.WindSample`). Only that component is shared: along the
heading the wind is known only through the vehicle's learned speed effectiveness, whose error
the fleet would share too (vehicles flying the same commands learn the same error, and pooled,
it would confirm itself). A neighbour's sample n'w measures this vehicle's wind across n,
less well: it was taken r metres away and a few tenths of a second ago, and the wind's changing
part (the learned gust, intensity sigma, time constant T) differs between two such points by a
variance of

    D(r, age) = 2 sigma^2 (1 - exp(-r / L - age / T))

(L, the distance over which the gusts decorrelate, `LearningSettings.wind_length_m`; the mean
wind is the same everywhere). That difference is no sensor noise: it stays for seconds, while
the drift's filter takes each period's sample as new and averages about 1 / K of them (K its
steady-state gain on a sample of the gust, `memory_periods`). D is counted that many times, so
that the samples together carry no more than the difference allows.

The samples tell this vehicle its wind across its own heading n_i only. Across it, the wind is
what a unicycle answers slowest (by turning, docs/design.md, "What the controller leaves of the
wind"); along it, the wind and a_V share one measurement, and any bias there from a neighbour
would be learned as a_V. A neighbour heading within `MAX_HEADING_OFF` of this vehicle's
measures s_j = n_j'w; its wind across n_i is s_j less (n_j - n_i)'d^ (this vehicle's own drift
estimate d^ makes up the small part along its track). Each is then a measurement of n_i'd, of
the drift d = m + g, with the variance std_j^2 + D_j / K. `WindPool.pool` returns their mean
weighed by those variances, a_j the weights (summing to 1), with the variance
sum a_j^2 std_j^2 + (sum a_j sqrt(D_j / K))^2: the sensors' errors are independent and average
out, the differences are not (neighbours close to each other differ from this vehicle's wind
alike, and all their samples are a period old) and are taken as fully correlated.
"""

import math
from collections.abc import Iterable
from dataclasses import dataclass

from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.onboard.core.unicycle import wrap
from fleetmpc.protocol.plan import Plan

__all__ = ["PooledWind", "WindPool", "gust_filter", "memory_periods"]


@dataclass(frozen=True)
class PooledWind:
    """The neighbours' samples as one measurement of this vehicle's drift across its heading."""

    direction: tuple[float, float]
    """n_i = (-sin heading, cos heading) of this vehicle (North, East)."""
    across_m_s: float
    """The drift along n_i [m/s]."""
    variance: float
    """Its error variance [m^2/s^2]."""
    samples: int
    """How many neighbours' samples went in."""


MAX_HEADING_OFF = math.radians(30.0)
"""A neighbour heading farther from this vehicle's measures too little of its cross wind."""


def gust_filter(settings: LearningSettings, tau: float) -> tuple[float, float] | None:
    """The drift's filter of the gust from the ground velocity in steady state: the prior
    variance P and the gain K = P / (P + R) of a Gauss-Markov gust (sigma, T) sampled every tau
    with the velocity sensor's noise R, from the scalar Riccati equation
    P = F^2 P R / (P + R) + Q solved for P; None without a gust part."""
    sigma, T = settings.gust_std_m_s, settings.gust_time_constant_s
    R = settings.measurement_velocity_std_m_s**2
    if sigma == 0.0:
        return None
    F2 = math.exp(-2.0 * tau / T)
    Q = sigma * sigma * (1.0 - F2)
    b = R * (1.0 - F2) - Q
    prior = 0.5 * (-b + math.sqrt(b * b + 4.0 * Q * R))
    return prior, prior / (prior + R)


def memory_periods(settings: LearningSettings, tau: float) -> float:
    """How many periods' samples the drift's filter averages, 1 / K (`gust_filter`); 1 without
    a gust part."""
    steady = gust_filter(settings, tau)
    return 1.0 if steady is None else 1.0 / steady[1]


class WindPool:
    """One agent's pooling of the neighbours' wind samples (its settings, once)."""

    def __init__(self, settings: LearningSettings, *, tau: float) -> None:
        self.length_m = settings.wind_length_m
        self.time_constant_s = settings.gust_time_constant_s
        self.spread = 2.0 * settings.gust_std_m_s**2 * memory_periods(settings, tau)
        """2 sigma^2 / K: D's scale, counted over the filter's memory."""

    def pool(
        self,
        plans: Iterable[Plan],
        pose: tuple[float, float, float],
        drift: tuple[float, float],
        stamp_ns: int,
    ) -> PooledWind | None:
        """This vehicle's wind across its heading from the samples that the plans carry, each
        weighed by its own error and by how far (from `pose`, x, y, heading) and how long ago
        (before `stamp_ns`) it was taken; `drift` is this vehicle's own estimate (North, East).
        None without any sample from a vehicle heading close enough."""
        x, y, heading = pose
        n_i = (-math.sin(heading), math.cos(heading))
        heard = []  # (value, sensor variance, difference variance)
        for plan in plans:
            w = plan.wind
            if w is None or abs(wrap(w.heading_rad - heading)) > MAX_HEADING_OFF:
                continue
            px, py, _ = plan.states[0].tolist()
            age_s = max(0.0, (stamp_ns - plan.stamp_ns) * 1e-9)
            apart = math.hypot(px - x, py - y) / self.length_m
            difference = self.spread * (1.0 - math.exp(-apart - age_s / self.time_constant_s))
            n_j = (-math.sin(w.heading_rad), math.cos(w.heading_rad))
            along_part = (n_j[0] - n_i[0]) * drift[0] + (n_j[1] - n_i[1]) * drift[1]
            heard.append((w.across_m_s - along_part, w.std_m_s**2, difference))
        if not heard:
            return None
        weights = [1.0 / (noise + difference) for _, noise, difference in heard]
        share = [wt / sum(weights) for wt in weights]
        value = sum(a * v for a, (v, _, _) in zip(share, heard, strict=True))
        noise = sum(a * a * n for a, (_, n, _) in zip(share, heard, strict=True))
        difference = sum(a * math.sqrt(d) for a, (_, _, d) in zip(share, heard, strict=True))
        return PooledWind(n_i, value, noise + difference**2, len(heard))
