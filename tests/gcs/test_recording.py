"""Rerun recording of a lockstep run: written to a file, read back, reported."""

import dataclasses
import json
import time

import numpy as np
import pytest
import rerun as rr
from viewer import blueprint_fields

from fleetmpc.bench.telemetry import receive_period
from fleetmpc.cli import main
from fleetmpc.gcs.blueprint import BETA_SERIES, TIMELINE, TRAIL_WINDOW_S
from fleetmpc.gcs.figures import FIGURE_FILES
from fleetmpc.gcs.metrics import compute_metrics, pair_indices
from fleetmpc.gcs.record import FlightRecord
from fleetmpc.gcs.report import METRICS_FILE
from fleetmpc.gcs.rrd_reader import RecordingError, read_recording
from fleetmpc.gcs.station import GroundStation
from fleetmpc.gcs.telemetry import RerunSink, write_recording
from fleetmpc.lockstep.flight import run_lockstep

DURATION_S = 5.0


@pytest.fixture
def strict_rerun():
    """Make rerun raise on a bad log call instead of warning (it is global state: restore it)."""
    before = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(before)


@pytest.fixture(scope="module")
def run(paper):
    t0 = time.perf_counter()
    rec = run_lockstep(paper, duration_s=DURATION_S)
    return rec, time.perf_counter() - t0


@pytest.fixture
def rrd(run, tmp_path, strict_rerun):
    rec, run_s = run
    path = tmp_path / "run.rrd"
    t0 = time.perf_counter()
    rid = write_recording(rec, path, recording_id="test-run", run_info={"learning": True})
    return path, rid, time.perf_counter() - t0, run_s


def _chunks_by_entity(path) -> dict[str, list]:
    out: dict[str, list] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        out.setdefault(chunk.entity_path, []).append(chunk)
    return out


def test_round_trip_is_bit_exact(run, rrd):
    rec, _ = run
    path, rid, _, _ = rrd
    back = read_recording(path)
    assert back.recording_id == rid == "test-run"
    assert back.run_info == {"learning": True}
    # Every field comes back: the agents' target predictions and plan ages in the flight_record
    # rows, the horizon in meta, what the plan bus did in run_end.
    for field in dataclasses.fields(FlightRecord):
        a, b = getattr(rec, field.name), getattr(back.record, field.name)
        if isinstance(a, np.ndarray):
            assert b.shape == a.shape, field.name
            assert b.dtype == np.asarray(a).dtype, field.name
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), field.name
        else:
            assert a == b, field.name
    assert back.record.prediction_horizon_periods == 5
    # float64 is stored as float64 and the plan bus's counters as JSON: the round trip is exact.
    assert compute_metrics(back.record) == compute_metrics(rec)


def test_a_record_without_the_agents_fields_reads_back_without_them(run, tmp_path):
    """A record that has no agents' predictions or plan ages (a live one's are NaN) is written
    with NaN rows and reads back with NaN: the metrics say "unknown" for both."""
    rec, _ = run
    bare = dataclasses.replace(rec, target_prediction=None, plan_age_s=None, network=None)
    path = tmp_path / "bare.rrd"
    write_recording(bare, path)
    back = read_recording(path).record
    assert np.isnan(back.target_prediction).all() and np.isnan(back.plan_age_s).all()
    assert back.network is None
    metrics = compute_metrics(back)
    assert metrics["target_prediction_rms_m"] is None
    assert (
        metrics["plan_age_s"]["median"] is None and metrics["plan_age_s"]["missing_fraction"] == 1
    )


def test_every_entity_family_is_in_the_file(run, rrd):
    rec, _ = run
    path, _, _, _ = rrd
    ids = rec.vehicle_ids
    expected = {"/map/target", "/map/formation_links", "/series/centre_distance", "/events"}
    expected |= {"/map/vehicles", "/map/trails", "/map/slots", "/series/separation"}
    expected |= {"/series/formation_error", "/series/c_norm", "/series/solve_time_ms"}
    expected |= {f"/series/beta/{name}" for name, _ in BETA_SERIES}
    chunks = _chunks_by_entity(path)
    assert expected <= set(chunks), sorted(expected - set(chunks))
    # A record on its own has no plans or ground-side predictions: those hold their statics.
    for entity in ("/map/plans", "/map/target_prediction"):
        assert all(c.is_static for c in chunks[entity]), entity
    k = len(rec.t_s)
    # Every time series has one row per period on the sim_time timeline, in integer ns.
    for entity in expected - {"/events"}:
        temporal = [c for c in chunks[entity] if not c.is_static]
        assert sum(c.num_rows for c in temporal) == k, entity
        assert all(c.timeline_names == [TIMELINE] for c in temporal), entity
    batch = next(c for c in chunks["/series/centre_distance"] if not c.is_static)
    batch = batch.to_record_batch()
    t_ns = batch.column(batch.schema.get_field_index(TIMELINE)).cast("int64").to_numpy()
    assert np.array_equal(t_ns, np.round(rec.t_s * 1e9).astype(np.int64))
    # One instance per vehicle: positions and heading arrows ride together, in fleet order.
    (vehicles,) = [c for c in chunks["/map/vehicles"] if not c.is_static]
    batch = vehicles.to_record_batch()
    assert "Points2D:positions" in batch.schema.names and "Arrows2D:vectors" in batch.schema.names
    positions = batch.column(batch.schema.names.index("Points2D:positions")).to_pylist()
    north, east = rec.truth[3, 2, :2]
    assert positions[3][2] == pytest.approx([east, -north], abs=1e-4)  # map x East, y South
    # One line per pair and per vehicle, named by a static SeriesLines.
    (separation,) = [c for c in chunks["/series/separation"] if not c.is_static]
    batch = separation.to_record_batch()
    lines = batch.column(batch.schema.names.index("Scalars:scalars")).to_pylist()
    a, b = rec.truth[5, 0, :2], rec.truth[5, 1, :2]
    assert len(lines[5]) == len(pair_indices(len(ids)))
    assert lines[5][0] == pytest.approx(np.hypot(*(a - b)), rel=1e-12)
    # Beta: per vehicle, the two parameters learned, then their truth.
    (names,) = [c for c in chunks["/series/beta/effectiveness"] if c.is_static]
    batch = names.to_record_batch()
    got = batch.column(batch.schema.names.index("SeriesLines:names")).to_pylist()[0]
    learned = [f"UAV {v} speed" for v in ids] + [f"UAV {v} yaw rate" for v in ids]
    assert got == learned + [f"{line} truth" for line in learned]
    (beta,) = [c for c in chunks["/series/beta/effectiveness"] if not c.is_static]
    batch = beta.to_record_batch()
    lines = batch.column(batch.schema.names.index("Scalars:scalars")).to_pylist()
    n = len(ids)
    assert lines[9][n + 2] == rec.beta[9, 2, 1]  # UAV 3's learned yaw-rate effectiveness
    assert lines[9][3 * n + 1] == rec.beta_truth[9, 1, 1]  # UAV 2's true one
    assert rr.chunk.RrdReader(path).blueprints(), "no blueprint sent with the recording"


def test_trails_are_steps_the_blueprint_shows_over_the_trail_window(run, rrd):
    """Each period logs every vehicle's step since the previous period; the map view shows
    `map/trails` alone over the last TRAIL_WINDOW_S, so the steps join into trails."""
    rec, _ = run
    path, _, _, _ = rrd
    (trails,) = [c for c in _chunks_by_entity(path)["/map/trails"] if not c.is_static]
    batch = trails.to_record_batch()
    strips = batch.column(batch.schema.names.index("LineStrips2D:strips")).to_pylist()
    n = len(rec.vehicle_ids)
    assert len(strips) == len(rec.t_s) and all(len(row) == n for row in strips)
    for k in (0, 1, 17):
        for i in range(n):
            north, east = rec.truth[max(k - 1, 0), i, :2]
            north_now, east_now = rec.truth[k, i, :2]
            want = [[east, -north], [east_now, -north_now]]
            assert strips[k][i] == [pytest.approx(p, abs=1e-4) for p in want], (k, i)
    overrides = blueprint_fields(path)
    (ranges,) = [
        fields["ranges"]
        for entity, fields in overrides.items()
        if entity.endswith("/ViewContents/overrides/map/trails/visualizers")
    ]
    window_ns = round(TRAIL_WINDOW_S * 1e9)
    want = {"timeline": TIMELINE, "range": {"start": -window_ns, "end": 0}}
    assert ranges == [want]


def test_qp_fallback_becomes_a_warning_event(run, tmp_path, strict_rerun):
    rec, _ = run
    qp_ok = np.ones_like(rec.qp_ok, dtype=bool)
    qp_ok[7, 1] = False
    path = tmp_path / "fallback.rrd"
    write_recording(dataclasses.replace(rec, qp_ok=qp_ok), path)
    (events,) = _chunks_by_entity(path)["/events"]
    batch = events.to_record_batch()
    texts = [row[0] for row in batch.column(batch.schema.names.index("TextLog:text")).to_pylist()]
    t_ns = batch.column(batch.schema.get_field_index(TIMELINE)).cast("int64").to_numpy()
    assert len(texts) == 2
    assert texts[1] == f"UAV {rec.vehicle_ids[1]}: QP failed, fallback input applied"
    assert t_ns[1] == round(rec.t_s[7] * 1e9)
    assert not read_recording(path).record.qp_ok[7, 1]


def _same(got, want) -> bool:
    """JSON values equal, floats within rounding (1e-12 relative), at any depth."""
    if isinstance(want, dict):
        return (
            isinstance(got, dict)
            and got.keys() == want.keys()
            and all(_same(got[k], want[k]) for k in want)
        )
    if isinstance(want, list):
        return isinstance(got, list) and len(got) == len(want) and all(map(_same, got, want))
    if isinstance(want, float) and isinstance(got, float):
        return got == pytest.approx(want, rel=1e-12, abs=1e-12)
    return type(got) is type(want) and got == want


def test_report_gives_every_metric_sim_gives_for_the_same_run(tmp_path, capsys):
    """`fleetmpc report` of a `sim --rrd` recording: every key of `sim --metrics`, equal (the
    target prediction RMS, the plan ages, what the plan bus did and the known-model figures
    included), and the figures."""
    rrd, sim_metrics, out = tmp_path / "run.rrd", tmp_path / "sim.json", tmp_path / "report"
    args = ["sim", "scenarios/paper.toml", "--duration", "3", "--quiet", "--seed", "11"]
    args.append("--known-model")
    assert main([*args, "--metrics", str(sim_metrics), "--rrd", str(rrd)]) == 0
    assert main(["report", str(rrd), "--out", str(out)]) == 0
    for name in FIGURE_FILES:
        assert (out / name).stat().st_size > 1000, name
    direct = json.loads(sim_metrics.read_text())
    reported = json.loads((out / METRICS_FILE).read_text())
    assert direct["target_prediction_rms_m"] > 0 and direct["plan_age_s"]["max"] > 0
    assert direct["network"]["received"]["accepted"] > 0 and direct["seed"] == 11
    assert direct["learned_over_known"] > 0
    assert set(direct) <= set(reported), sorted(set(direct) - set(reported))
    for key, want in direct.items():
        assert _same(reported[key], want), (key, reported[key], want)
    assert reported["source"] == "lockstep"  # (and the recording's id: what only it has)


@pytest.mark.parametrize("target_source", ["script", "mavlink"])
def test_report_of_a_live_recording_gives_the_ground_stations_metrics(
    paper, tmp_path, capsys, target_source
):
    """`fleetmpc report` of a ground station's recording: every key of its `--metrics`, equal,
    what it could not judge included (vehicles without ground truth, whose learned model is
    not judged; with another target than the scenario's, the figures against the target)."""
    rec = run_lockstep(paper, duration_s=3.0)
    rrd, out = tmp_path / "live.rrd", tmp_path / "report"
    gs = GroundStation(paper, speed=1.0, duration_s=3.0, target_source=target_source)
    gs.open_sinks([RerunSink(path=rrd)])
    for k in range(len(rec.t_s)):
        receive_period(gs, rec, k, plan_age_ns=200_000_000, setpoint_rate_hz=5.0)
        if k % 5 == 4:
            gs.flush()
    gs.flush(final=True)
    direct = json.loads(json.dumps(gs.metrics()))
    gs.close_sinks()
    assert main(["report", str(rrd), "--out", str(out)]) == 0
    reported = json.loads((out / METRICS_FILE).read_text())
    assert direct["beta_error_without_truth"] == list(rec.vehicle_ids)  # (no truth was sent)
    assert (direct["formation_rms_m"] is None) == (target_source != "script")
    assert set(reported) - set(direct) == {"recording_id"}
    for key, want in direct.items():
        assert _same(reported[key], want), (key, reported[key], want)


def test_report_of_a_missing_or_foreign_file_is_a_clean_error(tmp_path, capsys):
    with pytest.raises(RecordingError, match="no such recording"):
        read_recording(tmp_path / "missing.rrd")
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"not a recording")
    assert main(["report", str(junk), "--out", str(tmp_path / "o")]) == 2
    assert "report: error" in capsys.readouterr().err


def test_logging_cost_is_small_against_the_run(rrd, capsys):
    """Benchmark-style: prints the cost, asserts nothing on wall time."""
    path, _, write_s, run_s = rrd
    with capsys.disabled():
        print(
            f"\n[rrd] {DURATION_S:.0f} s paper run: lockstep {1e3 * run_s:.0f} ms, "
            f"write .rrd {1e3 * write_s:.1f} ms ({100 * write_s / run_s:.1f} % of the run), "
            f"{path.stat().st_size / 1024:.0f} KiB"
        )
    assert path.stat().st_size > 0
