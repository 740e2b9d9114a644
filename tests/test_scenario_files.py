"""Every file in scenarios/ validates; the suite's scenarios hold what their headers promise."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from fleetmpc.check.feasibility import check_scenario
from fleetmpc.gcs.metrics import corner_indices
from fleetmpc.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted((ROOT / "scenarios").glob("*.toml"))

SUITE = {  # name: (vehicles, horizon)
    "square": (4, 8),
    "uturn-start": (4, 5),
    "figure-eight": (4, 8),
    "grid9": (9, 5),
}
"""The scenarios written for `fleetmpc suite`."""


def _target_track(sc: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times, positions and velocities of the target at every control period of the run."""
    period_ns = sc.controller.period_ns
    t = np.arange(round(sc.duration_s * 1e9 / period_ns) + 1) * period_ns * 1e-9  # as lockstep
    states = [sc.target.state_at(float(ti)) for ti in t]
    return t, np.array([p for p, _ in states]), np.array([v for _, v in states])


def _slots_at_start(sc: Scenario) -> np.ndarray:
    """Every slot (N, 2) at t = 0, where the formation's course is the target's: the centre trails
    the target by trail_m along it, offsets (forward, right) rotate with it in the course frame."""
    (tx, ty), (vx, vy) = sc.target.state_floats(0.0)
    c = math.atan2(vy, vx)
    u = np.array([math.cos(c), math.sin(c)])
    offsets = np.array(sc.formation.slots_m)
    if sc.formation.frame == "course":
        offsets = offsets[:, :1] * u + offsets[:, 1:] * np.array([-u[1], u[0]])
    return np.array([tx, ty]) - sc.formation.trail_m * u + offsets


def _suite(name: str) -> Scenario:
    return load_scenario(ROOT / "scenarios" / f"{name}.toml")


def test_the_suite_scenarios_are_there():
    assert {f.stem for f in FILES} >= set(SUITE) | {"paper", "paper-strict", "wedge-circle"}


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_every_scenario_file_validates(path):
    sc = load_scenario(path)
    assert sc.name == path.stem
    assert sc.controller.period_ns % sc.plant_steps_per_period == 0
    assert Path(sc.source) == path
    assert path.read_text().startswith("#"), "a header comment says what the scenario tests"


@pytest.mark.parametrize("name", sorted(SUITE))
def test_suite_scenarios_fly_the_common_setup(name):
    sc = _suite(name)
    vehicles, horizon = SUITE[name]
    c = sc.controller
    assert len(sc.vehicles) == vehicles and c.horizon == horizon
    assert (c.speed_max_m_s, c.yaw_rate_max_rad_s, c.d_safe_m) == (2.0, 0.5, 2.0)
    assert (sc.target.observation_noise_m, sc.target.observation_rate_hz) == (0.05, 5.0)
    assert sc.learning.enabled
    for v in sc.vehicles:
        t = v.truth
        assert 0.85 <= t.speed_effectiveness <= 1.15 and 0.85 <= t.yaw_rate_effectiveness <= 1.15
        assert (t.actuator_lag_s, t.position_noise_m, t.heading_noise_rad) == (0.1, 0.05, 0.01)
        assert 0.2 <= math.hypot(*t.wind.mean_m_s) <= 0.35
        assert 0.0 < t.wind.gust_amplitude_m_s <= 0.1 and t.wind.gust_period_s >= 60.0
    effectiveness = {
        (v.truth.speed_effectiveness, v.truth.yaw_rate_effectiveness) for v in sc.vehicles
    }
    assert len(effectiveness) == vehicles  # each vehicle its own errors
    for i, a in enumerate(sc.vehicles):
        for b in sc.vehicles[i + 1 :]:
            gap = math.hypot(a.initial[0] - b.initial[0], a.initial[1] - b.initial[1])
            assert gap >= 3.0, (a.id, b.id)


@pytest.mark.parametrize("name", sorted(SUITE))
def test_the_gate_window_starts_25_s_after_the_last_sharp_manoeuvre(name):
    sc = _suite(name)
    t, _, vel = _target_track(sc)
    corners = corner_indices(vel)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    assert speed.min() > 0.5 and speed.max() <= 1.31  # moving all along, about 1 m/s
    if name == "square":
        # one corner every 40 s, seen at the first period past it
        assert t[corners] == pytest.approx([40.0, 80.0, 120.0, 160.0], abs=0.21)
    else:
        assert corners == []
    last = t[corners[-1]] if corners else 0.0
    assert sc.duration_s - 10.0 >= last + 25.0


@pytest.mark.parametrize("name", sorted(set(SUITE) - {"square"}))
def test_the_targets_are_feasible_in_speed(name):
    report = check_scenario(_suite(name))
    assert report.feasible, report.problems


def test_the_square_has_40_m_sides_and_runs_on_past_its_last_corner():
    sc = _suite("square")
    pts = np.array(sc.target.waypoints_m)
    sides = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    assert list(sides[:4]) == [40.0] * 4 and pts[4].tolist() == pts[0].tolist()
    assert sc.target.speed_m_s == 1.0 and sc.controller.reference_speed_m_s == 1.0
    assert sides[4] > sc.duration_s - 160.0  # still flying straight when the run ends
    assert sc.duration_s - 160.0 == pytest.approx(36.0)


@pytest.mark.parametrize("name", ["square", "figure-eight", "grid9"])
def test_vehicles_start_near_their_slots(name):
    sc = _suite(name)
    for v, s in zip(sc.vehicles, _slots_at_start(sc), strict=True):
        assert math.hypot(v.initial[0] - s[0], v.initial[1] - s[1]) <= 2.5, v.id


def test_uturn_start_puts_every_vehicle_ahead_of_the_target_facing_its_course():
    sc = _suite("uturn-start")
    assert sc.formation.frame == "course" and sc.duration_s == 60.0
    assert sorted(max(abs(x), abs(y)) for x, y in sc.formation.slots_m) == [7.0] * 4
    (tx, ty), (vx, vy) = sc.target.state_floats(0.0)
    course = math.atan2(vy, vx)
    for v in sc.vehicles:
        ahead = (v.initial[0] - tx) * math.cos(course) + (v.initial[1] - ty) * math.sin(course)
        assert 10.0 <= ahead <= 20.0, v.id
        assert abs(math.remainder(v.initial[2] - course, math.tau)) < 1e-3, v.id
    # every slot is behind the target: each vehicle must turn round
    for s in _slots_at_start(sc):
        assert (s[0] - tx) * math.cos(course) + (s[1] - ty) * math.sin(course) < 0.0


def test_figure_eight_speed_and_turns_stay_gentle_for_one_whole_eight():
    sc = _suite("figure-eight")
    assert sc.target.kind == "figure_eight" and sc.formation.frame == "course"
    assert sc.duration_s >= sc.target.period_s + 10.0
    t, _, vel = _target_track(sc)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    assert speed.min() >= 0.6 and speed.max() <= 1.3 + 1e-3
    rate = np.gradient(np.unwrap(np.arctan2(vel[:, 1], vel[:, 0])), t)
    assert rate.max() > 0.03 and rate.min() < -0.03  # right and left
    assert (speed / np.maximum(np.abs(rate), 1e-12)).min() >= 12.0  # path radius


def test_grid9_is_a_3_by_3_world_frame_grid_of_6_m():
    sc = _suite("grid9")
    assert sc.formation.frame == "world"
    assert sorted(sc.formation.slots_m) == [
        (x, y) for x in (-6.0, 0.0, 6.0) for y in (-6.0, 0.0, 6.0)
    ]
    assert sc.target.kind == "circle" and sc.target.radius_m == 60.0
    assert sc.duration_s == 60.0


HARD = sorted((ROOT / "scenarios" / "hard").glob("*.toml"))


@pytest.mark.parametrize("path", HARD, ids=[p.stem for p in HARD])
def test_the_hard_cases_are_feasible_scenarios_whose_first_slots_are_near_their_vehicles(path):
    """scenarios/hard/ holds cases kept to measure against, not broken files: each validates, its
    target is feasible, and every vehicle starts within 40 m of its first slot."""
    sc = load_scenario(path)
    assert check_scenario(sc).feasible
    starts = np.array([v.initial[:2] for v in sc.vehicles])
    assert np.hypot(*(starts - _slots_at_start(sc)).T).max() < 40.0


CORNERS = sorted((ROOT / "scenarios" / "corners").glob("*.toml"))
"""Compact formations at sharp corners, kept to measure against (their headers say how they fly)."""


@pytest.mark.parametrize("path", CORNERS, ids=lambda p: p.stem)
def test_the_corner_studies_are_feasible_course_frame_rings(path):
    sc = load_scenario(path)
    assert check_scenario(sc).feasible, path
    assert sc.formation.frame == "course" and len(sc.vehicles) == 6


def test_check_gives_each_vehicles_slack_to_its_separation_margin():
    # A pair keeps d_safe + s + 2 r_M = 2 + (2 * 2 * 0.2)^2 / 16 + 2 * 0.174 = 2.39 m.
    ring = load_scenario(ROOT / "scenarios" / "corners" / "compact-ring.toml")
    text = check_scenario(ring).render()
    assert "the closest slots, 3.00 m apart, leave each vehicle 0.31 m to its margin" in text
    assert "(a pair keeps 2.39 m)" in text
    tight = dataclasses.replace(ring, controller=dataclasses.replace(ring.controller, d_safe_m=2.8))
    report = check_scenario(tight)
    assert not report.feasible
    assert any("can never both be on their slots" in p for p in report.problems), report.problems
