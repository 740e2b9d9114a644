"""The ground station's live record: the same metrics as the lockstep from the same data."""

import dataclasses
import math

import numpy as np
import pytest
import rerun as rr

from fleetmpc.bench.telemetry import period_messages, receive_period
from fleetmpc.gcs.live import LiveRecord
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.gcs.palette import lighter, vehicle_colour
from fleetmpc.gcs.record import LiveRows, RunConstants
from fleetmpc.gcs.rrd_reader import read_recording
from fleetmpc.gcs.station import GroundStation
from fleetmpc.gcs.telemetry import RerunSink, samples_of
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.protocol.messages import NeighbourPlanAge, PlanMessage

DURATION_S = 6.0


@pytest.fixture(scope="module")
def lockstep(paper):
    return run_lockstep(paper, duration_s=DURATION_S)


def _feed(live: LiveRecord, rec, *, poses: bool = True, start: int = 0) -> None:
    """What a ground station would receive from a run that flew exactly `rec` (from period
    `start` on)."""
    for k in range(start, len(rec.t_s)):
        msgs = period_messages(
            rec, k, period_ns=live.period_ns, horizon=live.scenario.controller.horizon
        )
        if poses:
            for pose in msgs.poses:
                live.add_pose(*pose)
        for plan in msgs.plans:
            live.add_plan(plan)
        for status in msgs.statuses:
            live.add_status(status)
        live.add_target(msgs.target)


def test_live_record_gives_the_lockstep_metrics(paper, lockstep) -> None:
    live = LiveRecord(paper)
    _feed(live, lockstep)
    assert live.complete_periods() == len(lockstep.t_s)
    rec = live.record()
    np.testing.assert_array_equal(rec.truth, lockstep.truth)
    np.testing.assert_allclose(rec.slots, lockstep.slots, atol=1e-12)
    np.testing.assert_allclose(rec.target, lockstep.target, atol=1e-12)
    np.testing.assert_allclose(rec.beta_truth, lockstep.beta_truth, atol=1e-12)
    want, got = compute_metrics(lockstep), compute_metrics(rec)
    for key in ("separation_error_m",):
        np.testing.assert_allclose(got[key], want[key], atol=1e-12)
    for key in (
        "centre_distance_error_m",
        "formation_rms_m",
        "c_norm_final",
        "inputs_within_bounds",
    ):
        assert got[key] == pytest.approx(want[key], abs=1e-12), key
    assert got["beta_error"] == want["beta_error"]
    assert got["qp_fallbacks"] == want["qp_fallbacks"]
    # Interpolated between 0.2 s samples on the plant tick: a little above the plant-rate minimum.
    assert want["min_separation_m"] <= got["min_separation_m"] <= want["min_separation_m"] + 0.05
    # The ground side's prediction of the target, at every period's time from the first.
    paths = live.target_paths(len(lockstep.t_s))
    assert paths.shape == (len(lockstep.t_s), paper.controller.horizon + 1, 2)
    np.testing.assert_allclose(paths[:, 0], lockstep.target, atol=0.1)
    # The agents do not send their predictions: known as the horizon only.
    assert np.isnan(rec.target_prediction).all() and got["target_prediction_rms_m"] is None
    assert rec.prediction_horizon_periods == paper.controller.horizon


def test_without_telemetry_positions_come_from_the_plans(paper, lockstep) -> None:
    live = LiveRecord(paper)
    _feed(live, lockstep, poses=False)
    np.testing.assert_array_equal(live.record().truth, lockstep.truth)


def test_partial_and_out_of_order_input(paper) -> None:
    live = LiveRecord(paper)
    assert live.complete_periods() == 0
    with pytest.raises(ValueError, match="no complete control period"):
        live.record()
    for vid in paper.vehicle_ids:
        live.add_pose(vid, 0.0, 0.0, float(vid), 0.0)
        live.add_pose(vid, 0.5, 1.0, float(vid), 0.0)
    live.add_pose(1, 0.3, 99.0, 99.0, 0.0)  # older than the newest sample: dropped
    live.add_pose(1, 0.7, math.nan, 0.0, 0.0)  # not finite: dropped
    live.add_pose(99, 1.0, 0.0, 0.0, 0.0)  # not a vehicle of the scenario: ignored
    assert live.complete_periods() == 3  # 0.0, 0.2, 0.4 <= 0.5
    rec = live.record()
    np.testing.assert_allclose(rec.truth[:, 0, 0], [0.0, 0.4, 0.8])
    assert np.isnan(rec.command).all() and np.isnan(rec.beta).all()
    assert compute_metrics(rec)["inputs_within_bounds"] is None


def _first_periods(rec, end: int):
    """The first `end` periods of a FlightRecord, as a growing live record would be."""
    per_period = {
        f.name: getattr(rec, f.name)[:end]
        for f in dataclasses.fields(rec)
        if np.shape(getattr(rec, f.name))[:1] == rec.t_s.shape
    }
    return dataclasses.replace(rec, **per_period)


def test_a_record_logged_in_slices_reads_back_whole(lockstep, tmp_path) -> None:
    path = tmp_path / "sliced.rrd"
    sink = RerunSink(path=path, series_every=2)
    sink.open(RunConstants.of(lockstep), {})
    k = len(lockstep.t_s)
    samples = samples_of(lockstep, LiveRows.blank(*lockstep.truth.shape[:2]))
    for start, end in ((0, 7), (7, 8), (8, k)):
        sink.log(samples[start:end])
        sink.flush()
    sink.close()
    back = read_recording(path).record
    for name in ("t_s", "truth", "command", "c", "beta", "slots", "qp_ok"):
        np.testing.assert_array_equal(getattr(back, name), getattr(lockstep, name), err_msg=name)
    # Each slice's trail steps start where the previous slice ended.
    steps = [
        row
        for c in rr.chunk.RrdReader(path).stream()
        if c.entity_path == "/map/trails" and not c.is_static
        for b in [c.to_record_batch()]
        for row in b.column(b.schema.names.index("LineStrips2D:strips")).to_pylist()
    ]
    east_south = np.stack([lockstep.truth[..., 1], -lockstep.truth[..., 0]], axis=-1)
    previous = np.concatenate([east_south[:1], east_south[:-1]])
    want = np.stack([previous, east_south], axis=2)  # (K, N, 2 points, 2)
    np.testing.assert_allclose(np.array(steps), want, atol=1e-4)


def _assert_same_record(got, want) -> None:
    for f in dataclasses.fields(want):
        a, b = getattr(got, f.name), getattr(want, f.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, f.name
            assert np.array_equal(a, b, equal_nan=b.dtype.kind == "f"), f.name
        else:
            assert a == b, f.name


def test_a_growing_record_is_the_record_built_at_once(paper, lockstep) -> None:
    """Records built period slice by slice, while the input still arrives (and some of it late),
    are bit for bit the record a fresh LiveRecord builds from everything at the end."""
    whole = LiveRecord(paper)
    _feed(whole, lockstep)
    k = len(lockstep.t_s)
    growing = LiveRecord(paper, periods=k)  # the scenario's fields before the flight
    start = 0
    for end in (1, 4, 5, 12, 20, k):
        _feed(growing, _first_periods(lockstep, end), start=start)
        _assert_same_record(growing.record(end), whole.record(end))
        start = end
    # A late plan for an early period changes that period and the commands held after it.
    late = growing.latest_plan(lockstep.vehicle_ids[1])
    plan = dataclasses.replace(late.plan, stamp_ns=3 * growing.period_ns)
    status = dataclasses.replace(late.status, qp_fallback=True)
    for live in (growing, whole):
        live.add_plan(PlanMessage(seq=999, plan=plan, status=status))
    rec = growing.record()
    assert not rec.qp_ok[3, 1]
    _assert_same_record(rec, whole.record())
    fresh = LiveRecord(paper)
    _feed(fresh, lockstep)
    fresh.add_plan(PlanMessage(seq=999, plan=plan, status=status))
    _assert_same_record(rec, fresh.record())
    # A tail of the record: its periods, and the whole run's minimum separation.
    tail = growing.record(first=9)
    assert tail.min_separation_m == rec.min_separation_m
    for f in dataclasses.fields(rec):
        a, b = getattr(tail, f.name), getattr(rec, f.name)
        if np.shape(b)[:1] == rec.t_s.shape:
            assert np.array_equal(a, b[9:], equal_nan=b.dtype.kind == "f"), f.name


def test_yaw_wraps_like_one_unwrap_of_every_sample(paper) -> None:
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.3, 200))
    yaw = np.angle(np.exp(1j * np.cumsum(rng.normal(0.0, 1.5, 200))))  # wraps often
    live = LiveRecord(paper)
    for j, (ts, y) in enumerate(zip(t, yaw, strict=True)):
        for vid in paper.vehicle_ids:
            live.add_pose(vid, float(ts), 0.0, float(vid), float(y))
        if j % 17 == 0:
            live.record()
    k = live.complete_periods()
    grid = np.arange(k) * live.period_ns * 1e-9
    want = np.interp(grid, t, np.unwrap(yaw))
    np.testing.assert_array_equal(live.record().truth[:, 0, 2], want)


@pytest.mark.parametrize("series_every", [1, 3])
def test_ground_station_flushes_read_back_as_the_live_record(
    paper, lockstep, tmp_path, series_every
) -> None:
    """A ground station fed a run and flushed every few periods: the recording reads back as
    its live record (minimum separation included), with each vehicle's plan and status rows,
    whether the time series and flight_record rows go out with every flush or every third
    (and the final one)."""
    path = tmp_path / "live.rrd"
    gs = GroundStation(paper, speed=1.0, duration_s=DURATION_S)
    gs.open_sinks([RerunSink(path=path, series_every=series_every)])
    for k in range(len(lockstep.t_s)):
        # Each vehicle sees its neighbours' plans 50 ms old.
        receive_period(gs, lockstep, k, plan_age_ns=50_000_000, setpoint_rate_hz=20.0)
        if k % 7 == 6:
            gs.flush()
    gs.flush(final=True)
    gs.close_sinks()
    want = gs.live.record()
    back = read_recording(path).record
    _assert_same_record(back, want)
    assert back.min_separation_m == want.min_separation_m

    chunks: dict[str, list] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        if not chunk.is_static:
            chunks.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())

    def rows(entity: str, component: str) -> list:
        return [
            row
            for b in chunks[entity]
            for row in b.column(b.schema.names.index(component)).to_pylist()
        ]

    k = len(lockstep.t_s)
    flushes = math.ceil(k / 7)  # the last one final, with the periods left
    assert len(chunks["/map/vehicles"]) == flushes
    assert len(chunks["/flight_record"]) == len(chunks["/series/separation"])
    assert len(chunks["/flight_record"]) == (flushes - 1) // series_every + 1
    # A plan is a bead per planned period after the first: 3 vehicles x horizon 5.
    plans = rows("/map/plans", "Points2D:positions")
    assert len(plans) == k and all(len(r) == 3 * 5 for r in plans)
    north, east = lockstep.truth[4, 1, :2]
    assert plans[4][5:10] == [pytest.approx([east, -north], abs=1e-4)] * 5
    # Each bead in a lighter shade of its vehicle's colour (RGBA packed, opaque).
    shade = [lighter(vehicle_colour(i)) for i in range(3)]
    want = [(r << 24) | (g << 16) | (b << 8) | 255 for r, g, b in shade for _ in range(5)]
    assert rows("/map/plans", "Points2D:colors")[4] == want
    plan_age = rows("/series/plan_age", "Scalars:scalars")
    assert plan_age[-1] == pytest.approx([0.05] * 6)
    assert rows("/series/setpoint_rate", "Scalars:scalars")[-1] == [20.0] * 3
    names = [
        b.column(b.schema.names.index("SeriesLines:names")).to_pylist()[0]
        for c in rr.chunk.RrdReader(path).stream()
        if c.is_static and c.entity_path == "/series/plan_age"
        for b in [c.to_record_batch()]
    ]
    assert names == [
        ["UAV 1 sees 2", "UAV 1 sees 3", "UAV 2 sees 1"]
        + ["UAV 2 sees 3", "UAV 3 sees 1", "UAV 3 sees 2"]
    ]
    # A target prediction at every period's time.
    assert len(rows("/map/target_prediction", "LineStrips2D:strips")) == k


def _bits(a: np.ndarray) -> tuple:
    return a.dtype.str, a.shape, a.tobytes()


def _copied(rows):
    """A record or live rows with every array copied (views of a build kept past the next)."""
    return dataclasses.replace(
        rows,
        **{
            f.name: getattr(rows, f.name).copy()
            for f in dataclasses.fields(rows)
            if isinstance(getattr(rows, f.name), np.ndarray)
        },
    )


@pytest.mark.parametrize(("every", "copy"), [(1, True), (6, True), (20, True), (6, False)])
def test_a_record_built_in_slices_is_the_record_built_once_bit_for_bit(
    paper, lockstep, every, copy
) -> None:
    """Tails built every few periods as the input arrives (yaw wrapping, plans missing, statuses
    between periods with neighbour ages) put together are, bit for bit, the record and the live
    rows one build at the end gives; -0.0 and NaN payloads included. Tails built as views
    (`copy=False`, as the ground station logs them) hold the same, read at once."""
    rng = np.random.default_rng(7)
    period_ns = paper.controller.period_ns
    k = len(lockstep.t_s)
    yaw = np.angle(np.exp(1j * np.cumsum(rng.normal(0.0, 2.0, (k, 3)), axis=0)))
    yaw[0, 0] = -0.0
    messages = []
    for j in range(k):
        msgs = period_messages(lockstep, j, period_ns=period_ns, horizon=5)
        poses = [(*p[:4], float(yaw[j, i])) for i, p in enumerate(msgs.poses)]
        plans = [m for m in msgs.plans if rng.random() > 0.2]
        statuses = []
        for m in msgs.statuses:
            seen = tuple(
                NeighbourPlanAge(o, int(rng.integers(1, 10**8)))
                for o in paper.vehicle_ids
                if o != m.sender_id and rng.random() > 0.3
            )
            status = dataclasses.replace(
                m.status, neighbour_plan_ages=seen, setpoint_rate_hz=float(rng.uniform(0, 30))
            )
            stamp = m.stamp_ns + int(rng.choice([0, 1, period_ns // 2, period_ns - 1]))
            statuses.append(dataclasses.replace(m, status=status, stamp_ns=stamp))
        messages.append((poses, plans, statuses))

    def feed(live: LiveRecord, j: int) -> None:
        poses, plans, statuses = messages[j]
        for pose in poses:
            live.add_pose(*pose)
        for m in (*plans, *statuses):
            (live.add_plan if isinstance(m, PlanMessage) else live.add_status)(m)

    sliced = LiveRecord(paper)
    tails, live_tails, logged = [], [], 0
    for j in range(k):
        feed(sliced, j)
        done = sliced.complete_periods()
        if (j + 1) % every == 0 and done > logged:
            tail = sliced.record(done, first=logged, copy=copy)
            live_tail = sliced.live_rows(logged, done, copy=copy)
            tails.append(tail if copy else _copied(tail))
            live_tails.append(live_tail if copy else _copied(live_tail))
            logged = done
    if sliced.complete_periods() > logged:
        tails.append(sliced.record(first=logged))
        live_tails.append(sliced.live_rows(logged, sliced.complete_periods()))
    once = LiveRecord(paper)
    for j in range(k):
        feed(once, j)
    whole = once.record()
    whole_live = once.live_rows(0, len(whole.t_s))
    assert len(tails) > 1
    for f in dataclasses.fields(whole):
        want = getattr(whole, f.name)
        if np.shape(want)[:1] == whole.t_s.shape:
            got = np.concatenate([getattr(t, f.name) for t in tails])
            assert _bits(got) == _bits(want), f.name
        elif isinstance(want, np.ndarray):
            assert _bits(getattr(tails[-1], f.name)) == _bits(want), f.name
        else:
            assert getattr(tails[-1], f.name) == want, f.name
    for name in ("plans", "setpoint_rate_hz", "plan_age_s"):
        got = np.concatenate([getattr(t, name) for t in live_tails])
        assert _bits(got) == _bits(getattr(whole_live, name)), name
    # The cases are there: a -0.0 yaw, periods before any status, yaw unwrapped past +-pi.
    assert np.signbit(whole.truth[0, 0, 2]) and np.isnan(whole.beta).any()
    assert np.abs(whole.truth[:, :, 2]).max() > 2 * np.pi
