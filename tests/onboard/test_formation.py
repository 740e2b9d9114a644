import math

import numpy as np
import pytest

from fleetmpc.onboard.core.config import FormationSettings
from fleetmpc.onboard.core.formation import (
    MIN_COURSE_RATE_RAD_S,
    REVERSAL_BAND_RAD,
    SPEED_RESERVE,
    CourseRateLimit,
    Formation,
    FormationReference,
    course_rate_limit,
    true_reference,
)
from fleetmpc.onboard.core.target_path import CHORD_HALF_M, TargetPath

DT = 0.2


def _fixed_limit(rate_rad_s: float) -> CourseRateLimit:
    """The same course-rate limit at every speed (no lever arm)."""
    return CourseRateLimit(
        speed_bound_m_s=math.inf, yaw_rate_bound_rad_s=2.0 * rate_rad_s, lever_m=0.0
    )


def _reference(trail_m: float = 5.0, rate: float = 0.05, frame: str = "course"):
    formation = Formation(FormationSettings(slots_m=((0.0, 0.0),), frame=frame, trail_m=trail_m))
    return FormationReference(formation, _fixed_limit(rate))


def _fly(ref, positions, velocities, std=0.0):
    """Follow the target through positions and velocities (K, 2): centres (K, 2), courses."""
    out = [
        ref.follow(p, v, DT, velocity_std_m_s=std)
        for p, v in zip(positions, velocities, strict=True)
    ]
    return np.array([c for c, _ in out]), np.array([c for _, c in out])


def _line(course: float, seconds: float, speed: float = 1.0, start=(0.0, 0.0)):
    t = DT * np.arange(int(round(seconds / DT)))
    u = np.array([math.cos(course), math.sin(course)])
    return np.asarray(start) + speed * t[:, None] * u, np.tile(speed * u, (len(t), 1))


def test_on_a_straight_line_the_centre_trails_the_target_by_d_s():
    p, v = _line(0.7, 30.0)
    centres, courses = _fly(_reference(trail_m=6.0), p, v)
    u = np.array([math.cos(0.7), math.sin(0.7)])
    np.testing.assert_allclose(centres, p - 6.0 * u, atol=1e-9)
    np.testing.assert_allclose(courses, 0.7, atol=1e-12)


def test_on_a_steady_turn_the_centre_stays_on_the_path_and_the_course_follows_without_lag():
    radius, speed = 40.0, 1.0
    w = speed / radius
    t = DT * np.arange(1500)
    p = radius * np.column_stack([np.sin(w * t), 1.0 - np.cos(w * t)])
    v = speed * np.column_stack([np.cos(w * t), np.sin(w * t)])
    centres, courses = _fly(_reference(trail_m=10.0), p, v)
    late = t > 60.0
    # d_s of arc behind the target, moved inside the turn by about CHORD_HALF_M^2 / (6 R).
    back = w * (t - 10.0 / speed)
    on_path = radius * np.column_stack([np.sin(back), 1.0 - np.cos(back)])
    inside = np.linalg.norm(centres - on_path, axis=1)[late]
    assert np.all(np.abs(inside - CHORD_HALF_M**2 / (6.0 * radius)) < 0.01)
    # Its course is the path's there, the tangent at the centre: no lag.
    np.testing.assert_allclose(np.unwrap(courses)[late], back[late], atol=2e-3)


def test_jitter_of_an_estimated_path_reaches_the_course_and_the_centre_attenuated():
    rng = np.random.default_rng(0)
    p, v = _line(0.0, 120.0)
    noisy = p + 0.03 * rng.standard_normal(p.shape)
    centres, courses = _fly(_reference(trail_m=10.0), noisy, v)
    # (rad; a position jitter of 3 cm at each end of an 8 m chord: sqrt(2) 0.03 / 8 = 0.0053)
    assert np.std(courses[100:]) < 0.006
    assert np.std(centres[100:, 1]) < 0.01  # (across the path)
    # Along the path the centre steps as the target's estimate does, no more.
    steps = np.linalg.norm(np.diff(centres[100:], axis=0), axis=1)
    target_steps = np.linalg.norm(np.diff(noisy[100:], axis=0), axis=1)
    assert np.std(steps) <= np.std(target_steps)


def test_a_corner_becomes_a_sweep_at_the_rate_limit_when_the_centre_gets_there():
    p1, v1 = _line(0.0, 40.0)
    p2, v2 = _line(math.pi / 2, 80.0, start=p1[-1] + v1[-1] * DT)
    p, v = np.vstack([p1, p2]), np.vstack([v1, v2])
    centres, courses = _fly(_reference(trail_m=5.0, rate=0.05), p, v)
    steps = np.diff(courses)
    t = DT * np.arange(len(p))
    # Nothing turns before the centre's window reaches the corner (d_s - CHORD_HALF_M after
    # the target's), then the course sweeps at the limit and settles on the new course.
    assert np.all(np.abs(courses[t < 40.0 + (5.0 - CHORD_HALF_M) - DT]) < 1e-9)
    assert np.all(np.abs(steps) <= 0.05 * DT + 1e-12)
    assert np.sum(np.isclose(steps, 0.05 * DT)) > 100
    assert courses[-1] == pytest.approx(math.pi / 2, abs=1e-6)
    # The centre goes round the corner smoothly: its speed dips, it never jumps.
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=1) / DT
    assert speed.max() < 1.0 + 1e-6 and speed[t[1:] > 50.0].min() > 0.6


@pytest.mark.parametrize("side", [-1.0, 1.0])
def test_a_reversal_sweeps_to_starboard_whichever_side_the_noise_puts_it(side):
    out, v_out = _line(0.0, 50.0)
    lateral = side * 0.05  # (the way back a few centimetres to either side of the way out)
    back, v_back = _line(math.pi, 90.0, start=out[-1] + (0.0, lateral))
    p, v = np.vstack([out, back]), np.vstack([v_out, v_back])
    centres, courses = _fly(_reference(trail_m=5.0, rate=0.05), p, v)
    steps = np.diff(courses)
    # (The way back beside the way out tilts the path's course there, as the chord shortens
    # to the fold, by up to the lateral offset over FOLD_SHARE of the window: 0.02 rad here.)
    assert courses.min() > -0.03 and courses[-1] == pytest.approx(math.pi, abs=0.01)
    assert np.sum(np.isclose(steps, 0.05 * DT)) > 100  # to starboard, at the limit
    # The centre goes on to where the target turned and comes back behind it.
    assert centres[:, 0].max() == pytest.approx(50.0 - DT, abs=CHORD_HALF_M / 2)
    assert centres[-1, 0] == pytest.approx(p[-1, 0] + 5.0, abs=0.05)
    # A sharp turn outside the band takes the short way, as any corner does.
    turn, v_turn = _line(-(math.pi - 1.5 * REVERSAL_BAND_RAD), 30.0, start=out[-1])
    _, courses = _fly(_reference(trail_m=5.0), np.vstack([out, turn]), np.vstack([v_out, v_turn]))
    assert courses[-1] < 0.0


def test_a_target_that_stops_leaves_the_centre_where_the_path_puts_it_despite_an_overshoot():
    p, v = _line(0.0, 30.0)
    stop = p[-1] + v[-1] * DT
    # An estimate that overshoots the stop by 30 cm, moving, then comes back and settles.
    over = stop + np.array([[0.15, 0.0], [0.3, 0.0], [0.2, 0.0], [0.1, 0.0]])
    v_over = np.array([[0.75, 0.0], [0.5, 0.0], [-0.5, 0.0], [-0.5, 0.0]])
    still = np.tile(stop, (100, 1))
    positions = np.vstack([p, over, still])
    velocities = np.vstack([v, v_over, np.zeros((100, 2))])
    centres, courses = _fly(_reference(trail_m=5.0), positions, velocities)
    assert centres[-1] == pytest.approx(stop - (5.0, 0.0), abs=0.02)
    assert courses[-1] == pytest.approx(0.0, abs=1e-3)
    # Moving on, it resumes from where it stopped, with no jump.
    on, v_on = _line(0.0, 10.0, start=stop)
    ref = _reference(trail_m=5.0)
    _fly(ref, positions, velocities)
    centres_on, _ = _fly(ref, on, v_on)
    assert np.max(np.linalg.norm(np.diff(centres_on, axis=0), axis=1)) < 0.25


def test_a_target_that_never_moves_has_no_course_and_its_jitter_lays_no_path():
    rng = np.random.default_rng(1)
    still = 0.02 * rng.standard_normal((300, 2))
    velocity = 0.05 * rng.standard_normal((300, 2))  # (its uncertainty: 0.05 m/s)
    ref = _reference(trail_m=6.0)
    centres, courses = _fly(ref, still, velocity, std=0.05)
    assert ref.value is None and np.all(courses == 0.0)  # (North, while unknown)
    np.testing.assert_allclose(centres, still - (6.0, 0.0), atol=0.01)
    assert ref.path.length_m == 0.0


def test_ahead_places_the_prediction_as_following_would_and_leaves_the_state_alone():
    p, v = _line(0.3, 20.0)
    ref, copy = _reference(trail_m=2.0), _reference(trail_m=2.0)
    _fly(ref, p[:80], v[:80])
    _fly(copy, p[:80], v[:80])
    state = (ref.value, ref.path.length_m, list(ref.path.xs))
    ahead = ref.ahead([tuple(x) for x in p[80:90]], [tuple(x) for x in v[80:90]], DT)
    assert (ref.value, ref.path.length_m, list(ref.path.xs)) == state
    followed = [copy.follow(x, y, DT) for x, y in zip(p[80:90], v[80:90], strict=True)]
    for (c1, k1), (c2, k2) in zip(ahead, followed, strict=True):
        assert c1 == pytest.approx(c2, abs=1e-9) and k1 == pytest.approx(k2, abs=1e-9)


@pytest.mark.parametrize("moved", [True, False])
def test_ahead_of_a_stopped_target_the_centre_stays_where_it_is(moved):
    """A stopped target's prediction lays no path: its positions, a few centimetres from where
    the target was placed on its path (an estimate), are placed there too. Laid as path, the
    first step ahead moved the centre by that gap, and the slots' first chord with it (a steady
    yaw rate beyond the limit for a vehicle holding station in a wind)."""
    ref = _reference(trail_m=5.0)
    if moved:
        p, v = _line(0.0, 30.0)
        _fly(ref, p, v)
        stop = p[-1] + v[-1] * DT
    else:
        stop = np.zeros(2)
    estimate = stop + (0.03, 0.04)  # (off the path, as an estimate is)
    _fly(ref, np.tile(estimate, (20, 1)), np.full((20, 2), 0.01), std=0.02)
    centre, course = ref.follow(estimate, (0.01, 0.01), DT, velocity_std_m_s=0.02)
    track = [tuple(estimate + 0.002 * j) for j in range(1, 10)]
    ahead = ref.ahead(track, [(0.01, 0.01)] * 9, DT, velocity_std_m_s=0.02)
    centres = np.array([centre, *(c for c, _ in ahead)])
    moved_by = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.all(moved_by <= 0.002 * math.sqrt(2.0) + 1e-9)  # (no more than the target)
    assert all(k == pytest.approx(course) for _, k in ahead)


def test_a_paths_moments_kept_up_as_points_come_match_moments_computed_afresh():
    rng = np.random.default_rng(4)
    path = TargetPath(tail_m=10.0, keep_m=20.0)
    for k in range(300):  # (a wavy path; some steps shorter than the spacing, replaced)
        step = 0.02 if k % 7 == 0 else 0.2
        x, y = step * k, math.sin(0.02 * k) * 5.0 + 0.01 * rng.standard_normal()
        path.extend(x, y, 0.0)
        path.at(path.length_m - 5.0)  # (its moments: now kept up as points come)
        ahead = path.copy()
        for j in range(1, 8):
            ahead.extend(x + 0.2 * j, y, 0.0)
            ahead.at(ahead.length_m - 5.0)
        fresh = ahead.copy()
        fresh._moments = None  # (recomputed from the points)
        for s in (ahead.length_m - 5.0, ahead.length_m - 1.0):
            (c1, k1), (c2, k2) = ahead.at(s), fresh.at(s)
            assert c1 == pytest.approx(c2, abs=1e-9) and k1 == pytest.approx(k2, abs=1e-9)


def test_a_path_keeps_only_what_the_centre_can_reach():
    path = TargetPath(tail_m=10.0, keep_m=20.0)
    for x in np.arange(0.0, 200.0, 0.2):
        path.extend(float(x), 0.0, 0.0)
    assert path.length_m == pytest.approx(199.8)
    assert path.ss[0] >= path.length_m - 20.5 and len(path.xs) < 110
    assert path.point_at(path.length_m - 15.0) == pytest.approx((184.8, 0.0))


def test_the_rate_limit_spends_the_spare_speed_on_the_longest_lever():
    course_frame = Formation(
        FormationSettings(slots_m=((0.0, 0.0), (-3.0, 4.0)), frame="course", trail_m=5.0)
    )
    np.testing.assert_allclose(course_frame.lever_arms_m(), [0.0, 5.0])
    limit = course_rate_limit(course_frame, speed_bound_m_s=1.9, yaw_rate_bound_rad_s=0.4)
    assert limit.at(1.0) == pytest.approx((1 - SPEED_RESERVE) * 0.9 / 5.0)
    # A slower target leaves more spare speed for the turn; one at the bound leaves the floor.
    assert limit.at(0.5) == pytest.approx((1 - SPEED_RESERVE) * 1.4 / 5.0)
    assert limit.at(1.9) == MIN_COURSE_RATE_RAD_S
    world = Formation(FormationSettings(slots_m=((0.0, 0.0), (0.0, 10.0)), trail_m=5.0))
    np.testing.assert_allclose(world.lever_arms_m(), [0.0, 0.0])  # (it does not turn)
    fast = course_rate_limit(world, speed_bound_m_s=1.9, yaw_rate_bound_rad_s=0.4)
    assert fast.at(1.0) == pytest.approx(0.2)  # half the tightened yaw-rate bound
    assert _fixed_limit(0.05).at(1.7) == 0.05


def test_the_reference_turns_faster_where_the_target_slows_down():
    formation = Formation(
        FormationSettings(slots_m=((0.0, 0.0), (0.0, 5.0)), frame="course", trail_m=2.0)
    )
    limit = course_rate_limit(formation, speed_bound_m_s=1.8, yaw_rate_bound_rad_s=0.4)
    swept = []
    for speed in (1.2, 0.6):
        p1, v1 = _line(0.0, 20.0, speed=speed)
        p2, v2 = _line(math.pi / 2, 20.0, speed=speed, start=p1[-1])
        _, courses = _fly(FormationReference(formation, limit), np.vstack([p1, p2]),
                          np.vstack([v1, v2]))  # fmt: skip
        swept.append(np.max(np.diff(courses)) / DT)
    assert swept == pytest.approx([limit.at(1.2), limit.at(0.6)])
    assert swept[1] > 1.5 * swept[0]


def test_slots_turn_with_the_reference_course_about_the_centre():
    f = Formation(FormationSettings(slots_m=((2.0, 1.0),), frame="course", trail_m=5.0))
    slots = f.slots(np.array([[10.0, 0.0], [10.0, 0.0]]), [0.0, math.pi / 2])
    np.testing.assert_allclose(slots[0, 0], [12.0, 1.0])
    np.testing.assert_allclose(slots[1, 0], [9.0, 2.0], atol=1e-12)
    world = Formation(FormationSettings(slots_m=((2.0, 1.0),), trail_m=5.0))
    np.testing.assert_allclose(world.slots(np.array([[10.0, 0.0]]), [1.0])[0, 0], [12.0, 1.0])


def test_the_true_reference_of_a_run_is_the_stateful_one_period_by_period():
    p1, v1 = _line(0.0, 40.0)
    p2, v2 = _line(math.pi / 2, 40.0, start=p1[-1])
    p, v = np.vstack([p1, p2]), np.vstack([v1, v2])
    formation = Formation(FormationSettings(slots_m=((0.0, 0.0),), frame="course", trail_m=5.0))
    limit = _fixed_limit(0.04)
    ref = FormationReference(formation, limit)
    one_by_one = [ref.follow(a, b, DT) for a, b in zip(p.tolist(), v.tolist(), strict=True)]
    centres, courses = true_reference(formation, limit, p, v, DT)
    np.testing.assert_allclose(centres, [c for c, _ in one_by_one], atol=1e-12)
    np.testing.assert_allclose(courses, [k for _, k in one_by_one], atol=1e-12)


def test_an_estimate_that_settles_sweeps_as_the_truth_does_on_a_turn_beyond_the_limit():
    """A target circling faster than r_max: the agents' reference and the judge's both turn at
    the limit for as long as it circles, so a lead either takes at the start is kept. The
    agents' estimate starts at a few cm/s; the speed the limit reads, slewed up from there, took
    20 s to reach the target's, while the reference turned faster than the judge's (a 25 m
    circle, 12 m lever arms: 0.04 rad of formation, 0.4 m at the outer slots, for good)."""
    formation = Formation(
        FormationSettings(slots_m=((0.0, 12.0), (0.0, -12.0)), frame="course", trail_m=6.0)
    )
    limit = course_rate_limit(formation, speed_bound_m_s=1.6, yaw_rate_bound_rad_s=0.45)
    radius, speed = 25.0, 1.0
    assert limit.at(speed) < speed / radius  # (the circle turns faster than the limit)
    t = DT * np.arange(300)
    w = speed / radius
    p = radius * np.column_stack([np.sin(w * t), 1.0 - np.cos(w * t)])
    v = speed * np.column_stack([np.cos(w * t), np.sin(w * t)])
    _, truth = _fly(FormationReference(formation, limit), p, v)
    # The estimate: its velocity settles over the first 0.6 s, uncertain until then (as the
    # target filter's does); the judge has the truth from the start.
    settle = np.clip(t / 0.6, 0.0, 1.0)[:, None]
    stds = np.where(t < 0.6, 0.5, 0.02)
    estimate = FormationReference(formation, limit)
    courses = np.array(
        [estimate.follow(a, b, DT, velocity_std_m_s=s)[1]
         for a, b, s in zip(p, settle * v, stds, strict=True)]
    )  # fmt: skip
    # Left: what the circle turned beyond the limit before the estimate's path told a course
    # (about 1.4 s at 0.015 rad/s); it was 0.1 rad.
    np.testing.assert_allclose(courses[t > 20.0], truth[t > 20.0], atol=0.015)
