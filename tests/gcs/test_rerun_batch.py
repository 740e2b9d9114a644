"""Column batches written to a recording and read back: rows, nulls, strips and shared columns."""

import numpy as np
import pytest
import rerun as rr

from fleetmpc.gcs.record import LiveRows
from fleetmpc.gcs.recording import _live_map
from fleetmpc.gcs.rerun_batch import ColumnBatch, send_batches

TIMELINE = "t"


@pytest.fixture
def stream(tmp_path):
    path = tmp_path / "batch.rrd"
    s = rr.RecordingStream("fleetmpc-test", recording_id="batch")
    s.set_sinks(rr.FileSink(str(path)))
    yield s, path


def _read(path) -> dict[str, dict[str, list]]:
    """Temporal rows by entity and component column, and their times [ns] under TIMELINE."""
    out: dict[str, dict[str, list]] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.is_static:
            continue
        b = chunk.to_record_batch()
        columns = out.setdefault(chunk.entity_path, {})
        t = b.column(b.schema.get_field_index(TIMELINE)).cast("int64").to_pylist()
        columns.setdefault(TIMELINE, []).extend(t)
        for name in b.schema.names:
            if ":" in name:
                columns.setdefault(name, []).extend(b.column(name).to_pylist())
    return out


def test_points_strips_and_scalars_come_back_row_by_row(stream) -> None:
    s, path = stream
    rows = 4
    batch = ColumnBatch(TIMELINE, np.arange(rows) * 1_000_000)
    xy = np.arange(rows * 2 * 2, dtype=float).reshape(rows * 2, 2)
    positions, origins = rr.Points2D.descriptor_positions(), rr.Arrows2D.descriptor_origins()
    batch.points("p", (positions, origins), xy, per_row=2)
    # Two strips a row, of varying length (empty ones too), in rows 0 and 2 only.
    strip_xy = 10.0 + np.arange(10, dtype=float).reshape(5, 2)
    batch.strips(
        "s",
        strip_xy,
        points_per_strip=np.array([3, 0, 2, 0]),
        per_row=2,
        present=np.array([True, False, True, False]),
    )
    batch.scalars("a", np.array([[1.0, np.nan], [np.nan, np.nan], [2.0, 3.0], [4.0, 5.0]]))
    batch.scalars("b", np.full(rows, np.nan))  # nothing finite: not logged
    batch.scalars("c", np.arange(rows, dtype=float))
    send_batches(s, batch)
    s.flush()
    s.disconnect()
    got = _read(path)
    assert "/b" not in got
    p = got["/p"]
    assert p["Points2D:positions"] == p["Arrows2D:origins"]
    assert p["Points2D:positions"][1] == [[4.0, 5.0], [6.0, 7.0]]
    strips = got["/s"]["LineStrips2D:strips"]
    assert strips[0] == [[[10.0, 11.0], [12.0, 13.0], [14.0, 15.0]], []]
    assert strips[1] is None and strips[3] is None  # nothing logged at those times
    assert strips[2] == [[[16.0, 17.0], [18.0, 19.0]], []]
    a = got["/a"]["Scalars:scalars"]
    assert a[0] == pytest.approx([1.0, np.nan], nan_ok=True)
    assert a[1] is None  # no finite value in the row: null
    assert a[2:] == [[2.0, 3.0], [4.0, 5.0]]
    assert got["/c"]["Scalars:scalars"] == [[0.0], [1.0], [2.0], [3.0]]
    assert got["/c"][TIMELINE] == [0, 1_000_000, 2_000_000, 3_000_000]


def test_batches_on_different_times_go_out_together(stream) -> None:
    s, path = stream
    short = ColumnBatch(TIMELINE, np.array([5, 6]))
    short.scalars("x", np.array([1.0, 2.0]))
    long = ColumnBatch(TIMELINE, np.array([1, 2, 3, 4, 5, 6]))
    long.scalars("y", np.arange(6, dtype=float))
    send_batches(s, short, long)
    s.flush()
    s.disconnect()
    got = _read(path)
    assert got["/x"][TIMELINE] == [5, 6]
    assert got["/x"]["Scalars:scalars"] == [[1.0], [2.0]]
    assert got["/y"]["Scalars:scalars"] == [[float(v)] for v in range(6)]


def test_plans_before_every_vehicle_has_one_stay_in_their_rows(stream) -> None:
    """A live slice whose first rows have no plan, or plans of only some vehicles: each row
    shows its own plans (null where no vehicle has one, an empty strip for a vehicle without
    one), not an earlier row's."""
    s, path = stream
    plans = np.full((3, 2, 2, 2), np.nan)  # rows, vehicles, points, (North, East)
    plans[1, 0] = [[1.0, 2.0], [3.0, 4.0]]  # row 1: vehicle 0 only
    plans[2, 0] = [[5.0, 6.0], [7.0, 8.0]]
    plans[2, 1] = [[9.0, 10.0], [11.0, 12.0]]
    live = LiveRows(
        plans=plans,
        setpoint_rate_hz=np.full((3, 2), np.nan),
        plan_age_s=np.full((3, 2, 1), np.nan),
        target_prediction=None,
    )
    batch = ColumnBatch(TIMELINE, np.arange(3) * 1_000_000)
    _live_map(batch, live, skip=0)
    send_batches(s, batch)
    s.flush()
    s.disconnect()
    strips = _read(path)["/map/plans"]["LineStrips2D:strips"]
    # The map's x is East and its y is South.
    assert strips[0] is None
    assert strips[1] == [[[2.0, -1.0], [4.0, -3.0]], []]
    assert strips[2] == [[[6.0, -5.0], [8.0, -7.0]], [[10.0, -9.0], [12.0, -11.0]]]
