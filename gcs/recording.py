"""A flight record as a Rerun recording (`.rrd`): a map, time series, events and a blueprint.

Everything is logged column-wise on the `sim_time` timeline, a duration in integer nanoseconds:
the component columns of every entity that shares a time index are built straight as Arrow arrays
into one record batch, which Rerun splits into one chunk per entity, and all the chunks of a call
go out in one `rr.send_chunks` (one call per flush instead of one `send_columns` per entity, and
no archetype conversions). The cost of a flush grows with the number of entities (Rerun makes
and ships one chunk per entity, some 70 us each), not with the rows, so the vehicles of a fleet
share entities, one instance or one line each. Entity layout (a live ground station logs the
same paths):

- `map/vehicles`: every vehicle's position (Points2D) and heading (Arrows2D), one instance
  per vehicle in fleet order, coloured and labelled by a static logged once;
- `map/trails` (LineStrips2D): each vehicle's step since the previous period, a two-point
  strip per vehicle and period; the blueprint shows this entity over the last `trail_window_s`
  before the time cursor (a visible time range on it alone), so the steps join into trails
  while a period costs one segment per vehicle, not the whole window;
- `map/formation_links` (every pair) as LineStrips2D; `map/target` and `map/slots` (one per
  vehicle) as Points2D;
- `series/separation` (one line per pair), `series/centre_distance`,
  `series/formation_error`, `series/c_norm`, `series/solve_time_ms` (one line per vehicle),
  `series/beta/<param>` (per vehicle: learned, then truth) as Scalars, the lines named and
  coloured by a static SeriesLines;
- `events` (TextLog): QP fallbacks; live runs add mode changes and STATUSTEXT;
- live runs only: `map/plans` (each agent's planned horizon, LineStrips2D),
  `map/target_prediction` (the ground station's prediction of the target over the horizon),
  `series/plan_age` [s] (one line per vehicle and neighbour) and `series/setpoint_rate` [Hz];
- `meta` (static AnyValues) and `flight_record` (AnyValues: one `periods` column, a float64
  list per period that packs every per-period FlightRecord field in `record_layout`'s order):
  what `gcs.rrd_reader` needs to rebuild the FlightRecord bit for bit.

Map frame: the viewer's 2-D x is East and its y is South (the viewer's y points down), so North
is up on screen, as in the paper's Fig. 1. `map_from_ned` is the only place that conversion lives.
"""

import json
import uuid
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401  (loaded here: a masked ListArray imports it, ~130 ms)
import rerun as rr
import rerun.blueprint as rrb

from gcs.metrics import pair_indices
from gcs.record import FlightRecord, LiveRows

__all__ = [
    "APPLICATION_ID",
    "BETA_PARAMS",
    "MIN_SEPARATION_COLUMN",
    "RECORD_ARRAYS",
    "RECORD_COLUMN",
    "TIMELINE",
    "TRAIL_WINDOW_S",
    "fleet_blueprint",
    "log_events",
    "log_flight_record",
    "log_statics",
    "open_recording",
    "map_from_ned",
    "record_layout",
    "sim_time_ns",
    "write_recording",
]

APPLICATION_ID = "fleetmpc"
TIMELINE = "sim_time"
BETA_PARAMS = (
    "speed_effectiveness",
    "yaw_rate_effectiveness",
    "drift_north_m_s",
    "drift_east_m_s",
)
"""Names of the four beta entries, in FlightRecord.beta's order."""
RECORD_ARRAYS = (
    "truth",
    "target",
    "target_velocity",
    "slots",
    "command",
    "c",
    "beta",
    "beta_truth",
    "qp_ok",
    "step_time_ms",
    "slot_offsets_world",
)
"""Per-period FlightRecord fields stored losslessly under `flight_record`."""
RECORD_COLUMN = "periods"
"""The `flight_record` component: one float64 list per period, the parts of `record_layout`
one after the other (qp_ok as 1.0 / 0.0)."""
MIN_SEPARATION_COLUMN = "min_separation_known_m"
"""The last part of a `flight_record` row: the run's minimum separation as known when the row
was logged (a growing record logs it with every slice, so the newest row has the whole run's).
It is the only copy: `meta` holds what does not change."""


def record_layout(n_vehicles: int) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """(name, per-period shape) of each part of a `flight_record` row, in order, for N vehicles:
    the RECORD_ARRAYS, then MIN_SEPARATION_COLUMN (one value)."""
    n = n_vehicles
    shapes = {
        "truth": (n, 3),
        "target": (2,),
        "target_velocity": (2,),
        "slots": (n, 2),
        "command": (n, 2),
        "c": (n, 2),
        "beta": (n, 4),
        "beta_truth": (n, 4),
        "qp_ok": (n,),
        "step_time_ms": (n,),
        "slot_offsets_world": (n, 2),
    }
    return (*((name, shapes[name]) for name in RECORD_ARRAYS), (MIN_SEPARATION_COLUMN, (1,)))


TRAIL_WINDOW_S = 20.0
"""Default length of the trail the map shows behind each vehicle [s]."""

_HEADING_ARROW_M = 2.0
_RGB = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
)


def map_from_ned(north_east_m: np.ndarray) -> np.ndarray:
    """(..., 2) North, East [m] -> (..., 2) viewer map x = East, y = South [m]."""
    ne = np.asarray(north_east_m, dtype=np.float64)
    return np.stack([ne[..., 1], -ne[..., 0]], axis=-1)


def sim_time_ns(t_s: np.ndarray) -> np.ndarray:
    """Sample times [s] -> integer nanoseconds (int64) for the `sim_time` timeline."""
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)


def _colour(i: int) -> tuple[int, int, int]:
    return _RGB[i % len(_RGB)]


def fleet_blueprint(
    *, vehicle_ids: tuple[int, ...], trail_window_s: float = TRAIL_WINDOW_S
) -> rrb.Blueprint:
    """The viewer layout: the map on the left, the time series on the right; the map shows
    `map/trails` over the last `trail_window_s` [s] before the time cursor."""
    trail = rrb.VisibleTimeRanges(
        timeline=TIMELINE,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-trail_window_s),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )
    series = [
        rrb.TimeSeriesView(origin="series/separation", name="separation [m]"),
        rrb.TimeSeriesView(origin="series/centre_distance", name="centre distance [m]"),
        rrb.TimeSeriesView(origin="series/formation_error", name="formation error [m]"),
        rrb.TimeSeriesView(origin="series/c_norm", name="||c||"),
        rrb.TimeSeriesView(
            name="effectiveness (learned, truth)",
            origin="series/beta",
            contents=[f"series/beta/{p}" for p in BETA_PARAMS[:2]],
        ),
        rrb.TimeSeriesView(
            name="drift [m/s] (learned, truth)",
            origin="series/beta",
            contents=[f"series/beta/{p}" for p in BETA_PARAMS[2:]],
        ),
        rrb.TimeSeriesView(origin="series/solve_time_ms", name="agent step [ms]"),
        rrb.TimeSeriesView(origin="series/plan_age", name="neighbour plan age [s]"),
        rrb.TimeSeriesView(origin="series/setpoint_rate", name="setpoint rate [Hz]"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="map",
                    name=f"map ({len(vehicle_ids)} UAVs)",
                    overrides={"/map/trails": trail},
                ),
                rrb.TextLogView(origin="events", name="events"),
                row_shares=[4, 1],
            ),
            rrb.Grid(*series),
            column_shares=[1, 1],
        ),
    )


_F32_XY = pa.list_(pa.field("item", pa.float32(), nullable=False), 2)
"""Arrow type of one 2-D position or vector (rerun.datatypes.Vec2D)."""
_STRIP = pa.list_(pa.field("item", _F32_XY, nullable=False))
"""Arrow type of one line strip (rerun.components.LineStrip2D)."""
_INDEX = pa.field(
    TIMELINE, pa.duration("ns"), metadata={"rerun:kind": "index", "rerun:index_name": TIMELINE}
)


_SCALARS = rr.Scalars.descriptor_scalars()
_POSITIONS = rr.Points2D.descriptor_positions()
_STRIPS = rr.LineStrips2D.descriptor_strips()
_ORIGINS = rr.Arrows2D.descriptor_origins()
_VECTORS = rr.Arrows2D.descriptor_vectors()


def _offsets(lengths: np.ndarray) -> pa.Array:
    return pa.array(np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32))


def _xy(points: np.ndarray) -> pa.Array:
    """(M, 2) -> M Vec2D (float32)."""
    flat = pa.array(np.ascontiguousarray(points, dtype=np.float32).ravel())
    return pa.FixedSizeListArray.from_arrays(flat, type=_F32_XY)


_FIELDS: dict[tuple[str, str], pa.Field] = {}
"""Schema fields by (entity path, component): the same few dozen every flush (keyed without the
Arrow type, whose hash costs some 8 us; a field is made anew if its column's type differs)."""


class _Columns:
    """Component columns of many entities on one `sim_time` index, sent as one record batch.

    Each column is a list array with one row per time; its `rerun:entity_path` metadata names its
    entity, so `rr.chunk.Chunk.from_record_batch` makes one chunk per entity of it.
    """

    def __init__(self, t_ns: np.ndarray) -> None:
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self.rows = len(self.t_ns)
        self._fields = [_INDEX]
        self._arrays = [pa.array(self.t_ns.astype("timedelta64[ns]"))]
        self._uniform: dict[tuple[int, int], pa.Array] = {}
        self._scalars: list[tuple[str, np.ndarray]] = []

    def _rows_of(self, m: int, per_row: int = 1) -> pa.Array:
        """Offsets of `rows` x `per_row` lists of m items each."""
        key = (m, per_row)
        if key not in self._uniform:
            end = self.rows * per_row * m
            self._uniform[key] = pa.array(np.arange(0, end + 1, m, dtype=np.int32))
        return self._uniform[key]

    def add(self, path: str, descriptor: rr.ComponentDescriptor | str, column: pa.Array) -> None:
        """A list array of `rows` rows (an archetype's descriptor, or a bare name: AnyValues)."""
        component = descriptor if isinstance(descriptor, str) else descriptor.component
        key = (path, component)
        f = _FIELDS.get(key)
        if f is None or not f.type.equals(column.type):
            meta = {"rerun:kind": "data", "rerun:entity_path": path, "rerun:component": component}
            if not isinstance(descriptor, str):
                meta["rerun:archetype"] = descriptor.archetype
                meta["rerun:component_type"] = descriptor.component_type
            f = _FIELDS[key] = pa.field(f"{path}:{component}", column.type, metadata=meta)
        self._fields.append(f)
        self._arrays.append(column)

    def scalars(self, path: str, values: np.ndarray) -> None:
        """Scalars: values (rows,) or (rows, lines), one line per column (an entity with
        several lines names them with a static SeriesLines). A row with no finite value stays
        empty (null); a series with no finite value at all is not logged."""
        values = np.asarray(values, dtype=np.float64)
        self._scalars.append((path, values.reshape(self.rows, -1)))

    def _add_scalars(self) -> None:
        """Every Scalars series, converted to Arrow in one array."""
        if not self._scalars:
            return
        flat = pa.array(np.concatenate([v.ravel() for _, v in self._scalars]))
        at = 0
        for path, values in self._scalars:
            missing = ~np.isfinite(values).any(axis=1)
            size = values.size
            if not missing.all():
                mask = pa.array(missing) if missing.any() else None
                column = pa.ListArray.from_arrays(
                    self._rows_of(values.shape[1]), flat.slice(at, size), mask=mask
                )
                self.add(path, _SCALARS, column)
            at += size
        self._scalars = []

    def xy(
        self, path: str, descriptor: rr.ComponentDescriptor, points: np.ndarray, per_row: int = 1
    ) -> None:
        """(rows x per_row, 2): `per_row` positions / vectors in every row."""
        self.add(path, descriptor, pa.ListArray.from_arrays(self._rows_of(per_row), _xy(points)))

    def strips(
        self,
        path: str,
        points: np.ndarray,
        strip_lengths: np.ndarray,
        per_row: int,
        missing: np.ndarray | None = None,
    ):
        """LineStrips2D: `per_row` strips in every row that is not `missing` (a missing row is
        null: nothing logged at that time, so the viewer keeps the previous strips), of
        `strip_lengths` points of `points`."""
        strips = pa.ListArray.from_arrays(_offsets(strip_lengths), _xy(points), type=_STRIP)
        if missing is None or not missing.any():
            column = pa.ListArray.from_arrays(self._rows_of(per_row), strips)
        else:
            counts = np.where(missing, 0, per_row)
            column = pa.ListArray.from_arrays(_offsets(counts), strips, mask=pa.array(missing))
        self.add(path, _STRIPS, column)

    def segments(self, path: str, points: np.ndarray, per_row: int) -> None:
        """LineStrips2D of two points each, `per_row` of them in every row."""
        strips = pa.ListArray.from_arrays(self._rows_of(2, per_row), _xy(points), type=_STRIP)
        self.add(path, _STRIPS, pa.ListArray.from_arrays(self._rows_of(per_row), strips))

    def values(self, path: str, name: str, rows: np.ndarray) -> None:
        """AnyValues component `name`: (rows, m) float64 or bool, one list of m per row."""
        m = rows.shape[1]
        flat = pa.array(np.ascontiguousarray(rows).ravel())
        self.add(path, name, pa.ListArray.from_arrays(self._rows_of(m), flat))

    def chunks(self) -> list:
        self._add_scalars()
        if len(self._arrays) == 1:
            return []
        batch = pa.RecordBatch.from_arrays(self._arrays, schema=pa.schema(self._fields))
        return rr.chunk.Chunk.from_record_batch(batch)


def _send(stream: rr.RecordingStream, groups: list[_Columns]) -> None:
    chunks = [c for group in groups for c in group.chunks()]
    if chunks:
        rr.send_chunks(chunks, recording=stream)


def _log_meta(stream: rr.RecordingStream, rec: FlightRecord, *, run_info: dict) -> None:
    stream.log(
        "meta",
        rr.AnyValues(
            scenario=rec.scenario,
            vehicle_ids=np.asarray(rec.vehicle_ids, dtype=np.int64),
            desired_distance_m=np.asarray(rec.desired_distance_m, dtype=np.float64).ravel(),
            trail_m=np.array([rec.trail_m], dtype=np.float64),
            speed_max_m_s=np.array([rec.speed_max_m_s], dtype=np.float64),
            yaw_rate_max_rad_s=np.array([rec.yaw_rate_max_rad_s], dtype=np.float64),
            d_safe_m=np.array([rec.d_safe_m], dtype=np.float64),
            run_info_json=json.dumps(run_info, sort_keys=True),
        ),
        static=True,
    )


def _record_rows(columns: _Columns, rec: FlightRecord, *, start: int) -> None:
    """Periods start.. of the record as `flight_record` rows (`record_layout`)."""
    rows = columns.rows
    parts = [np.asarray(getattr(rec, name))[start:].reshape(rows, -1) for name in RECORD_ARRAYS]
    parts.append(np.full((rows, 1), rec.min_separation_m))
    packed = np.concatenate(parts, axis=1, dtype=np.float64)
    columns.values("flight_record", RECORD_COLUMN, packed)


def _series_names(
    ids: tuple[int, ...], *, live: bool
) -> dict[str, tuple[list[str], list[tuple[int, ...]]]]:
    """Line names and colours of every multi-line series entity (logged once, static)."""
    uav = [f"UAV {v}" for v in ids]
    rgb = [_colour(i) for i in range(len(ids))]
    pairs = pair_indices(len(ids))
    out = {
        "series/separation": (
            [f"{ids[a]}-{ids[b]}" for a, b in pairs],
            [_colour(len(ids) + p) for p in range(len(pairs))],
        ),
    }
    if live:
        out["series/setpoint_rate"] = (uav, rgb)
        out["series/plan_age"] = (
            [f"UAV {v} sees {o}" for v in ids for o in ids if o != v],
            [_colour(i) for i, v in enumerate(ids) for o in ids if o != v],
        )
    for name in _PER_VEHICLE_SERIES:
        out[f"series/{name}"] = (uav, rgb)
    for param in BETA_PARAMS:
        truth = [f"UAV {v} truth" for v in ids]
        out[f"series/beta/{param}"] = (uav + truth, rgb + [(*c, 110) for c in rgb])
    return out


def log_statics(stream: rr.RecordingStream, vehicle_ids: tuple[int, ...], *, live: bool) -> None:
    """Colours, labels and line names: logged once, at the start of a recording.

    `log_flight_record` logs them with its first slice; a live ground station logs them when it
    opens its recording, before the fleet flies (`statics=False` then), so that the first
    logging calls of a process, which are slow, are not paid during the flight."""
    ids = vehicle_ids
    rgb = [_colour(i) for i in range(len(ids))]
    stream.log(
        "map/vehicles",
        rr.Points2D.from_fields(colors=rgb, labels=[f"UAV {v}" for v in ids], radii=[-4.0]),
        static=True,
    )
    stream.log("map/vehicles", rr.Arrows2D.from_fields(colors=rgb), static=True)
    stream.log("map/trails", rr.LineStrips2D.from_fields(colors=rgb), static=True)
    stream.log(
        "map/slots",
        rr.Points2D.from_fields(colors=rgb, radii=[-3.0], labels=[f"slot {v}" for v in ids]),
        static=True,
    )
    stream.log("map/target", rr.Points2D.from_fields(colors=[(0, 0, 0)], radii=[-5.0]), static=True)
    if live:
        stream.log("map/plans", rr.LineStrips2D.from_fields(colors=rgb), static=True)
        stream.log(
            "map/target_prediction",
            rr.LineStrips2D.from_fields(colors=[(0, 0, 0)], radii=[-1.0]),
            static=True,
        )
    for path, (names, colours) in _series_names(ids, live=live).items():
        stream.log(path, rr.SeriesLines(names=names, colors=colours), static=True)


def _map(columns: _Columns, rec: FlightRecord, *, start: int) -> None:
    k, n = rec.truth.shape[:2]
    before = max(start - 1, 0)
    pos = map_from_ned(rec.truth[before:, :, :2])  # periods before .. k - 1
    here = pos[start - before :]
    previous = pos[:-1] if start else np.concatenate([pos[:1], pos[:-1]])
    yaw = rec.truth[start:, :, 2]
    heading = map_from_ned(_HEADING_ARROW_M * np.stack([np.cos(yaw), np.sin(yaw)], axis=-1))
    flat = here.reshape(-1, 2)
    columns.xy("map/vehicles", _POSITIONS, flat, per_row=n)
    columns.xy("map/vehicles", _ORIGINS, flat, per_row=n)
    columns.xy("map/vehicles", _VECTORS, heading.reshape(-1, 2), per_row=n)
    steps = np.stack([previous, here], axis=2)  # (K, N, 2 points, 2)
    columns.segments("map/trails", steps.reshape(-1, 2), per_row=n)
    columns.xy("map/slots", _POSITIONS, map_from_ned(rec.slots[start:]).reshape(-1, 2), per_row=n)
    columns.xy("map/target", _POSITIONS, map_from_ned(rec.target[start:]))
    pairs = pair_indices(n)
    if pairs:
        a, b = np.array(pairs).T
        links = np.stack([here[:, a], here[:, b]], axis=2)  # (K, P, 2 points, 2)
        columns.segments("map/formation_links", links.reshape(-1, 2), per_row=len(pairs))


_PER_VEHICLE_SERIES = ("formation_error", "c_norm", "solve_time_ms")
"""Series entities with one line per vehicle, besides beta and the live-only ones."""


def _series(columns: _Columns, rec: FlightRecord, *, start: int) -> None:
    pos = rec.truth[start:, :, :2]
    pairs = pair_indices(len(rec.vehicle_ids))
    if pairs:
        d = [np.linalg.norm(pos[:, a] - pos[:, b], axis=1) for a, b in pairs]
        columns.scalars("series/separation", np.stack(d, axis=1))
    centre = np.mean(pos - rec.slot_offsets_world[start:], axis=1)
    columns.scalars("series/centre_distance", np.linalg.norm(centre - rec.target[start:], axis=1))
    columns.scalars("series/formation_error", np.linalg.norm(pos - rec.slots[start:], axis=2))
    columns.scalars("series/c_norm", np.linalg.norm(rec.c[start:], axis=2))
    columns.scalars("series/solve_time_ms", rec.step_time_ms[start:])
    for p, param in enumerate(BETA_PARAMS):
        both = np.concatenate([rec.beta[start:, :, p], rec.beta_truth[start:, :, p]], axis=1)
        columns.scalars(f"series/beta/{param}", both)


def _live(columns: _Columns, live: LiveRows) -> None:
    """Plans, setpoint rates, plan ages and the target prediction of a live slice."""
    k, n = live.plans.shape[:2]
    has = np.isfinite(live.plans).all(axis=(2, 3))  # (K, N)
    if has.any():
        points = map_from_ned(live.plans[has].reshape(-1, 2))
        lengths = np.where(has, live.plans.shape[2], 0).ravel()
        columns.strips("map/plans", points, lengths, per_row=n, missing=~has.any(axis=1))
    columns.scalars("series/setpoint_rate", live.setpoint_rate_hz)
    if live.plan_age_s.shape[2]:
        columns.scalars("series/plan_age", live.plan_age_s.reshape(k, -1))
    if live.target_prediction is not None:
        prediction = map_from_ned(np.asarray(live.target_prediction).reshape(-1, 2))
        missing = np.arange(k) < k - 1  # the prediction is made at the last row's time
        columns.strips(
            "map/target_prediction", prediction, np.array([len(prediction)]), per_row=1,
            missing=missing,
        )  # fmt: skip


def log_events(
    stream: rr.RecordingStream,
    events: list[tuple[int, str, str]],
) -> None:
    """Log (sim_time ns, level, text) events to `events` in one column batch; level is a
    `rr.TextLogLevel` name such as "INFO" or "WARN"."""
    if not events:
        return
    times, levels, texts = zip(*events, strict=True)
    stream.send_columns(
        "events",
        indexes=[rr.TimeColumn(TIMELINE, duration=np.array(times).astype("timedelta64[ns]"))],
        columns=rr.TextLog.columns(text=list(texts), level=list(levels)),
    )


def _qp_events(rec: FlightRecord, *, t_ns: np.ndarray, start: int) -> list[tuple[int, str, str]]:
    events = []
    if start == 0:
        events.append(
            (
                int(t_ns[0]),
                "INFO",
                f"run start: scenario {rec.scenario}, UAVs {list(rec.vehicle_ids)}",
            )
        )
    k_idx, i_idx = np.nonzero(~np.asarray(rec.qp_ok, dtype=bool)[start:])
    for k, i in zip(k_idx, i_idx, strict=True):
        events.append(
            (
                int(t_ns[start + k]),
                "WARN",
                f"UAV {rec.vehicle_ids[i]}: QP failed, fallback input applied",
            )
        )
    return events


def log_flight_record(
    stream: rr.RecordingStream,
    rec: FlightRecord,
    *,
    run_info: dict | None = None,
    start: int = 0,
    live: LiveRows | None = None,
    statics: bool = True,
) -> None:
    """Log a FlightRecord to an open recording stream, column-wise, in one batch.

    run_info: JSON-able facts about the run that are not in the record (learning, seed, ...).
    start: log only periods `start`.. (a live ground station logs a growing record in slices;
    the trail's first step starts at period `start` - 1). The static `meta` (the record's
    constants and the run facts), colours and line names are logged when start is 0.
    live: what a live run adds to periods `start`.. (plans, setpoint rates, plan ages, the
    target prediction).
    statics: log the colours, labels and line names with the first slice (`log_statics`).
    """
    t_ns = sim_time_ns(rec.t_s)
    if start == 0:
        _log_meta(stream, rec, run_info=run_info or {})
    if start == 0 and statics:
        log_statics(stream, rec.vehicle_ids, live=live is not None)
    if start >= len(t_ns):
        return
    columns = _Columns(t_ns[start:])
    _record_rows(columns, rec, start=start)
    _map(columns, rec, start=start)
    _series(columns, rec, start=start)
    if live is not None:
        if live.plans.shape[0] != columns.rows:
            raise ValueError(
                f"live rows: {live.plans.shape[0]} periods for a slice of {columns.rows}"
            )
        _live(columns, live)
    _send(stream, [columns])
    log_events(stream, _qp_events(rec, t_ns=t_ns, start=start))


def open_recording(
    *,
    vehicle_ids: tuple[int, ...],
    path: str | Path | None = None,
    viewer_url: str | None = None,
    spawn_viewer: bool = False,
    recording_id: str | None = None,
    trail_window_s: float = TRAIL_WINDOW_S,
) -> rr.RecordingStream:
    """A recording stream with its blueprint, teed to an `.rrd` file and/or a viewer.

    `viewer_url`: a running viewer's gRPC URL (``rerun+http://HOST:9876/proxy``);
    `spawn_viewer`: start a local viewer (the `rerun` executable) and stream to it;
    `trail_window_s`: length of the trail the map shows behind each vehicle [s].
    """
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or str(uuid.uuid4()))
    blueprint = fleet_blueprint(vehicle_ids=vehicle_ids, trail_window_s=trail_window_s)
    if spawn_viewer:
        stream.spawn(default_blueprint=blueprint)
        viewer_url = viewer_url or "rerun+http://127.0.0.1:9876/proxy"
    sinks = []
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(path))
    if viewer_url is not None:
        sinks.append(rr.GrpcSink(viewer_url))
    if sinks:
        stream.set_sinks(*sinks, default_blueprint=blueprint)
    return stream


def write_recording(
    rec: FlightRecord,
    path: str | Path,
    *,
    recording_id: str | None = None,
    run_info: dict | None = None,
    trail_window_s: float = TRAIL_WINDOW_S,
) -> str:
    """Write a FlightRecord and its blueprint to an `.rrd` file; return the recording id."""
    stream = open_recording(
        vehicle_ids=rec.vehicle_ids,
        path=path,
        recording_id=recording_id,
        trail_window_s=trail_window_s,
    )
    log_flight_record(stream, rec, run_info=run_info)
    stream.flush()
    stream.disconnect()
    return stream.get_recording_id()
