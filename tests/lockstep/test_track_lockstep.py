"""A recorded track flown in lockstep: the walk with a 5 s dropout kept in the repository
(scenarios/tracks/walk-dropout.toml, made by tools/make_walk_track.py), and a dropout longer than
the agents fly a prediction for, so that the formation holds and then re-acquires."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from fleetmpc.gcs.blueprint import TIMELINE
from fleetmpc.gcs.recording import map_from_ned
from fleetmpc.gcs.telemetry import MemorySink, RerunSink
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import load_scenario
from fleetmpc.targets.track import RecordedTrack

ROOT = Path(__file__).resolve().parents[2]
WALK = ROOT / "scenarios" / "tracks" / "walk-dropout.toml"


def _slot_errors(record) -> np.ndarray:
    """Each vehicle's distance to its slot, the formation placed along the true track (K, N)."""
    return np.linalg.norm(record.truth[:, :, :2] - record.slots, axis=2)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """The walk flown once, recorded: (scenario, record, the recording's path)."""
    sc = load_scenario(WALK)
    rrd = tmp_path_factory.mktemp("walk") / "walk.rrd"
    return sc, run_lockstep(sc, sinks=[RerunSink(path=rrd)]), rrd


def _entity_rows(rrd: Path, entity: str, component: str) -> tuple[np.ndarray, list]:
    """The times [ns] and values of an entity's temporal rows in a recording."""
    times, values = [], []
    for chunk in rr.chunk.RrdReader(rrd).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            column = batch.column(batch.schema.get_field_index(TIMELINE))
            times.extend(column.cast("int64").to_pylist())
            values.extend(batch.column(batch.schema.names.index(component)).to_pylist())
    order = np.argsort(times, kind="stable")
    return np.array(times)[order], [values[k] for k in order]


def test_the_walk_has_its_dropout(walk):
    sc, _, _ = walk
    gaps = np.diff(sc.target.times_s)
    (k,) = np.flatnonzero(gaps > 1.0)
    assert sc.target.times_s[k] == pytest.approx(64.8) and gaps[k] == pytest.approx(5.2)


def test_walk_with_a_dropout_meets_its_gates(walk):
    sc, record, _ = walk
    err, t = _slot_errors(record), record.t_s
    assert record.min_separation_m >= sc.controller.d_safe_m
    dropout = (t >= 64.8) & (t <= 70.0)
    assert err[dropout].max() < 1.0  # (measured: 0.38 m)
    back = np.argmin(np.abs(t - 80.0))  # (10 s after the fixes resume at 70 s)
    assert err[back].max() < 0.2  # (measured: 0.15 m)
    after = (t >= 80.0) & (t <= 82.0)
    assert np.sqrt(np.mean(err[after] ** 2)) < 0.2


def test_the_recording_shows_the_raw_fixes_the_filtered_target_and_the_lost_states(walk):
    """Every fix at its own time and where it was (the dropout a gap), the ground side's
    filtered target at every period from the first fix, and each vehicle's target state as it
    changes: predicting 2 s into the dropout, reacquiring at the first fix after it, tracking
    once the glide back is over."""
    sc, record, rrd = walk
    t_ns, fixes = _entity_rows(rrd, "/map/target_observations", "Points2D:positions")
    flown = sc.target.times_s <= record.t_s[-1]
    want_t = np.round(sc.target.times_s[flown] * 1e9).astype(np.int64)
    assert np.array_equal(t_ns, want_t)
    got = np.array([row[0] for row in fixes])  # (one point a row)
    assert np.allclose(got, map_from_ned(sc.target.positions_m[flown]), atol=1e-3)
    assert np.diff(t_ns).max() == pytest.approx(5.2e9)
    period_t, _ = _entity_rows(rrd, "/map/target_estimate", "Points2D:positions")
    assert np.array_equal(period_t, np.round(record.t_s * 1e9).astype(np.int64))
    event_t, texts = _entity_rows(rrd, "/events", "TextLog:text")
    lost_s, glide_s = sc.controller.target_lost_s, sc.controller.target_reacquire_s
    for v in sc.vehicle_ids:
        mine = f"UAV {v}: target"
        states = [(t * 1e-9, x[0]) for t, x in zip(event_t, texts, strict=True) if mine in x[0]]
        assert [text.split()[-1] for _, text in states] == ["predicting", "reacquiring", "tracking"]
        (predicting, _), (reacquiring, _), (tracking, _) = states
        assert predicting == pytest.approx(64.8 + lost_s, abs=0.2 + 1e-9)
        assert reacquiring == pytest.approx(70.0, abs=0.2 + 1e-9)
        assert tracking == pytest.approx(70.0 + glide_s, abs=0.2 + 1e-9)


def _line_with_a_long_gap() -> RecordedTrack:
    """A walk due North at 1.2 m/s from (5, 0), fixes at 5 Hz with 5 cm of noise, none from 30 s
    to 55 s."""
    rng = np.random.default_rng(11)
    t = np.arange(0.0, 100.0, 0.2)
    t = t[(t < 30.0) | (t >= 55.0)]
    p = np.column_stack([5.0 + 1.2 * t, np.zeros_like(t)]) + 0.05 * rng.standard_normal((t.size, 2))
    return RecordedTrack(times_s=t, positions_m=p, observation_noise_m=0.05, file="line")


def test_a_long_dropout_holds_the_formation_then_reacquires():
    walk_sc = load_scenario(WALK)
    sc = dataclasses.replace(
        walk_sc,
        target=_line_with_a_long_gap(),
        vehicles=tuple(
            dataclasses.replace(v, initial=(0.0, v.slot_m[1], 0.0)) for v in walk_sc.vehicles
        ),
        duration_s=100.0,
    )
    sink = MemorySink()
    record = run_lockstep(sc, sinks=[sink])
    t, xy = record.t_s, record.truth[:, :, :2]
    predict_s = sc.controller.target_predict_s
    states = [text.split(": target ")[1] for _, _, text in sink.events if ": target " in text]
    cycle = ["predicting", "holding", "reacquiring", "tracking"]
    assert states == [state for state in cycle for _ in sc.vehicle_ids]
    assert record.min_separation_m >= sc.controller.d_safe_m
    # Held: from 10 s after the prediction ends (the vehicles have stopped, and turned into the
    # wind to stand) until the fixes resume, they stand, each at its slot about the held target:
    # the formation's shape kept.
    held = (t >= 30.0 + predict_s + 10.0) & (t < 55.0)
    travel = np.linalg.norm(xy[held] - xy[held][0], axis=2)
    assert travel.max() < 0.3
    gaps = np.linalg.norm(xy[held][:, :, None] - xy[held][:, None, :], axis=3)
    assert np.abs(gaps - record.desired_distance_m).max() < 0.5
    # Where they held: where the prediction had the target at 30 s + predict_s, braked to a
    # stop from 1.2 m/s at a quarter of speed_rate_max_m_s2, the formation's trail behind.
    hold_centre = xy[held][-1].mean(axis=0)
    brake_m = 1.2**2 / (2.0 * 0.25 * sc.controller.speed_rate_max_m_s2)
    expected = 5.0 + 1.2 * (30.0 + predict_s) + brake_m - sc.formation.trail_m
    assert hold_centre[0] == pytest.approx(expected, abs=1.0)
    # Back: on its slot again 25 s after the fixes resume.
    err = _slot_errors(record)
    assert err[(t >= 80.0) & (t <= 95.0)].max() < 0.3  # (the track ends at 99.8 s)
