import math

import numpy as np
import pytest

from fleetmpc.onboard.core.config import FormationSettings
from fleetmpc.onboard.core.formation import (
    COURSE_GAIN_PER_S,
    MIN_COURSE_RATE_RAD_S,
    REVERSAL_BAND_RAD,
    SPEED_RESERVE,
    STOPPING_SHARE,
    CourseRateLimit,
    Formation,
    ReferenceCourse,
    TrueReference,
    course_rate_limit,
    reference_courses,
)


def _velocity(course: float, speed: float = 1.0) -> tuple[float, float]:
    return speed * math.cos(course), speed * math.sin(course)


def test_a_corner_becomes_a_sweep_at_the_rate_limit():
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    ref.follow(_velocity(0.0), 0.2)
    values = [ref.follow(_velocity(math.pi / 2), 0.2) for _ in range(400)]
    steps = np.diff([0.0, *values])
    # It sweeps at exactly the limit until it is close, then settles on the new course.
    assert steps[:100] == pytest.approx(0.05 * 0.2)
    assert values[-1] == pytest.approx(math.pi / 2, abs=1e-3)
    assert np.all(np.abs(steps) <= 0.05 * 0.2 + 1e-12)


def test_a_replay_turns_as_the_reference_would_have_from_a_past_value():
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    ref.follow(_velocity(0.0), 0.2)
    replayed = ref.replay(0.0, _velocity(math.pi / 2), 0.2, 10, turn_rate_rad_s=0.0)
    assert ref.value == 0.0  # (the state stays)
    followed = [ref.follow(_velocity(math.pi / 2), 0.2) for _ in range(10)][-1]
    assert replayed == pytest.approx(followed) == pytest.approx(0.05 * 0.2 * 10)
    assert ref.replay(0.3, _velocity(1.0), 0.2, 0) == 0.3


def test_a_steady_turn_below_the_limit_is_followed_without_lag():
    rate, dt = 0.03, 0.2
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    courses = rate * dt * np.arange(300)
    for c in courses:
        value = ref.follow(_velocity(c), dt, turn_rate_rad_s=rate)
    assert value == pytest.approx(courses[-1], abs=1e-9)


def test_course_noise_reaches_the_reference_attenuated():
    rng = np.random.default_rng(0)
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    noise = 0.02 * rng.standard_normal(500)
    values = [ref.follow(_velocity(n), 0.2) for n in noise]
    assert np.std(values[50:]) < 0.3 * np.std(noise)
    assert COURSE_GAIN_PER_S * 0.2 < 0.1


def test_a_still_target_keeps_the_course_and_ahead_leaves_the_state_alone():
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    assert ref.follow((0.0, 0.0), 0.2) is None
    ref.follow(_velocity(1.0), 0.2)
    assert ref.follow((0.01, 0.0), 0.2) == pytest.approx(1.0)
    ahead = ref.ahead([_velocity(2.0)] * 5, 0.2)
    assert ahead == pytest.approx([1.0 + 0.01 * k for k in range(1, 6)])
    assert ref.value == pytest.approx(1.0)


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_a_reversal_sweeps_to_starboard_whichever_side_the_noise_puts_it(side):
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    ref.follow(_velocity(0.0), 0.2)
    back = math.pi + side * 0.9 * REVERSAL_BAND_RAD  # (just inside the band, either side)
    values = [ref.follow(_velocity(back), 0.2) for _ in range(5)]
    assert np.diff([0.0, *values]) == pytest.approx(0.05 * 0.2)  # positive: to the right
    # A sharp turn outside the band takes the short way, as any corner does.
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    ref.follow(_velocity(0.0), 0.2)
    assert ref.follow(_velocity(-(math.pi - 1.1 * REVERSAL_BAND_RAD)), 0.2) < 0.0


def test_a_target_that_stops_mid_sweep_leaves_the_reference_turning_on_to_its_last_course():
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    ref.follow(_velocity(0.0), 0.2)
    for _ in range(10):  # a corner of 90 degrees: the sweep begins
        ref.follow(_velocity(math.pi / 2), 0.2)
    assert ref.value == pytest.approx(0.1)
    for _ in range(400):  # then it stops
        ref.follow((0.0, 0.0), 0.2)
    assert ref.value == pytest.approx(math.pi / 2, abs=1e-3)


def test_an_estimate_swinging_past_zero_as_the_target_stops_says_nothing_of_its_course():
    ref = ReferenceCourse(CourseRateLimit.fixed(0.05))
    for _ in range(20):
        ref.follow(_velocity(0.0), 0.2)
    # The velocity estimate of a target that stopped at once overshoots backwards, slower than
    # a third of its speed: the reference keeps its course instead of reversing.
    swing = 0.9 * STOPPING_SHARE
    for speed in (swing, swing, 0.5 * swing, 0.1, 0.0):
        assert ref.follow(_velocity(math.pi, speed), 0.2) == pytest.approx(0.0)


def test_the_rate_limit_spends_the_spare_speed_on_the_longest_lever():
    course_frame = Formation(
        FormationSettings(slots_m=((0.0, 0.0), (-3.0, 4.0)), frame="course", trail_m=5.0)
    )
    np.testing.assert_allclose(course_frame.lever_arms_m(), [5.0, math.hypot(8.0, 4.0)])
    limit = course_rate_limit(course_frame, speed_bound_m_s=1.9, yaw_rate_bound_rad_s=0.4)
    lever = math.hypot(8.0, 4.0)
    assert limit.at(1.0) == pytest.approx((1 - SPEED_RESERVE) * 0.9 / lever)
    # A slower target leaves more spare speed for the turn; one at the bound leaves the floor.
    assert limit.at(0.5) == pytest.approx((1 - SPEED_RESERVE) * 1.4 / lever)
    assert limit.at(1.9) == MIN_COURSE_RATE_RAD_S
    world = Formation(FormationSettings(slots_m=((0.0, 0.0), (0.0, 10.0)), trail_m=5.0))
    np.testing.assert_allclose(world.lever_arms_m(), [5.0, 5.0])
    fast = course_rate_limit(world, speed_bound_m_s=10.0, yaw_rate_bound_rad_s=0.4)
    assert fast.at(1.0) == pytest.approx(0.2)  # half the tightened yaw-rate bound
    assert CourseRateLimit.fixed(0.05).at(1.7) == 0.05


def test_the_reference_turns_faster_where_the_target_slows_down():
    limit = course_rate_limit(
        Formation(FormationSettings(slots_m=((0.0, 0.0),), frame="course", trail_m=10.0)),
        speed_bound_m_s=1.8,
        yaw_rate_bound_rad_s=0.4,
    )
    swept = []
    for speed in (1.2, 0.6):
        ref = ReferenceCourse(limit)
        ref.follow(_velocity(0.0, speed), 0.2)
        swept.append(ref.follow(_velocity(math.pi / 2, speed), 0.2) / 0.2)
    assert swept == pytest.approx([limit.at(1.2), limit.at(0.6)])
    assert swept[1] == pytest.approx(2.0 * swept[0])


def test_slots_turn_with_the_reference_course():
    f = Formation(FormationSettings(slots_m=((2.0, 1.0),), frame="course", trail_m=5.0))
    slots = f.slots(np.array([[10.0, 0.0], [10.0, 0.0]]), [0.0, math.pi / 2])
    np.testing.assert_allclose(slots[0, 0], [10.0 - 5.0 + 2.0, 1.0])
    np.testing.assert_allclose(slots[1, 0], [10.0 - 1.0, -5.0 + 2.0], atol=1e-12)


def test_the_true_reference_of_a_run_is_the_stateful_one_period_by_period():
    t = 0.2 * np.arange(400)
    course = np.where(t < 40.0, 0.0, math.pi / 2)
    v = np.column_stack([np.cos(course), np.sin(course)])
    ref = TrueReference(CourseRateLimit.fixed(0.04))
    one_by_one = [ref.follow(tuple(x), 0.2) for x in v]
    np.testing.assert_allclose(
        reference_courses(v, 0.2, CourseRateLimit.fixed(0.04)), one_by_one, atol=1e-12
    )
    assert max(np.diff(one_by_one)) <= 0.04 * 0.2 + 1e-12
