import math

import numpy as np
import pytest

from fleetmpc.onboard.core.target_estimator import TargetEstimator, turn_motion
from fleetmpc.targets.script import TargetScript

PERIOD_NS = 200_000_000


def _track(script: TargetScript, seconds: float, horizon: int) -> tuple[list, TargetEstimator]:
    """Horizon-end prediction errors [m] after the first 5 s, and the filter."""
    rng = np.random.default_rng(3)
    est = TargetEstimator(observation_std_m=script.observation_noise_m)
    predictions, errors = {}, []
    for k in range(int(seconds / 0.2) + 1):
        est.observe(k * PERIOD_NS, script.observe(k * 0.2, rng))
        positions, _ = est.predicted_track(k * PERIOD_NS, PERIOD_NS, horizon + 1)
        predictions[k] = positions[horizon]
        if k - horizon in predictions and k * 0.2 > 5.0:
            truth, _ = script.state_at(k * 0.2)
            errors.append(float(np.hypot(*(np.array(predictions[k - horizon]) - truth))))
    return errors, est


def test_turn_motion_is_a_circle_and_a_line_at_zero_rate():
    x, y, vx, vy = turn_motion(0.0, 0.0, 1.0, 0.0, math.pi / 10, 10.0)  # half a turn
    assert (x, y) == pytest.approx((0.0, 20.0 / math.pi))
    assert (vx, vy) == pytest.approx((-1.0, 0.0))
    assert turn_motion(1.0, 2.0, 1.0, 0.5, 0.0, 2.0) == pytest.approx((3.0, 3.0, 1.0, 0.5))


@pytest.mark.parametrize(
    ("script", "limit_m"),
    [
        (
            TargetScript(kind="line", start_m=(5, 5), velocity_m_s=(1, 1),
                         observation_noise_m=0.05),
            0.1,
        ),
        (
            TargetScript(kind="circle", center_m=(0, 40), radius_m=40, speed_m_s=1.0,
                         start_angle_rad=math.pi, clockwise=False, observation_noise_m=0.05),
            0.15,
        ),
        (
            TargetScript(kind="circle", center_m=(0, 0), radius_m=15, speed_m_s=1.2,
                         clockwise=True, observation_noise_m=0.05),
            0.2,
        ),
    ],
)  # fmt: skip
def test_the_prediction_curves_with_the_target(script, limit_m):
    errors, _ = _track(script, 120.0, horizon=8)
    assert math.sqrt(np.mean(np.square(errors))) < limit_m


def test_a_corner_is_noticed_and_the_course_follows_within_seconds():
    square = TargetScript(
        kind="waypoints", waypoints_m=((0, 0), (40, 0), (40, 40)), speed_m_s=1.0,
        observation_noise_m=0.05,
    )  # fmt: skip
    rng = np.random.default_rng(5)
    est = TargetEstimator(observation_std_m=0.05)
    noticed, courses = None, []
    for k in range(int(50.0 / 0.2) + 1):
        t = k * 0.2
        est.observe(k * PERIOD_NS, square.observe(t, rng))
        if t < 39.0:
            assert not est.manoeuvring
        if t > 39.0 and noticed is None and est.manoeuvring:
            noticed = t
        if t >= 46.0:
            _, velocities = est.predicted_track(k * PERIOD_NS, PERIOD_NS, 1)
            courses.append(math.atan2(velocities[0][1], velocities[0][0]))
    assert noticed is not None and noticed < 41.0
    assert max(abs(c - math.pi / 2) for c in courses) < math.radians(10)


def test_the_steady_model_holds_a_line_and_the_turning_one_a_tightening_turn():
    line = TargetScript(kind="line", start_m=(0, 0), velocity_m_s=(1, 0.5),
                        observation_noise_m=0.05)  # fmt: skip
    eight = TargetScript(kind="figure_eight", center_m=(0, 0), radius_m=60.0, period_s=410.0,
                         observation_noise_m=0.05)  # fmt: skip
    rng = np.random.default_rng(7)
    for script, model, seconds in ((line, 0, 60.0), (eight, 1, 60.0)):
        est = TargetEstimator(observation_std_m=0.05)
        probabilities = []
        for k in range(int(seconds / 0.2) + 1):
            est.observe(k * PERIOD_NS, script.observe(k * 0.2, rng))
            probabilities.append(est.probabilities[model])
        assert np.mean(probabilities[len(probabilities) // 2 :]) > 0.6


def test_out_of_order_and_non_finite_observations_are_ignored():
    est = TargetEstimator(observation_std_m=0.05)
    assert est.observe(PERIOD_NS, np.array([1.0, 2.0]))
    assert not est.observe(PERIOD_NS, np.array([5.0, 5.0]))
    assert not est.observe(2 * PERIOD_NS, np.array([math.nan, 0.0]))
    assert est.observations == 1
    assert est.x[:2].tolist() == [1.0, 2.0]


def test_the_velocity_std_is_the_combined_covariances_after_every_observation():
    rng = np.random.default_rng(1)
    estimator = TargetEstimator(observation_std_m=0.05)
    for k in range(40):  # (a turn that tightens: the models disagree, their spread counts)
        p = np.array([0.2 * k, 0.01 * k * k]) + 0.05 * rng.standard_normal(2)
        estimator.observe(k * 200_000_000, p)
        P = estimator.P
        expected = math.sqrt(max(P[2, 2], P[3, 3]))
        assert estimator.velocity_std_m_s() == pytest.approx(expected, rel=1e-12)
