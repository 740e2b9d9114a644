"""A flight record as a Rerun recording (`.rrd`): a map, time series, events and a blueprint.

Everything is logged column-wise on the `sim_time` timeline, a duration in integer nanoseconds:
the component columns of every entity that shares a time index are built straight as Arrow arrays
into one record batch, which Rerun splits into one chunk per entity, and all the chunks of a call
go out in one `rr.send_chunks` (one call per flush instead of one `send_columns` per entity, and
no archetype conversions). Entity layout (a live ground station logs the same paths):

- `map/vehicles/<id>`: position (Points2D) and heading (Arrows2D);
- `map/trails/<id>`: the last `trail_window_s` of the path (LineStrips2D);
- `map/target`, `map/slots/<id>` (Points2D), `map/formation_links` (LineStrips2D, every pair);
- `series/separation/<a>-<b>`, `series/centre_distance`, `series/formation_error/<id>` [m],
  `series/c_norm/<id>`, `series/beta/<id>/<param>`, `series/beta_truth/<id>/<param>`,
  `series/solve_time_ms/<id>` (Scalars);
- `events` (TextLog): QP fallbacks; live runs add mode changes and STATUSTEXT;
- live runs only: `map/plans/<id>` (each agent's planned horizon, LineStrips2D),
  `map/target_prediction` (the ground station's prediction of the target over the horizon),
  `series/plan_age/<id>/<neighbour>` [s] and `series/setpoint_rate/<id>` [Hz] (Scalars);
- `meta` (static AnyValues) and `flight_record` (AnyValues, float64, one row per period): what
  `gcs.rrd_reader` needs to rebuild the FlightRecord bit for bit.

Map frame: the viewer's 2-D x is East and its y is South (the viewer's y points down), so North
is up on screen, as in the paper's Fig. 1. `map_from_ned` is the only place that conversion lives.
"""

import json
import uuid
from collections import defaultdict
from pathlib import Path

import numpy as np
import pyarrow as pa
import rerun as rr
import rerun.blueprint as rrb

from gcs.metrics import pair_indices
from gcs.record import FlightRecord
from protocol.messages import PlanMessage, StatusMessage

__all__ = [
    "APPLICATION_ID",
    "BETA_PARAMS",
    "RECORD_ARRAYS",
    "TIMELINE",
    "fleet_blueprint",
    "log_events",
    "log_flight_record",
    "log_plans",
    "log_status_series",
    "log_target_predictions",
    "open_recording",
    "map_from_ned",
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


def fleet_blueprint(*, vehicle_ids: tuple[int, ...]) -> rrb.Blueprint:
    """The viewer layout: the map on the left, the time series on the right."""
    series = [
        rrb.TimeSeriesView(origin="series/separation", name="separation [m]"),
        rrb.TimeSeriesView(origin="series/centre_distance", name="centre distance [m]"),
        rrb.TimeSeriesView(origin="series/formation_error", name="formation error [m]"),
        rrb.TimeSeriesView(origin="series/c_norm", name="||c||"),
        rrb.TimeSeriesView(
            name="beta (learned, truth)",
            origin="series",
            contents=["series/beta/**", "series/beta_truth/**"],
        ),
        rrb.TimeSeriesView(origin="series/solve_time_ms", name="agent step [ms]"),
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(origin="map", name=f"map ({len(vehicle_ids)} UAVs)"),
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


def _offsets(lengths: np.ndarray) -> pa.Array:
    return pa.array(np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32))


def _xy(points: np.ndarray) -> pa.Array:
    """(M, 2) -> M Vec2D (float32)."""
    flat = pa.array(np.ascontiguousarray(points, dtype=np.float32).ravel())
    return pa.FixedSizeListArray.from_arrays(flat, type=_F32_XY)


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
        self._uniform: dict[int, pa.Array] = {}
        self._scalars: list[tuple[str, np.ndarray]] = []

    def _rows_of(self, m: int) -> pa.Array:
        """Offsets of `rows` lists of m items each."""
        if m not in self._uniform:
            self._uniform[m] = pa.array(np.arange(0, self.rows * m + 1, m, dtype=np.int32))
        return self._uniform[m]

    def add(self, path: str, descriptor: rr.ComponentDescriptor | str, column: pa.Array) -> None:
        """A list array of `rows` rows (an archetype's descriptor, or a bare name: AnyValues)."""
        meta = {"rerun:kind": "data", "rerun:entity_path": path}
        if isinstance(descriptor, str):
            meta["rerun:component"] = descriptor
        else:
            meta["rerun:component"] = descriptor.component
            meta["rerun:archetype"] = descriptor.archetype
            meta["rerun:component_type"] = descriptor.component_type
        self._fields.append(
            pa.field(f"{path}:{meta['rerun:component']}", column.type, metadata=meta)
        )
        self._arrays.append(column)

    def scalars(self, path: str, values: np.ndarray) -> None:
        """One Scalars value per row; rows that are not finite stay empty (null), and a series
        with no finite value is not logged."""
        self._scalars.append((path, values))

    def _add_scalars(self) -> None:
        """Every Scalars series, converted to Arrow in one array."""
        if not self._scalars:
            return
        values = np.stack([np.asarray(v, dtype=np.float64) for _, v in self._scalars])
        missing = ~np.isfinite(values)
        flat = pa.array(values.ravel())
        offsets = self._rows_of(1)
        for j, (path, _) in enumerate(self._scalars):
            if missing[j].all():
                continue
            mask = pa.array(missing[j]) if missing[j].any() else None
            values_j = flat.slice(j * self.rows, self.rows)
            self.add(path, _SCALARS, pa.ListArray.from_arrays(offsets, values_j, mask=mask))
        self._scalars = []

    def xy(self, path: str, descriptor: rr.ComponentDescriptor, points: np.ndarray) -> None:
        """(rows, 2) one position / vector per row."""
        self.add(path, descriptor, pa.ListArray.from_arrays(self._rows_of(1), _xy(points)))

    def strips(self, path: str, points: np.ndarray, strip_lengths: np.ndarray, per_row: int):
        """LineStrips2D: `per_row` strips in every row, of `strip_lengths` points of `points`."""
        strips = pa.ListArray.from_arrays(_offsets(strip_lengths), _xy(points), type=_STRIP)
        column = pa.ListArray.from_arrays(self._rows_of(per_row), strips)
        self.add(path, _STRIPS, column)

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
            min_separation_m=np.array([rec.min_separation_m], dtype=np.float64),
            speed_max_m_s=np.array([rec.speed_max_m_s], dtype=np.float64),
            yaw_rate_max_rad_s=np.array([rec.yaw_rate_max_rad_s], dtype=np.float64),
            d_safe_m=np.array([rec.d_safe_m], dtype=np.float64),
            run_info_json=json.dumps(run_info, sort_keys=True),
        ),
        static=True,
    )


def _record_arrays(columns: _Columns, rec: FlightRecord, *, start: int) -> None:
    for name in RECORD_ARRAYS:
        a = np.asarray(getattr(rec, name))[start:]
        a = a.astype(np.bool_) if name == "qp_ok" else a.astype(np.float64)
        columns.values("flight_record", name, a.reshape(columns.rows, -1))


def _log_map_styles(stream: rr.RecordingStream, vehicle_ids: tuple[int, ...]) -> None:
    for i, vid in enumerate(vehicle_ids):
        rgb = _colour(i)
        stream.log(f"map/vehicles/{vid}", rr.Points2D.from_fields(colors=[rgb]), static=True)
        stream.log(f"map/trails/{vid}", rr.LineStrips2D.from_fields(colors=[rgb]), static=True)
        stream.log(
            f"map/slots/{vid}",
            rr.Points2D.from_fields(colors=[rgb], radii=[-3.0], labels=[f"slot {vid}"]),
            static=True,
        )
        stream.log(f"map/plans/{vid}", rr.LineStrips2D.from_fields(colors=[rgb]), static=True)
    stream.log("map/target", rr.Points2D.from_fields(colors=[(0, 0, 0)], radii=[-5.0]), static=True)
    stream.log(
        "map/target_prediction",
        rr.LineStrips2D.from_fields(colors=[(0, 0, 0)], radii=[-1.0]),
        static=True,
    )


def _trail_points(pos: np.ndarray, *, first: np.ndarray, start: int) -> tuple:
    """Points of the trails of rows start.. (each row: pos[first[j] .. j]) and their lengths."""
    rows = np.arange(start, len(pos))
    lengths = rows + 1 - first[rows]
    begin = np.repeat(np.cumsum(lengths) - lengths, lengths)
    index = np.arange(lengths.sum()) - begin + np.repeat(first[rows], lengths)
    return pos[index], lengths


def _map(
    columns: _Columns,
    rec: FlightRecord,
    *,
    t_ns: np.ndarray,
    trail_window_s: float,
    start: int,
) -> None:
    k, n = rec.truth.shape[:2]
    pos = map_from_ned(rec.truth[:, :, :2])
    rows = slice(start, k)
    yaw = rec.truth[rows, :, 2]
    heading = map_from_ned(_HEADING_ARROW_M * np.stack([np.cos(yaw), np.sin(yaw)], axis=-1))
    slots = map_from_ned(rec.slots[rows])
    step_ns = np.median(np.diff(t_ns)) if k > 1 else 1
    window = max(1, int(round(trail_window_s * 1e9 / max(step_ns, 1))))
    first = np.maximum(np.arange(k) - window + 1, 0)
    for i, vid in enumerate(rec.vehicle_ids):
        path = f"map/vehicles/{vid}"
        columns.xy(path, _POSITIONS, pos[rows, i])
        columns.xy(path, rr.Arrows2D.descriptor_origins(), pos[rows, i])
        columns.xy(path, rr.Arrows2D.descriptor_vectors(), heading[:, i])
        trail, lengths = _trail_points(pos[:, i], first=first, start=start)
        columns.strips(f"map/trails/{vid}", trail, lengths, per_row=1)
        columns.xy(f"map/slots/{vid}", _POSITIONS, slots[:, i])
    columns.xy("map/target", _POSITIONS, map_from_ned(rec.target[rows]))
    pairs = pair_indices(n)
    if pairs:
        links = np.stack([pos[rows][:, [a, b]] for a, b in pairs], axis=1)  # (K, P, 2, 2)
        columns.strips(
            "map/formation_links",
            links.reshape(-1, 2),
            np.full(links.shape[0] * len(pairs), 2),
            per_row=len(pairs),
        )


def _series(columns: _Columns, rec: FlightRecord, *, start: int) -> None:
    ids = rec.vehicle_ids
    pos = rec.truth[start:, :, :2]
    for a, b in pair_indices(len(ids)):
        d = np.linalg.norm(pos[:, a] - pos[:, b], axis=1)
        columns.scalars(f"series/separation/{ids[a]}-{ids[b]}", d)
    centre = np.mean(pos - rec.slot_offsets_world[start:], axis=1)
    columns.scalars("series/centre_distance", np.linalg.norm(centre - rec.target[start:], axis=1))
    formation_error = np.linalg.norm(pos - rec.slots[start:], axis=2)
    c_norm = np.linalg.norm(rec.c[start:], axis=2)
    for i, vid in enumerate(ids):
        columns.scalars(f"series/formation_error/{vid}", formation_error[:, i])
        columns.scalars(f"series/c_norm/{vid}", c_norm[:, i])
        columns.scalars(f"series/solve_time_ms/{vid}", rec.step_time_ms[start:, i])
        for p, param in enumerate(BETA_PARAMS):
            columns.scalars(f"series/beta/{vid}/{param}", rec.beta[start:, i, p])
            columns.scalars(f"series/beta_truth/{vid}/{param}", rec.beta_truth[start:, i, p])


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
    trail_window_s: float = 20.0,
    start: int = 0,
) -> None:
    """Log a FlightRecord to an open recording stream, column-wise.

    run_info: JSON-able facts about the run that are not in the record (learning, seed, ...).
    trail_window_s: length of the trail drawn behind each vehicle [s].
    start: log only periods `start`.. (a live ground station logs a growing record in slices;
    earlier periods still draw the trails). The static `meta` is logged every time.
    """
    t_ns = sim_time_ns(rec.t_s)
    _log_meta(stream, rec, run_info=run_info or {})
    if start == 0:
        _log_map_styles(stream, rec.vehicle_ids)
    if start >= len(t_ns):
        return
    columns = _Columns(t_ns[start:])
    _record_arrays(columns, rec, start=start)
    _map(columns, rec, t_ns=t_ns, trail_window_s=trail_window_s, start=start)
    _series(columns, rec, start=start)
    _send(stream, [columns])
    log_events(stream, _qp_events(rec, t_ns=t_ns, start=start))


def log_plans(stream: rr.RecordingStream, plans: list[PlanMessage]) -> None:
    """Each agent's planned horizon at its stamp, one batch per vehicle: `map/plans/<id>`."""
    by_vehicle: dict[int, list[PlanMessage]] = defaultdict(list)
    for m in plans:
        by_vehicle[m.sender_id].append(m)
    groups = []
    for vid, items in by_vehicle.items():
        columns = _Columns([m.stamp_ns for m in items])
        states = [m.plan.states[:, :2] for m in items]
        columns.strips(
            f"map/plans/{vid}",
            map_from_ned(np.concatenate(states)),
            np.array([len(x) for x in states]),
            per_row=1,
        )
        groups.append(columns)
    _send(stream, groups)


def log_target_predictions(
    stream: rr.RecordingStream, predictions: list[tuple[int, np.ndarray]]
) -> None:
    """(sim_time ns, predicted positions (M + 1, 2) North/East) as `map/target_prediction`."""
    if predictions:
        stamps, paths = zip(*predictions, strict=True)
        columns = _Columns(stamps)
        columns.strips(
            "map/target_prediction",
            map_from_ned(np.concatenate(paths)),
            np.array([len(p) for p in paths]),
            per_row=1,
        )
        _send(stream, [columns])


def log_status_series(stream: rr.RecordingStream, statuses: list[StatusMessage]) -> None:
    """Setpoint rates and neighbour plan ages from vehicle statuses, one batch per vehicle."""
    by_vehicle: dict[int, list[StatusMessage]] = defaultdict(list)
    for m in statuses:
        by_vehicle[m.sender_id].append(m)
    groups = []
    for vid, items in by_vehicle.items():
        columns = _Columns([m.stamp_ns for m in items])
        columns.scalars(
            f"series/setpoint_rate/{vid}", np.array([m.status.setpoint_rate_hz for m in items])
        )
        ages: dict[int, np.ndarray] = {}
        for j, m in enumerate(items):
            for a in m.status.neighbour_plan_ages:
                ages.setdefault(a.vehicle_id, np.full(len(items), np.nan))[j] = a.age_ns * 1e-9
        for nbr, values in ages.items():
            columns.scalars(f"series/plan_age/{vid}/{nbr}", values)
        groups.append(columns)
    _send(stream, groups)


def open_recording(
    *,
    vehicle_ids: tuple[int, ...],
    path: str | Path | None = None,
    viewer_url: str | None = None,
    spawn_viewer: bool = False,
    recording_id: str | None = None,
) -> rr.RecordingStream:
    """A recording stream with its blueprint, teed to an `.rrd` file and/or a viewer.

    `viewer_url`: a running viewer's gRPC URL (``rerun+http://HOST:9876/proxy``);
    `spawn_viewer`: start a local viewer (the `rerun` executable) and stream to it.
    """
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or str(uuid.uuid4()))
    blueprint = fleet_blueprint(vehicle_ids=vehicle_ids)
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
    trail_window_s: float = 20.0,
) -> str:
    """Write a FlightRecord and its blueprint to an `.rrd` file; return the recording id."""
    stream = open_recording(vehicle_ids=rec.vehicle_ids, path=path, recording_id=recording_id)
    log_flight_record(stream, rec, run_info=run_info, trail_window_s=trail_window_s)
    stream.flush()
    stream.disconnect()
    return stream.get_recording_id()
