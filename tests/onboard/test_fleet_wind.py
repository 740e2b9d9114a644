"""The fleet's wind: pooling the neighbours' wind samples, and what it buys the drift."""

import dataclasses
import math

import numpy as np
import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.onboard.core.fleet_wind import WindPool, memory_periods
from fleetmpc.protocol.plan import Plan, WindSample
from fleetmpc.sitl.plant import TruthParams, TruthPlant
from fleetmpc.sitl.wind import Wind

TAU = 0.2
PERIOD_NS = 200_000_000


def _plan(x: float, y: float, stamp_ns: int, wind: WindSample | None) -> Plan:
    return Plan(1, stamp_ns, PERIOD_NS, np.array([[x, y, 0.0]] * 2), np.zeros((1, 2)), wind)


def _across(heading: float, wind: tuple[float, float]) -> float:
    return -math.sin(heading) * wind[0] + math.cos(heading) * wind[1]


def test_samples_taken_here_and_now_pool_to_their_mean_and_its_variance():
    pool = WindPool(LearningSettings(), tau=TAU)  # (no gust: the samples differ by noise alone)
    samples = [WindSample(0.0, 0.2, 0.1), WindSample(0.0, 0.4, 0.1)]
    plans = [_plan(5.0 * i, 0, 0, w) for i, w in enumerate(samples)]
    pooled = pool.pool(plans, (0, 0, 0), (0, 0), 0)
    assert pooled.direction == pytest.approx((0.0, 1.0))  # (heading North: across is East)
    assert pooled.across_m_s == pytest.approx(0.3)
    assert pooled.variance == pytest.approx(0.01 / 2) and pooled.samples == 2


def test_a_neighbour_heading_a_little_off_is_told_apart_by_the_own_drift():
    wind, off = (0.3, 0.2), math.radians(20.0)
    pool = WindPool(LearningSettings(), tau=TAU)
    sample = WindSample(off, _across(off, wind), 0.05)
    pooled = pool.pool([_plan(0, 0, 0, sample)], (0, 0, 0), wind, 0)
    assert pooled.across_m_s == pytest.approx(_across(0.0, wind))
    turned = WindSample(math.radians(90.0), 0.3, 0.05)
    assert pool.pool([_plan(0, 0, 0, turned)], (0, 0, 0), wind, 0) is None


def test_a_sample_from_farther_or_longer_ago_weighs_less():
    settings = LearningSettings(gust_std_m_s=0.1, gust_time_constant_s=5.0, wind_length_m=20.0)
    pool = WindPool(settings, tau=TAU)
    near, far = WindSample(0.0, 0.0, 0.05), WindSample(0.0, 1.0, 0.05)
    apart = pool.pool([_plan(0, 0, 0, near), _plan(20, 0, 0, far)], (0, 0, 0), (0, 0), 0)
    later = pool.pool([_plan(0, 0, 10**9, near), _plan(0, 0, 0, far)], (0, 0, 0), (0, 0), 10**9)
    assert 0.0 < apart.across_m_s < 0.2 and 0.0 < later.across_m_s < 0.5
    assert pool.pool([_plan(0, 0, 0, None)], (0, 0, 0), (0, 0), 0) is None


def test_a_uniform_wind_weighs_distance_not_at_all():
    settings = LearningSettings(gust_std_m_s=0.1, wind_length_m=math.inf)
    pool = WindPool(settings, tau=TAU)
    plans = [_plan(0, 0, 0, WindSample(0, 0.0, 0.05)), _plan(500, 0, 0, WindSample(0, 1.0, 0.05))]
    assert pool.pool(plans, (0, 0, 0), (0, 0), 0).across_m_s == pytest.approx(0.5)


@pytest.mark.parametrize(
    "sigma, T, noise", [(0.08, 5.8, 0.05), (0.15, 3.7, 0.05), (0.03, 12.0, 0.02)]
)
def test_memory_is_one_over_the_steady_gain_of_the_iterated_riccati_recursion(sigma, T, noise):
    F2 = math.exp(-2 * TAU / T)
    Q, R, P = sigma**2 * (1 - F2), noise**2, sigma**2
    for _ in range(10_000):  # the filter's own recursion, run to its steady state
        prior = F2 * P + Q
        P = prior * R / (prior + R)
    settings = LearningSettings(
        gust_std_m_s=sigma, gust_time_constant_s=T, measurement_velocity_std_m_s=noise
    )
    assert memory_periods(settings, TAU) == pytest.approx((prior + R) / prior, rel=1e-9)


def _fly_fleet(share: bool, seed: int) -> tuple[float, list[float]]:
    """Four vehicles 10 m apart in one wind swinging by 0.2 m/s every 20 s, each learning from
    its own noisy pose and ground velocity, and, with `share`, from the others' samples of the
    period before: the drift's RMS error across the heading over the last 30 s, and the
    learned a_V."""
    truth = TruthParams(
        speed_effectiveness=0.9,
        yaw_rate_effectiveness=1.1,
        actuator_lag_s=0.1,
        wind=Wind(mean_m_s=(0.3, -0.2), gust_amplitude_m_s=0.2, gust_period_s=20.0),
        position_noise_m=0.05,
        heading_noise_rad=0.01,
        velocity_noise_m_s=0.05,
    )
    settings = LearningSettings(gust_std_m_s=0.14, gust_time_constant_s=3.2, wind_length_m=math.inf)
    plants = [TruthPlant(truth, x_m=0.0, y_m=10.0 * i, yaw_rad=0.0) for i in range(4)]
    filters = [DualEkf(settings, tau=TAU) for _ in plants]
    pool, rng, errors = WindPool(settings, tau=TAU), np.random.default_rng(seed), []
    plans: list[Plan] = []
    for k in range(int(90 / TAU)):
        u = np.array([1.2 + 0.6 * np.sin(0.3 * k * TAU), 0.2 * np.sin(0.25 * k * TAU)])
        stamp = k * PERIOD_NS
        heard = []
        for i, (plant, f) in enumerate(zip(plants, filters, strict=True)):
            y = plant.measure(rng)
            others = [p for j, p in enumerate(plans) if j != i]
            pose, drift = (y[0], y[1], y[2]), (f.beta[2], f.beta[3])
            f.step(y, u, shared=pool.pool(others, pose, drift, stamp) if share else None)
            heard.append(_plan(y[0], y[1], stamp, f.wind_sample))
            if k * TAU >= 60:
                across = np.array((-np.sin(f.z[2]), np.cos(f.z[2])))
                errors.append(across.dot(f.beta[2:] - plant.wind_m_s))
            plant.command(*u)
            plant.advance(20_000_000, 10)
        plans = heard
    return float(np.sqrt(np.mean(np.square(errors)))), [f.beta[0] for f in filters]


@pytest.mark.parametrize("seed", [3, 4])
def test_the_neighbours_samples_bring_the_drift_closer_to_the_wind(seed):
    alone, _ = _fly_fleet(False, seed)
    shared, a_v = _fly_fleet(True, seed)
    assert shared < 0.8 * alone, (shared, alone)
    assert a_v == pytest.approx([0.9] * 4, rel=0.03)


def test_a_plan_carries_the_sample_its_filter_measured():
    f = DualEkf(dataclasses.replace(LearningSettings(), gust_std_m_s=0.1), tau=TAU)
    f.step(np.array([0.0, 0.0, 0.0, 0.0, 0.0]), np.zeros(2))
    assert f.wind_sample is None  # (the first measurement starts the filter)
    f.step(np.array([0.2, 0.0, 0.0, 1.0, 0.1]), np.array([1.0, 0.0]))
    w = f.wind_sample
    assert w is not None and w.std_m_s >= 0.05
    across = np.array((-np.sin(w.heading_rad), np.cos(w.heading_rad))).dot((1.0, 0.1))
    assert w.across_m_s == pytest.approx(across)  # (the ground velocity across the heading)


@pytest.mark.parametrize(
    "field, value",
    [("wind_length_m", 0.0), ("wind_length_m", math.nan), ("wind_length_m", True),
     ("fleet_wind", "yes")],
)  # fmt: skip
def test_a_bad_fleet_wind_setting_is_refused_naming_it(field, value):
    with pytest.raises(ConfigError, match=f"learning.{field}"):
        LearningSettings(**{field: value})
