import dataclasses

import numpy as np
import pytest

from fleetmpc.onboard.core.config import LearningSettings
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.sitl.plant import TruthParams, TruthPlant
from fleetmpc.sitl.wind import Wind

TAU = 0.2
TRUTH = TruthParams(
    speed_effectiveness=0.85,
    yaw_rate_effectiveness=1.10,
    actuator_lag_s=0.1,
    wind=Wind(mean_m_s=(0.3, -0.2)),
    position_noise_m=0.05,
    heading_noise_rad=0.01,
)


def _exciting_input(t: float) -> np.ndarray:
    return np.array([1.2 + 0.6 * np.sin(0.3 * t), 0.35 * np.sin(0.25 * t)])


def _fly(settings: LearningSettings, seconds: float, seed: int, inputs=_exciting_input):
    plant = TruthPlant(TRUTH, x_m=0.0, y_m=0.0, yaw_rad=0.0)
    rng = np.random.default_rng(seed)
    f = DualEkf(settings, tau=TAU)
    u = np.zeros(2)
    history = []
    for k in range(int(round(seconds / TAU)) + 1):
        f.step(plant.measure(rng)[:3], u)
        history.append((k * TAU, f.beta.copy(), f.P_p.copy()))
        u = inputs(k * TAU)
        plant.command(*u)
        plant.advance(20_000_000, 10)
    return f, history, plant


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dekf_learns_effectiveness_and_wind_by_20_s(seed):
    f, _, _ = _fly(LearningSettings(), 20.0, seed)
    a_v, a_w, d_x, d_y = f.beta
    assert a_v == pytest.approx(0.85, rel=0.05)
    assert a_w == pytest.approx(1.10, rel=0.05)
    assert abs(d_x - 0.3) <= 0.05
    assert abs(d_y + 0.2) <= 0.05


def test_beta_stays_put_and_bounded_without_excitation():
    def excite_then_hover(t):
        return _exciting_input(t) if t < 20.0 else np.zeros(2)

    _, history, _ = _fly(LearningSettings(), 80.0, 4, excite_then_hover)
    # The stop itself excites a_V (a change of speed no wind mimics) while the autopilot's lag
    # flies it out (a few tenths of a second); from then on, hovering, nothing does.
    learned = next(b for t, b, _ in history if t >= 21.0)
    final = history[-1][1]
    # Nothing excites the effectiveness parameters while hovering: they must not wander.
    assert abs(final[0] - learned[0]) < 1e-9
    assert abs(final[1] - learned[1]) < 1e-9
    # The drift stays observable (wind moves a hovering vehicle) and stays right.
    assert abs(final[2] - 0.3) < 0.05 and abs(final[3] + 0.2) < 0.05
    s = LearningSettings()
    for _, b, P_p in history:
        assert np.all(b >= np.array(s.beta_min)) and np.all(b <= np.array(s.beta_max))
        assert np.all(np.diag(P_p)[:4] <= np.square(s.beta_std_initial) * (1 + 1e-9))


def test_learning_off_keeps_beta_nominal():
    f, _, _ = _fly(dataclasses.replace(LearningSettings(), enabled=False), 10.0, 5)
    np.testing.assert_array_equal(f.beta, [1.0, 1.0, 0.0, 0.0])


def test_divergence_guard_resets_and_counts():
    s = LearningSettings()
    f = DualEkf(s, tau=TAU)
    f.step(np.zeros(3), np.zeros(2))
    f.step(np.array([1e6, -1e6, 0.0]), np.array([1.0, 0.0]))  # a jump no model explains
    assert f.resets == 1
    np.testing.assert_allclose(f.z, [1e6, -1e6, 0.0])
    assert np.all(np.isfinite(f.beta))
    with np.errstate(invalid="ignore"):
        f.step(np.array([np.nan, 0.0, 0.0]), np.array([1.0, 0.0]))
    assert f.resets == 2 and np.all(np.isfinite(f.beta))


def test_with_the_ground_velocity_a_gusty_wind_is_not_blamed_on_the_vehicle():
    """A wind swinging by 0.2 m/s every 20 s, learned as the drift's gust part from the
    measured ground velocity: a_V ends within 3 % and the drift follows the wind closely."""
    gusty = dataclasses.replace(
        TRUTH,
        wind=Wind(mean_m_s=(0.3, -0.2), gust_amplitude_m_s=0.2, gust_period_s=20.0),
        velocity_noise_m_s=0.05,
    )
    settings = LearningSettings(gust_std_m_s=0.14, gust_time_constant_s=3.2)
    plant = TruthPlant(gusty, x_m=0.0, y_m=0.0, yaw_rad=0.0)
    rng = np.random.default_rng(7)
    f = DualEkf(settings, tau=TAU)
    u = np.zeros(2)
    drift_errors = []
    for k in range(int(90 / TAU)):
        f.step(plant.measure(rng), u)
        if k * TAU >= 60:
            drift_errors.append(np.hypot(*(f.beta[2:] - plant.wind_m_s)))
        u = _exciting_input(k * TAU)
        plant.command(*u)
        plant.advance(20_000_000, 10)
    assert f.beta[0] == pytest.approx(0.85, rel=0.03)
    assert f.beta[1] == pytest.approx(1.10, rel=0.03)
    assert np.sqrt(np.mean(np.square(drift_errors))) < 0.07  # (0.17 without the gust part)
