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
that the samples together carry no more than the difference allows. Each sample is then a
measurement n_j'd of the drift d = m + g with the variance v_j = std_j^2 + D / K. Taken as
independent, k of them carry the information A = sum n_j n_j' / v_j, b = sum n_j s_j / v_j, and
as many measurements as A has non-zero eigenvalues (one while the fleet flies parallel, two
when headings differ) carry exactly as much: e_i'd = e_i'b / l_i with variance 1 / l_i for each
eigenpair (l_i, e_i) of A. `WindPool.pool` returns those.
"""

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.protocol.plan import Plan

__all__ = ["PooledWind", "WindPool", "memory_periods"]


@dataclass(frozen=True)
class PooledWind:
    """The neighbours' samples as one or two measurements of this vehicle's drift."""

    directions: np.ndarray
    """Unit vectors (k, 2) (North, East) along which the drift is measured."""
    values: np.ndarray
    """The drift along each [m/s] (k,)."""
    variances: np.ndarray
    """Their error variances [m^2/s^2] (k,)."""
    samples: int
    """How many neighbours' samples went in."""


def memory_periods(settings: LearningSettings, tau: float) -> float:
    """How many periods' samples the drift's filter averages, 1 / K: K is the steady-state
    Kalman gain of a Gauss-Markov gust (sigma, T) sampled every tau with the velocity sensor's
    noise, from the scalar Riccati equation P = F^2 P R / (P + R) + Q solved for the prior P."""
    sigma, T = settings.gust_std_m_s, settings.gust_time_constant_s
    R = settings.measurement_velocity_std_m_s**2
    if sigma == 0.0:
        return 1.0
    F2 = math.exp(-2.0 * tau / T)
    Q = sigma * sigma * (1.0 - F2)
    b = R * (1.0 - F2) - Q
    prior = 0.5 * (-b + math.sqrt(b * b + 4.0 * Q * R))
    return (prior + R) / prior


class WindPool:
    """One agent's pooling of the neighbours' wind samples (its settings, once)."""

    def __init__(self, settings: LearningSettings, *, tau: float) -> None:
        self.length_m = settings.wind_length_m
        self.time_constant_s = settings.gust_time_constant_s
        self.spread = 2.0 * settings.gust_std_m_s**2 * memory_periods(settings, tau)
        """2 sigma^2 / K: D's scale, counted over the filter's memory."""

    def pool(
        self, plans: Iterable[Plan], position: tuple[float, float], stamp_ns: int
    ) -> PooledWind | None:
        """The wind samples that the plans carry, each weighed by its own error and by how far
        (from `position` [m]) and how long ago (before `stamp_ns`) it was taken, as the
        measurements along the eigenvectors of their information; None without any sample."""
        x, y = position
        A, b = np.zeros((2, 2)), np.zeros(2)
        count = 0
        for plan in plans:
            w = plan.wind
            if w is None:
                continue
            px, py, _ = plan.states[0].tolist()
            age_s = max(0.0, (stamp_ns - plan.stamp_ns) * 1e-9)
            apart = math.hypot(px - x, py - y) / self.length_m
            kept = math.exp(-apart - age_s / self.time_constant_s)
            weight = 1.0 / (w.std_m_s**2 + self.spread * (1.0 - kept))
            n = np.array((-math.sin(w.heading_rad), math.cos(w.heading_rad)))
            A += weight * np.outer(n, n)
            b += weight * w.across_m_s * n
            count += 1
        if count == 0:
            return None
        info, vectors = np.linalg.eigh(A)
        keep = info > _RANK * info[-1]
        e, info = vectors[:, keep].T, info[keep]
        return PooledWind(e, e.dot(b) / info, 1.0 / info, count)


_RANK = 1e-6
"""Eigenvalues of the samples' information below this share of the largest carry nothing (a
fleet that flies parallel measures the wind across its heading only)."""
