"""The scenario suite's gates, flown as `fleetmpc suite scenarios/ --seeds 3` flies them.

Every scenario of the repository x 3 seeds x learning on and off, in lockstep on a process pool
(about half a minute on two cores). Behaviour is counted in simulated time, never in wall time.
"""

import dataclasses
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

from fleetmpc.check.feasibility import check_scenario
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.lockstep.suite import (
    CORNER_RECOVERY_MAX_S,
    EFFECTIVENESS_ERROR_MAX,
    LEARNING_RATIO_MAX,
    PAPER_SLOT_RMS_MAX_M,
    QP_FALLBACK_MAX_FRACTION,
    REVERSALS_MAX_PER_VEHICLE_MIN,
    SLOT_RMS_MAX_M,
    apply_gates,
    fly,
    suite_tasks,
)
from fleetmpc.scenario import load_scenario, parse_scenario

SCENARIOS = sorted(Path("scenarios").glob("*.toml"))


@pytest.fixture(scope="module")
def rows() -> list[dict]:
    tasks = suite_tasks(SCENARIOS, seeds=3, known_model=False)
    with ProcessPoolExecutor(max_workers=2) as pool:
        return apply_gates(list(pool.map(fly, tasks)))


def _ids(rows: list[dict]) -> set[str]:
    return {
        f"{r['scenario']} seed {r['seed']} learning {'on' if r['learning'] else 'off'}"
        for r in rows
    }


def test_every_run_flies_every_scenario_of_the_repository(rows):
    assert len(rows) == 2 * 3 * len(SCENARIOS)
    assert not [r for r in rows if r.get("error")]


def test_minimum_separation_holds_in_every_run(rows):
    """d_safe at plant rate, learning on and off, every seed, every scenario."""
    assert not _ids([r for r in rows if not r["min_separation_m"] >= r["d_safe_m"]])


def test_qp_fallbacks_stay_under_one_percent_of_agent_steps(rows):
    assert not _ids([r for r in rows if not r["qp_fallback_fraction"] <= QP_FALLBACK_MAX_FRACTION])


def test_no_yaw_rate_chattering_in_any_run(rows):
    limit = REVERSALS_MAX_PER_VEHICLE_MIN
    assert not _ids([r for r in rows if not r["yaw_rate_reversals_per_vehicle_min"] <= limit])


def test_formation_error_gates_with_learning(rows):
    judged = [r for r in rows if r["learning"] and r["feasible"]]
    assert not _ids([r for r in judged if not r["formation_rms_m"] <= SLOT_RMS_MAX_M])
    paper = [r for r in judged if r["scenario"] == "paper"]
    assert len(paper) == 3
    assert all(r["formation_rms_m"] <= PAPER_SLOT_RMS_MAX_M for r in paper)


def test_learning_reduces_the_error_in_every_scenario_with_unmodeled_dynamics(rows):
    judged = [r for r in rows if r["learning"] and r["feasible"] and r["unmodeled_dynamics"]]
    # (The figure eight missed it, 0.33 on seed 43, while the formation's centre trailed the
    # target along its estimated course: that course's error, magnified by a 15 m lever arm,
    # was the same with learning on and off. On the path, 0.22-0.29.)
    assert {r["scenario"] for r in judged} >= {"figure-eight", "square", "wedge-circle"}
    assert not _ids([r for r in judged if not r["learning_ratio"] <= LEARNING_RATIO_MAX])


def test_the_learned_effectiveness_ends_near_the_truth_even_in_gusts(rows):
    judged = [r for r in rows if r["learning"] and r["feasible"]]
    assert {r["scenario"] for r in judged} >= {"gusty-square", "gust-in-turn", "turbulence-light"}
    errors = [max(r["beta_error_speed_max"], r["beta_error_yaw_rate_max"]) for r in judged]
    assert max(errors) <= EFFECTIVENESS_ERROR_MAX


def test_the_target_prediction_on_a_circle(rows):
    circle = [r for r in rows if r["scenario"] in ("wedge-circle", "uturn-start")]
    assert circle and all(r["target_prediction_rms_m"] <= 0.3 for r in circle)


def test_the_square_is_feasible_with_its_corners_reported_and_recovered_from(rows):
    report = check_scenario(load_scenario("scenarios/square.toml"))
    assert report.feasible, report.render()
    assert sum(line.startswith("corner at t = ") for line in report.lines) == 4
    square = [r for r in rows if r["scenario"] == "square" and r["learning"]]
    assert len(square) == 3
    assert all(r["corners"] == 4 for r in square)
    assert all(r["corner_recovery_s"] <= CORNER_RECOVERY_MAX_S for r in square)


@pytest.mark.parametrize("horizon", [5, 15])
def test_the_uturn_start_does_not_chatter_at_short_or_long_horizons(horizon):
    sc = load_scenario("scenarios/uturn-start.toml")
    sc = dataclasses.replace(sc, controller=dataclasses.replace(sc.controller, horizon=horizon))
    m = compute_metrics(run_lockstep(sc))
    assert m["yaw_rate_reversals_per_vehicle_min"] <= REVERSALS_MAX_PER_VEHICLE_MIN
    assert m["min_separation_m"] >= sc.controller.d_safe_m
    assert m["qp_fallbacks"] <= QP_FALLBACK_MAX_FRACTION * 301 * len(sc.vehicles)
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M


def test_a_target_that_turns_straight_back_and_stops_keeps_its_formation():
    """Before the starboard rule, the agents' reference swept one way round the reversal and the
    true one the other (formation RMS 1.3-4.8 m), and `check` called the stop infeasible."""
    sc = load_scenario("scenarios/hard/out-and-back.toml")
    assert check_scenario(sc).feasible
    m = compute_metrics(run_lockstep(sc))
    assert m["corners"] == 2  # the reversal and the stop
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M  # 40 s after the stop
    assert m["min_separation_m"] >= sc.controller.d_safe_m
    assert m["corner_recovery_s"] <= 15.0  # (about 11 s from the reversal)


@pytest.mark.parametrize("seed", [31, 32, 33])
def test_a_compact_ring_is_back_on_its_slots_within_15_s_of_each_120_degree_corner(seed):
    """Slots 3 m apart with d_safe 2 m leave each vehicle 0.31 m to its separation margin. With
    the line of now held over the horizon, the ring stayed 0.65-1.3 m behind its slots after
    each corner (formation RMS 0.78 m, no corner recovered); with a line for each step, between
    where the two plans put the pair then, it is back within 11.6-12.2 s (docs/design.md, "Why a
    line for each step")."""
    sc = load_scenario("scenarios/corners/compact-ring.toml")
    m = compute_metrics(run_lockstep(sc, seed=seed))
    assert m["corners"] == 4  # (the last at the run's end)
    assert m["corner_recovery_s"] <= CORNER_RECOVERY_MAX_S
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M
    assert m["min_separation_m"] >= sc.controller.d_safe_m
    steps = (round(sc.duration_s / sc.controller.period_s) + 1) * len(sc.vehicles)
    assert m["qp_fallbacks"] <= QP_FALLBACK_MAX_FRACTION * steps


def test_in_a_figure_eights_lobe_the_formation_keeps_its_slots():
    """Placed d_s behind the target along its estimated course, the filter's lag on a turn that
    tightens and opens swung the rear slot by decimetres (formation RMS 0.18-0.25 m); trailing
    along the path, it reads where the target was."""
    sc = load_scenario("scenarios/hard/figure-eight-lobe.toml")
    m = compute_metrics(run_lockstep(sc))
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M
    assert m["yaw_rate_reversals_per_vehicle_min"] <= REVERSALS_MAX_PER_VEHICLE_MIN


def test_a_target_that_never_moves_leaves_the_formation_facing_north():
    """The target filter's first estimates swing while they settle; taken for a course, they
    turned the formation round (formation RMS 6.6-18.5 m)."""
    sc = load_scenario("scenarios/hard/still-target.toml")
    m = compute_metrics(run_lockstep(sc, seed=2))
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M
    assert m["min_separation_m"] >= sc.controller.d_safe_m


def test_holding_station_in_a_wind_it_does_not_know_a_vehicle_does_not_chatter():
    """Without learning, each vehicle drifts off its still slot and comes back at a walking
    pace, its QP linearized at 0.3 m/s. Its yaw rate was held within 0.25 rad/s of seeds that
    turned opposite ways one period after the other (5.1 reversals per vehicle-minute); the
    trust region is wider about a slow linearization."""
    sc = load_scenario("scenarios/hard/still-target.toml")
    m = compute_metrics(run_lockstep(sc, learning=False, seed=2))
    assert m["yaw_rate_reversals_per_vehicle_min"] <= REVERSALS_MAX_PER_VEHICLE_MIN
    assert m["min_separation_m"] >= sc.controller.d_safe_m


@pytest.mark.parametrize("learning", [True, False])
def test_vehicles_crossing_each_others_paths_keep_d_safe(learning):
    """Four vehicles turn about and cross each other's paths at M = 15. Pressed against the
    line through where it was, each period's model error that took a vehicle further in was
    kept: seed 5 came to 1.88 m with learning (d_safe 2 m). Its goal drawn back onto its
    margin's line, the cost takes it out again. Without learning, a vehicle pressed against its
    line by a wind it does not know turned in place (1.4 % of steps fell back, 3.25 reversals
    per vehicle-minute), until the trust region widened about a slow linearization and the
    steady inputs were kept in the box."""
    sc = load_scenario("scenarios/hard/crossing-start-m15.toml")
    m = compute_metrics(run_lockstep(sc, learning=learning, seed=5))
    assert m["min_separation_m"] >= sc.controller.d_safe_m
    steps = (round(sc.duration_s / sc.controller.period_s) + 1) * len(sc.vehicles)
    assert m["qp_fallbacks"] <= QP_FALLBACK_MAX_FRACTION * steps
    assert m["yaw_rate_reversals_per_vehicle_min"] <= REVERSALS_MAX_PER_VEHICLE_MIN


def test_on_a_circle_tighter_than_the_reference_may_turn_the_agents_sweep_as_the_judge():
    """On a 25 m circle the wedge's reference turns at r_max, slower than the path, for as long
    as the target circles; the agents' reference read a settling estimate's speed, slewed up
    from a few cm/s over 20 s, turned faster meanwhile and kept that lead: 0.04 rad of
    formation, formation RMS 0.36 m with learning and 0.51 m without (ratio 0.70)."""
    doc = tomllib.loads(Path("scenarios/wedge-circle.toml").read_text())
    doc["target"]["radius_m"] = 25.0
    sc = parse_scenario(doc)
    on = compute_metrics(run_lockstep(sc, seed=141))
    off = compute_metrics(run_lockstep(sc, seed=141, learning=False))
    assert on["formation_rms_m"] <= SLOT_RMS_MAX_M
    assert on["formation_rms_m"] <= LEARNING_RATIO_MAX * off["formation_rms_m"]


def test_check_judges_a_turn_beyond_the_bound_by_the_position_it_costs():
    doc = tomllib.loads(Path("scenarios/square.toml").read_text())
    # World frame: the formation does not turn, its centre goes round each corner over a few
    # metres of path and its vehicles with it, without falling behind.
    doc["formation"]["frame"] = "world"
    report = check_scenario(parse_scenario(doc))
    assert report.feasible, report.render()
    corners = [line for line in report.lines if line.startswith("corner at")]
    assert len(corners) == 4 and all("about 0.0 m behind" in line for line in corners)
    assert all("does not turn" in line for line in corners)
    # A circle tighter than the vehicles can turn round at speed is not.
    doc["target"] = {"kind": "circle", "radius_m": 2.5, "speed_m_s": 1.0, "clockwise": True}
    report = check_scenario(parse_scenario(doc))
    assert not report.feasible
    turning = [p for p in report.problems if "beyond |omega|" in p]
    assert turning and "heading lag costs" in turning[0], report.problems


def test_check_reports_a_steady_turn_the_course_frame_falls_behind_on():
    doc = tomllib.loads(Path("scenarios/wedge-circle.toml").read_text())
    assert not [
        line
        for line in check_scenario(parse_scenario(doc)).lines
        if line.startswith("reference course")
    ]
    doc["target"]["radius_m"] = 25.0  # 0.04 rad/s, r_max 0.035 rad/s, for all 60 s
    report = check_scenario(parse_scenario(doc))
    assert report.feasible  # (its slots can be flown; the formation turns slower than the path)
    lagging = [line for line in report.lines if line.startswith("reference course")]
    assert len(lagging) == 1 and "for 50 s" in lagging[0] and "up to 15 deg" in lagging[0]
