"""The manoeuvre metrics on small synthetic flight records, against numbers worked by hand."""

import dataclasses
import math
import re

import numpy as np
import pytest

from fleetmpc.gcs.metrics import compute_metrics, corner_indices, format_summary
from fleetmpc.gcs.record import FlightRecord

PERIOD_S = 0.5


def _record(k: int, n: int, **fields) -> FlightRecord:
    """K periods of N vehicles sitting on their slots at the origin, a target moving North at
    1 m/s, zero commands; `fields` replaces any of it."""
    t = np.arange(k) * PERIOD_S
    target = np.stack([t, np.zeros(k)], axis=1)
    base = {
        "scenario": "synthetic",
        "vehicle_ids": tuple(range(1, n + 1)),
        "t_s": t,
        "truth": np.zeros((k, n, 3)),
        "target": target,
        "target_velocity": np.tile([1.0, 0.0], (k, 1)),
        "slots": np.zeros((k, n, 2)),
        "command": np.zeros((k, n, 2)),
        "c": np.zeros((k, n, 2)),
        "beta": np.tile([1.0, 1.0, 0.0, 0.0], (k, n, 1)),
        "beta_truth": np.tile([1.0, 1.0, 0.0, 0.0], (k, n, 1)),
        "qp_ok": np.ones((k, n), dtype=bool),
        "step_time_ms": np.full((k, n), np.nan),
        "desired_distance_m": np.zeros((n, n)),
        "trail_m": 0.0,
        "slot_offsets_world": np.zeros((k, n, 2)),
        "min_separation_m": 5.0,
        "speed_max_m_s": 2.0,
        "yaw_rate_max_rad_s": 0.5,
        "d_safe_m": 2.0,
    }
    return FlightRecord(**{**base, **fields})


def test_yaw_rate_reversals_count_big_sign_flips_per_vehicle_minute():
    # 2 vehicles, 13 periods of 0.5 s: 6 s = 0.1 min of flight
    w = np.zeros((13, 2))
    w[:, 0] = [0.3, -0.3, 0.3, -0.3, 0.0, 0.4, -0.26, 0.5, 0.1, -0.5, 0.5, np.nan, -0.5]
    #          ^ three flips of 0.3 > 0.25 | 0.4 -> -0.26 -> 0.5: two | 0.1: too small |
    #          -0.5 -> 0.5: one | nan breaks 0.5 -> nan -> -0.5
    w[:, 1] = [0.2, -0.2, 0.2, -0.2, 0.25, -0.25, 0.0, 0.0, 0.3, 0.3, -0.3, -0.3, 0.3]
    #          ^ 0.2 and 0.25 are not above half the bound (0.25) | 0.3 -> -0.3, -0.3 -> 0.3
    command = np.zeros((13, 2, 2))
    command[..., 1] = w
    m = compute_metrics(_record(13, 2, command=command))
    assert m["yaw_rate_reversals_per_vehicle_min"] == pytest.approx((6 + 2) / (2 * 0.1), abs=1e-9)


def test_yaw_rate_reversals_of_a_single_period_are_zero():
    m = compute_metrics(_record(1, 2, command=np.full((1, 2, 2), 0.5)))
    assert m["yaw_rate_reversals_per_vehicle_min"] == 0.0


def test_worst_vehicle_slot_rms_over_the_last_10_s():
    k = 41  # 0 .. 20 s; the window is 10 s < t <= 20 s, 20 samples
    truth = np.zeros((k, 3, 3))
    truth[:, 0, 0] = 0.1  # vehicle 1: 0.1 m off all along
    truth[:, 1, 1] = np.where(np.arange(k) < 20, 9.0, 0.0)  # vehicle 2: far off, before 10 s only
    truth[21:, 2, 0] = np.where(np.arange(20) % 2 == 0, 0.3, 0.4)  # 10 x 0.3, 10 x 0.4
    truth[20, 2, 0] = 5.0  # at t = 10 s: outside the window
    m = compute_metrics(_record(k, 3, truth=truth))
    want = math.sqrt((10 * 0.09 + 10 * 0.16) / 20)
    assert m["slot_rms_max_vehicle_m"] == pytest.approx(want, abs=1e-12)
    assert m["formation_rms_m"] == pytest.approx(
        math.sqrt((20 * 0.01 + 10 * 0.09 + 10 * 0.16) / 60), abs=1e-12
    )


def test_target_prediction_rms_against_the_target_h_periods_later():
    k, h = 10, 3
    rec = _record(k, 2)
    prediction = rec.target[np.minimum(np.arange(k) + h, k - 1)].copy()  # perfect ...
    prediction[0] = np.nan  # ... unknown at first
    prediction[2] += (0.3, 0.4)  # 0.5 m off
    prediction[5] += (0.0, -1.2)  # 1.2 m off
    prediction[8:] = 99.0  # horizon past the end of the record: not counted
    rec = dataclasses.replace(rec, target_prediction=prediction, prediction_horizon_periods=h)
    # k = 1 .. 6 counted (k + 3 < 10, finite): errors 0, 0.5, 0, 0, 1.2, 0
    want = math.sqrt((0.25 + 1.44) / 6)
    assert compute_metrics(rec)["target_prediction_rms_m"] == pytest.approx(want, abs=1e-12)


def test_target_prediction_rms_is_none_without_a_prediction():
    rec = _record(10, 2)
    assert compute_metrics(rec)["target_prediction_rms_m"] is None  # not recorded
    unknown = dataclasses.replace(
        rec, target_prediction=np.full((10, 2), np.nan), prediction_horizon_periods=3
    )
    assert compute_metrics(unknown)["target_prediction_rms_m"] is None  # never known
    short = dataclasses.replace(
        rec, target_prediction=np.zeros((10, 2)), prediction_horizon_periods=10
    )
    assert compute_metrics(short)["target_prediction_rms_m"] is None  # horizon past the end


def _square_corner_record() -> FlightRecord:
    """40 periods (0 .. 19.5 s): North, a right-angle corner at period 10 (5 s), East, a corner
    at period 30 (15 s), South; one vehicle whose slot error decays after each corner."""
    k = 40
    v = np.zeros((k, 2))
    v[:10] = (1.0, 0.0)
    v[10:30] = (0.0, 1.0)
    v[30:] = (-1.0, 0.0)
    err = np.zeros(k)
    # after the first corner: 1.0, 0.8, 0.5, 0.2, 0.4 (back out), 0.3, 0.1 ... -> within from
    # period 15 (7.5 s) on: recovery 2.5 s
    err[10:17] = [1.0, 0.8, 0.5, 0.2, 0.4, 0.3, 0.1]
    # after the second: 2.0 at 30 .. 37, within from 38 (19.0 s): recovery 4.0 s
    err[30:38] = 2.0
    truth = np.zeros((k, 2, 3))
    truth[:, 0, 0] = err
    truth[:, 1, 1] = 0.05  # the other vehicle stays close
    return _record(k, 2, target_velocity=v, truth=truth)


def test_corner_recovery_is_the_longest_over_the_corners():
    rec = _square_corner_record()
    assert corner_indices(rec.target_velocity) == [10, 30]
    m = compute_metrics(rec)
    assert m["corners"] == 2
    assert m["corner_recovery_s"] == pytest.approx(4.0, abs=1e-12)


def test_corner_never_recovered_is_inf_and_a_gentle_target_has_no_corner():
    rec = _square_corner_record()
    truth = rec.truth.copy()
    truth[-1, 0, 0] = 0.31  # out again at the very end: the second corner is never recovered
    assert compute_metrics(dataclasses.replace(rec, truth=truth))["corner_recovery_s"] == math.inf
    # a turn of 0.45 rad per period, and a slow change of speed: no corner
    course = np.concatenate([np.zeros(5), 0.45 * np.arange(1, 6), np.full(5, 2.25)])
    speed = np.linspace(1.0, 0.4, 15)[:, None]
    v = speed * np.stack([np.cos(course), np.sin(course)], axis=1)
    gentle = _record(15, 2, target_velocity=v)
    m = compute_metrics(gentle)
    assert m["corners"] == 0 and m["corner_recovery_s"] is None


def test_a_target_that_stops_or_sets_off_at_once_turns_a_corner():
    v = np.tile([1.0, 0.0], (12, 1))
    v[4:8] = (0.0, 0.0)  # stops at period 4 and sets off again at right angles at 8
    v[8:] = (0.0, 1.0)
    assert corner_indices(v) == [4, 8]
    v[8] = (0.04, 0.0)  # still (nearly) stopped at 8: it sets off at 9
    assert corner_indices(v) == [4, 9]
    # a course change spread over two consecutive periods is one manoeuvre
    v = np.tile([1.0, 0.0], (8, 1))
    v[3] = (math.cos(0.8), math.sin(0.8))
    v[4:] = (0.0, 1.0)
    assert corner_indices(v) == [3]


def test_the_summary_shows_the_new_rows():
    rec = _square_corner_record()
    m = {
        "scenario": "synthetic",
        "learning": True,
        "feasible": True,
        "duration_s": float(rec.t_s[-1]),
        **compute_metrics(rec),
    }
    text = format_summary(m)
    assert re.search(r"worst vehicle slot RMS +1\.2649 m\n", text)
    assert re.search(r"yaw-rate reversals +0\.00 per vehicle-minute\n", text)
    assert re.search(r"target prediction RMS +unknown\n", text)
    assert re.search(r"target corners +2\n", text)
    assert re.search(r"corner recovery \(worst\) +4\.0 s", text)
    m["corners"], m["corner_recovery_s"] = 0, None
    assert "corner recovery" not in format_summary(m)


def test_a_large_fleets_summary_gives_its_worst_and_median_not_every_pair():
    rec = _square_corner_record()
    m = {"scenario": "synthetic", "learning": True, "feasible": True, "duration_s": 1.0}
    m.update(compute_metrics(rec))
    n = 12
    m["separation_pairs"] = [(a, b) for a in range(1, n + 1) for b in range(a + 1, n + 1)]
    m["separation_error_m"] = [0.01] * len(m["separation_pairs"])
    m["separation_error_m"][5] = 0.09  # the pair 1-7
    m["beta_error"] = [
        {
            "vehicle": v,
            "speed_effectiveness": 0.01 * v,
            "yaw_rate_effectiveness": 0.02,
            "drift_m_s": 0.05 if v == 3 else 0.01,
        }
        for v in range(1, n + 1)
    ]
    text = format_summary(m)
    assert "separation error 1-2" not in text and "beta error UAV 1 " not in text
    assert re.search(r"separation error, 66 pairs +worst 1-7 0\.0900 m, median 0\.0100 m\n", text)
    assert re.search(
        r"beta error, 12 UAVs +worst a_V 12\.0 % \(UAV 12\), a_w 2\.0 % \(UAV 1\), "
        r"drift 0\.050 m/s \(UAV 3\)",
        text,
    )
