"""Target lost, target back (`fleetmpc.onboard.core.target_watch`): the prediction flown for a
bounded time, then a braked hold, then a glide back without a jump; slow and bursty streams stay
tracked."""

import math

import numpy as np
import pytest

from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.target_watch import (
    HOLDING,
    PREDICTING,
    REACQUIRING,
    TRACKING,
    TargetWatch,
)

S = 1_000_000_000
PERIOD = S // 5


def _watch() -> TargetWatch:
    return TargetWatch(
        lost_s=2.0, predict_s=6.0, reacquire_s=3.0, glide_speed_m_s=1.0, brake_m_s2=0.5
    )


def _walk(t_ns: int) -> np.ndarray:
    """A target due North at 1 m/s."""
    return np.array([t_ns * 1e-9, 0.0])


def _fly(watch, estimator, stamps, until_ns):
    """Observations at `stamps`, the watch asked every period until `until_ns`; the states and
    the followed positions (now) by period."""
    states, followed = [], []
    pending = list(stamps)
    for t in range(0, until_ns, PERIOD):
        while pending and pending[0] <= t:
            watch.observe(estimator, pending[0], _walk(pending[0]))
            pending.pop(0)
        if estimator.ready:
            positions, _ = watch.track(estimator, t, PERIOD, 3)
            states.append(watch.state)
            followed.append(positions[0])
    return states, np.array(followed)


@pytest.mark.parametrize(
    "stamps",
    [
        list(range(0, 30 * S, S)),  # (1 Hz)
        [b + k * PERIOD // 5 for b in range(0, 30 * S, 3 * S // 2) for k in range(5)],  # (bursts)
    ],
)
def test_a_slow_or_bursty_stream_stays_tracked(stamps):
    watch, est = _watch(), TargetEstimator(observation_std_m=0.1)
    states, followed = _fly(watch, est, stamps, 30 * S)
    assert set(states) == {TRACKING} and watch.losses == 0
    assert followed[-1] == pytest.approx((29.8, 0.0), abs=0.3)


def test_lost_predicted_held_braked_then_glides_back_without_a_jump():
    watch, est = _watch(), TargetEstimator(observation_std_m=0.1)
    stamps = [k * PERIOD for k in range(int(20 * S / PERIOD))]  # (fixes until 20 s)
    stamps += [k * PERIOD for k in range(int(40 * S / PERIOD), int(60 * S / PERIOD))]
    states, followed = _fly(watch, est, stamps, 60 * S)
    t = np.arange(len(states)) * 0.2
    at = {name: t[[s == name for s in states]] for name in (PREDICTING, HOLDING, REACQUIRING)}
    assert at[PREDICTING].min() == pytest.approx(22.0)  # (2 s after the last, at 19.8 s)
    assert at[HOLDING].min() == pytest.approx(26.0)  # (6 s after it)
    assert at[REACQUIRING].min() == pytest.approx(40.0)
    assert watch.losses == 1
    # Predicted: straight on at 1 m/s; held: braked at 0.5 m/s^2 (1 m further), then standing.
    k26 = int(round(25.8 / 0.2))
    assert followed[k26, 0] == pytest.approx(25.8, abs=0.1)
    held = followed[(t >= 29.0) & (t < 40.0)]
    assert np.ptp(held[:, 0]) < 1e-9 and held[0, 0] == pytest.approx(25.8 + 1.0, abs=0.1)
    # The followed target never jumps: at most glide speed plus the target's own per period,
    # and it is back on the target once the glide is over (13 m at 1 m/s more than the
    # target's: about 13 s).
    steps = np.linalg.norm(np.diff(followed, axis=0), axis=1)
    assert steps.max() <= 0.2 * (1.0 + 1.0) + 0.05
    assert states[-1] == TRACKING
    assert followed[-1] == pytest.approx((59.8, 0.0), abs=0.3)


def test_an_observation_rejected_by_the_estimator_changes_nothing():
    watch, est = _watch(), TargetEstimator(observation_std_m=0.1)
    assert watch.observe(est, 0, np.array([0.0, 0.0]))
    assert not watch.observe(est, S, np.array([math.nan, 0.0]))
    assert not watch.observe(est, 0, np.array([1.0, 0.0]))  # (not after the last)
    watch.track(est, 5 * S, PERIOD, 1)
    assert watch.state == PREDICTING
