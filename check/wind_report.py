"""What a scenario's wind means at the vehicle, in m/s, for `fleetmpc check` (docs/design.md,
"Wind")."""

import math

import numpy as np

from fleetmpc.onboard.core.formation import Formation
from fleetmpc.scenario import Scenario
from fleetmpc.sitl.wind import Gust, Wind, von_karman_correlation

__all__ = ["CROSS_TRACK_GAIN_PER_M", "cross_track_time_s", "wind_lines"]

CROSS_TRACK_GAIN_PER_M = 0.7
"""kappa of the controller's cross-track loop, omega_y = sqrt(kappa V) at airspeed V [1/m]: a
unicycle moves sideways only by turning, so it answers a change of cross wind through its
heading, a double integrator whose gain grows with the speed. Identified from known-model
lockstep runs at 0.7 and 1.4 m/s (docs/design.md, "What the controller leaves of the wind")."""


def cross_track_time_s(airspeed_m_s: float) -> float:
    """1 / omega_y: how long the controller takes to answer a change of cross wind [s]."""
    return 1.0 / math.sqrt(CROSS_TRACK_GAIN_PER_M * max(airspeed_m_s, 0.1))


def wind_lines(sc: Scenario) -> list[str]:
    """One line per part of the fleet's wind (none for a calm scenario)."""
    winds = {v.truth.wind for v in sc.vehicles}
    lines = []
    for wind in sorted(winds, key=repr):
        whose = "" if len(winds) == 1 else f" (vehicles {_ids_with(sc, wind)})"
        lines += _lines_of(wind, sc, whose)
    return lines


def _ids_with(sc: Scenario, wind: Wind) -> str:
    return ", ".join(str(v.id) for v in sc.vehicles if v.truth.wind == wind)


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
    if not wind.is_steady and sc.learning.enabled:
        lines.append(_learner_line(sc, whose))
    return lines


def _learner_line(sc: Scenario, whose: str) -> str:
    """How well the learned drift can follow the wind from the reported ground velocity
    (docs/design.md, "The wind's two parts"): the steady state of the scalar Kalman filter of a
    Gauss-Markov gust (sigma, T) measured each period with noise sigma_v, its error and the
    bandwidth -ln(phi (1 - K)) / tau at which it follows."""
    s, tau = sc.learning, sc.controller.period_s
    sigma, T, R = s.gust_std_m_s, s.gust_time_constant_s, s.measurement_velocity_std_m_s**2
    if sigma == 0.0:
        return f"wind{whose}: the learned drift follows it as a slow random walk only"
    phi = math.exp(-tau / T)
    P = sigma * sigma  # (iterate the Riccati recursion to its fixed point)
    for _ in range(1000):
        prior = phi * phi * P + sigma * sigma * (1.0 - phi * phi)
        P = prior * R / (prior + R)
    gain = prior / (prior + R)
    bandwidth = -math.log(phi * (1.0 - gain)) / tau
    return (
        f"wind{whose}: the learned drift's gust part is {sigma:.3f} m/s over {T:.1f} s; from "
        f"the ground velocity (noise {math.sqrt(R):.2f} m/s) it follows the wind with a "
        f"bandwidth of {bandwidth:.2f} rad/s and an error of about {math.sqrt(P):.3f} m/s RMS"
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
    """What the wind costs the formation even known: its change over the cross-track loop's
    time t_y, which puts the vehicle half of it times t_y off (the mean of a ramp)."""
    airspeed = sc.controller.reference_speed_m_s
    t_y = cross_track_time_s(airspeed)
    change = wind.change_m_s(airspeed, t_y)
    lines = []
    if change > 0.0:
        lines.append(
            f"wind{whose}: even known, it costs about {0.5 * t_y * change:.3f} m of slot RMS "
            f"(add it to the calm-air figure in quadrature; a learned run flies above it): the "
            f"cross-track loop answers in {t_y:.1f} s at {airspeed:.2f} m/s, over which it "
            f"changes by {change:.3f} m/s RMS"
        )
    for gust in wind.gusts:
        # A 1 - cos gust of A over D seconds changes by at most A sin(pi t / D) in t.
        step = math.hypot(*gust.amplitude_m_s) * math.sin(math.pi * min(t_y / gust.duration_s, 0.5))
        lines.append(
            f"wind{whose}: even known, the gust at t = {gust.onset_s:g} s puts a vehicle about "
            f"{0.5 * t_y * step:.3f} m off its slot at its steepest (cross-track loop: "
            f"{t_y:.1f} s at {airspeed:.2f} m/s)"
        )
    return lines


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
    d = Formation(sc.formation).desired_distances()
    np.fill_diagonal(d, np.inf)
    return float(d.min())
