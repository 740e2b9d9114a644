"""What a scenario's wind means at the vehicle, in m/s, for `fleetmpc check` (docs/design.md,
"Wind")."""

import math
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.fleet_wind import gust_filter
from fleetmpc.onboard.core.formation import Formation
from fleetmpc.scenario import Scenario
from fleetmpc.sitl.wind import Gust, Wind, von_karman_correlation

__all__ = [
    "CROSS_TRACK_GAIN_PER_M",
    "DriftFilter",
    "cross_track_time_s",
    "drift_filter",
    "learner_noise_lines",
    "wind_lines",
    "wind_share_m",
]

CROSS_TRACK_GAIN_PER_M = 0.7
"""kappa of the controller's cross-track loop, omega_y = sqrt(kappa V) at airspeed V [1/m]: a
unicycle moves sideways only by turning, so it answers a change of cross wind through its
heading, a double integrator whose gain grows with the speed. Identified from known-model
lockstep runs at 0.7 and 1.4 m/s (docs/design.md, "What the controller leaves of the wind")."""


def cross_track_time_s(airspeed_m_s: float) -> float:
    """1 / omega_y: how long the controller takes to answer a change of cross wind [s]."""
    return 1.0 / math.sqrt(CROSS_TRACK_GAIN_PER_M * max(airspeed_m_s, 0.1))


def wind_share_m(wind: Wind, airspeed_m_s: float, lag_s: float = 0.0) -> float:
    """The wind's share of the slot RMS [m]: its change over the cross-track loop's time t_y
    (plus `lag_s`, how late the controller learns of it), half of it times that time (the mean
    of a ramp; docs/design.md, "What the controller leaves of the wind")."""
    t = cross_track_time_s(airspeed_m_s) + lag_s
    return 0.5 * t * wind.change_m_s(airspeed_m_s, t)


@dataclass(frozen=True)
class DriftFilter:
    """The learned drift's gust part as a steady-state scalar Kalman filter: a Gauss-Markov gust
    (sigma, T) measured each period by the ground velocity with noise sigma_v."""

    sigma_m_s: float
    time_constant_s: float
    noise_m_s: float
    bandwidth_rad_s: float
    """-ln(phi (1 - K)) / tau: how fast the estimate follows the wind; its inverse is its lag."""
    error_m_s: float
    """The estimate's steady-state error, RMS."""


def drift_filter(sc: Scenario) -> DriftFilter | None:
    """The learned drift's filter (docs/design.md, "The wind's two parts"); None without a gust
    part (the drift is then a slow random walk only)."""
    s, tau = sc.learning, sc.controller.period_s
    steady = gust_filter(s, tau)
    if steady is None:
        return None
    prior, gain = steady
    phi = math.exp(-tau / s.gust_time_constant_s)
    bandwidth = -math.log(phi * (1.0 - gain)) / tau
    noise = s.measurement_velocity_std_m_s
    error = math.sqrt(prior * (1.0 - gain))
    return DriftFilter(s.gust_std_m_s, s.gust_time_constant_s, noise, bandwidth, error)


def wind_lines(sc: Scenario) -> list[str]:
    """One line per part of the fleet's wind (none for a calm scenario)."""
    winds = {v.truth.wind for v in sc.vehicles}
    lines = []
    for wind in sorted(winds, key=repr):
        whose = "" if len(winds) == 1 else f" (vehicles {', '.join(_ids_with(sc, 'wind', wind))})"
        lines += _lines_of(wind, sc, whose)
    return lines


def _ids_with(sc: Scenario, field: str, value: object) -> list[str]:
    """The ids of the vehicles whose truth's `field` is `value`."""
    return [str(v.id) for v in sc.vehicles if getattr(v.truth, field) == value]


def _lines_of(wind: Wind, sc: Scenario, whose: str) -> list[str]:
    lines = []
    n, e = wind.mean_m_s
    if n or e:
        toward = math.degrees(math.atan2(e, n)) % 360
        lines.append(f"wind{whose}: mean {math.hypot(n, e):.2f} m/s toward {toward:.0f} deg")
    if wind.gust_amplitude_m_s > 0:
        a, period = wind.gust_amplitude_m_s, wind.gust_period_s
        lines.append(
            f"wind{whose}: slow variation of +-{a:.2f} m/s on each axis over {period:g} s "
            f"(changes by up to {2 * math.pi * a / period:.3f} m/s per second)"
        )
    if wind.turbulence.sigma_m_s > 0:
        lines.append(_turbulence_line(wind, sc, whose))
    lines += [_gust_line(g, whose) for g in wind.gusts]
    if not wind.is_steady:
        lines += _limit_lines(wind, sc, whose)
        if sc.learning.enabled:
            lines.append(_learner_line(sc, whose))
            lines += _fleet_wind_lines(sc, whose)
    return lines


def _fleet_wind_lines(sc: Scenario, whose: str) -> list[str]:
    """Whether the vehicles hear each other's wind (docs/design.md, "The fleet's wind")."""
    s = sc.learning
    if not s.fleet_wind or len(sc.vehicles) < 2:
        return []
    apart = (
        "alike everywhere"
        if math.isinf(s.wind_length_m)
        else f"to decorrelate over {s.wind_length_m:g} m"
    )
    return [
        f"wind{whose}: each vehicle also pools the wind its neighbours measure across their "
        f"headings, their gusts taken {apart} (learning.wind_length_m)"
    ]


def _learner_line(sc: Scenario, whose: str) -> str:
    """How well the learned drift can follow the wind from the reported ground velocity."""
    f = drift_filter(sc)
    if f is None:
        return f"wind{whose}: the learned drift follows it as a slow random walk only"
    return (
        f"wind{whose}: the learned drift's gust part is {f.sigma_m_s:.3f} m/s over "
        f"{f.time_constant_s:.1f} s; from the ground velocity (noise {f.noise_m_s:.2f} m/s) it "
        f"follows the wind with a bandwidth of {f.bandwidth_rad_s:.2f} rad/s and an error of "
        f"about {f.error_m_s:.3f} m/s RMS"
    )


def _turbulence_line(wind: Wind, sc: Scenario, whose: str) -> str:
    turb, tau = wind.turbulence, sc.controller.period_s
    airspeed = sc.controller.reference_speed_m_s
    t_c = turb.correlation_time_s(airspeed)
    per_period = turb.sigma_m_s * math.sqrt(2.0 * (1.0 - math.exp(-tau / t_c)))
    spacing = _nearest_slot_spacing_m(sc)
    together = ""
    if spacing is not None:
        corr = float(von_karman_correlation(np.array(spacing / turb.length_scale_m)))
        together = f"; neighbours {spacing:.1f} m apart feel it correlated {corr:.2f}"
    return (
        f"wind{whose}: turbulence of {turb.sigma_m_s:.2f} m/s on each axis at the vehicle "
        f"(1 in 100 samples beyond {2.58 * turb.sigma_m_s:.2f} m/s), von Karman L = "
        f"{turb.length_scale_m:g} m, {turb.time_scale_s:g} s; at {airspeed:.2f} m/s through "
        f"the air a vehicle sees it change over {t_c:.1f} s, by {per_period:.3f} m/s RMS "
        f"per control period{together}"
    )


def _limit_lines(wind: Wind, sc: Scenario, whose: str) -> list[str]:
    """What the wind costs the formation even known, and learned (`wind_share_m`); each gust's
    largest offset likewise."""
    airspeed = sc.controller.reference_speed_m_s
    t_y = cross_track_time_s(airspeed)
    f = drift_filter(sc) if sc.learning.enabled else None
    lag = None if f is None else 1.0 / f.bandwidth_rad_s
    learned = "" if lag is None else f"; learned (the drift lags it by {lag:.2f} s), about "
    lines = []
    change = wind.change_m_s(airspeed, t_y)
    if change > 0.0:
        lines.append(
            f"wind{whose}: known, it costs about {wind_share_m(wind, airspeed):.3f} m of slot RMS "
            f"(add it to the calm-air figure in quadrature): the cross-track loop answers in "
            f"{t_y:.1f} s at {airspeed:.2f} m/s, over which it changes by {change:.3f} m/s RMS"
            + ("" if lag is None else f"{learned}{wind_share_m(wind, airspeed, lag):.3f} m")
        )
    for gust in wind.gusts:
        lines.append(
            f"wind{whose}: known, the gust at t = {gust.onset_s:g} s puts a vehicle about "
            f"{_gust_offset_m(gust, t_y):.3f} m off its slot at its steepest (cross-track loop: "
            f"{t_y:.1f} s at {airspeed:.2f} m/s)"
            + ("" if lag is None else f"{learned}{_gust_offset_m(gust, t_y + lag):.3f} m")
        )
    return lines


def _gust_offset_m(gust: Gust, t_s: float) -> float:
    """Half of t_s times the most a 1 - cos gust of A over D seconds changes in t_s,
    A sin(pi t / D) (the whole gust beyond D / 2) [m]."""
    rise = math.hypot(*gust.amplitude_m_s) * math.sin(math.pi * min(t_s / gust.duration_s, 0.5))
    return 0.5 * t_s * rise


def _gust_line(gust: Gust, whose: str) -> str:
    a_n, a_e = gust.amplitude_m_s
    toward = math.degrees(math.atan2(a_e, a_n)) % 360
    return (
        f"wind{whose}: 1 - cosine gust of {math.hypot(a_n, a_e):.2f} m/s toward {toward:.0f} deg,"
        f" {gust.length_m:g} m long, its front passing the origin at t = {gust.onset_s:g} s at "
        f"{gust.front_speed_m_s:g} m/s: a vehicle standing in it feels it for "
        f"{gust.duration_s:.1f} s, rising at up to "
        f"{math.pi * math.hypot(a_n, a_e) / gust.duration_s:.3f} m/s per second"
    )


def _nearest_slot_spacing_m(sc: Scenario) -> float | None:
    if len(sc.formation.slots_m) < 2:
        return None
    return Formation(sc.formation).closest_slots()[2]


def learner_noise_lines(sc: Scenario) -> list[str]:
    """A line where the learner takes the ground velocity's noise as other than the simulated
    vehicles' (by more than a tenth): its filter then weighs each measurement wrongly."""
    if not sc.learning.enabled:
        return []
    assumed = sc.learning.measurement_velocity_std_m_s
    noises = sorted({v.truth.velocity_noise_m_s for v in sc.vehicles})
    lines = []
    for noise in noises:
        if abs(noise - assumed) <= 0.1 * max(noise, assumed):
            continue
        ids = _ids_with(sc, "velocity_noise_m_s", noise)
        who = (
            f"vehicle {ids[0]} measures" if len(ids) == 1 else f"vehicles {', '.join(ids)} measure"
        )
        effect = (
            "it trusts each measurement less than it could, so its drift follows the wind "
            "more slowly than the sensor allows"
            if noise < assumed
            else "it trusts each measurement more than it should, so its drift carries more "
            "of the sensor's noise"
        )
        lines.append(
            f"learner: takes the ground velocity's noise as {assumed:.3f} m/s "
            f"([learning] measurement_velocity_std_m_s), {who} it with "
            f"{noise:.3f} m/s ([truth] velocity_noise_m_s): {effect}"
        )
    return lines
