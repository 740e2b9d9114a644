"""A flight record as a Rerun recording (`.rrd`): a map, time series, events and a blueprint.

Everything is logged on the `sim_time` timeline, a duration in integer nanoseconds, through the
SDK's public column API: a slice of periods goes out as one `rr.send_columns` per entity (a
call costs some 0.1-0.4 ms whatever its rows, so the vehicles of a fleet share entities, one
instance or one line each, and a run is logged in slices: its map (`log_map`) and its time
series and flight_record rows (`log_series`), the latter in bigger slices if the caller likes;
`fleetmpc.gcs.telemetry.RerunSink` does both from a run's samples). Entity layout, the same for
a lockstep and a live run:

- `map/vehicles`: every vehicle's position (Points2D) and heading (Arrows2D), one instance
  per vehicle in fleet order, coloured and labelled by a static logged once;
- `map/trails` (LineStrips2D): each vehicle's step since the previous period, a two-point
  strip per vehicle and period; the blueprint shows this entity over the last `trail_window_s`
  before the time cursor (a visible time range on it alone), so the steps join into trails
  while a period costs one segment per vehicle, not the whole window;
- `map/formation_links` (each vehicle to the `LINK_NEAREST` slots nearest its own:
  `link_pairs`) as LineStrips2D; `map/target` and `map/slots` (one per vehicle) as Points2D;
- `map/target_observations` (Points2D): each target observation as the fleet received it (raw,
  before any filter: a script's or a recorded track's noisy fix, a MAVLink source's screened
  one), at its own time; the blueprint shows them over the trail window;
- `series/fleet/<name>` (`fleetmpc.gcs.fleet_series.FLEET_SERIES`: a line or two for the whole
  fleet, what the viewer shows by default);
- `series/separation` (one line per pair), `series/centre_distance`,
  `series/formation_error`, `series/c_norm`, `series/solve_time_ms` (one line per vehicle),
  `series/beta/effectiveness` and `series/beta/drift_m_s` (`BETA_SERIES`: two parameters each,
  learned, then truth, per parameter and vehicle) as Scalars, the lines named and
  coloured by a static SeriesLines;
- `events` (TextLog): QP fallbacks, each vehicle's target state as it changes (target lost:
  predicting, holding, reacquiring, tracking again); live runs add mode changes and STATUSTEXT;
- `map/plans` (each agent's planned horizon, a Points2D bead per planned period after the
  first, coloured row by row), `map/target_estimate` and `map/target_prediction` (the
  ground side's filtered target and its prediction over the horizon, made at each period's
  time from the observations stamped up to it), `series/plan_age` [s] (one line per vehicle
  and neighbour) and `series/setpoint_rate` [Hz];
- `meta` (static AnyValues), `flight_record` (AnyValues: one `periods` column, a float64
  list per period that packs every per-period FlightRecord field in `record_layout`'s order)
  and `run_end` (static AnyValues, logged at the end: what the plan bus did): what
  `fleetmpc.gcs.rrd_reader` needs to rebuild the FlightRecord bit for bit.

Every per-period item is logged at its own period's time, whenever the slice that holds it
goes out; events carry their own time too, which for a live run's events before the fleet
clock started is negative (fleet time runs back from the epoch at the run's speed).

Map frame: the viewer's 2-D x is East and its y is South (the viewer's y points down), so North
is up on screen, as in the paper's Fig. 1. `map_from_ned` is the only place that conversion lives.
"""

import json
import uuid
from functools import lru_cache
from pathlib import Path

import numpy as np
import rerun as rr

from fleetmpc.gcs.blueprint import BETA_SERIES, TIMELINE, TRAIL_WINDOW_S, fleet_blueprint
from fleetmpc.gcs.fleet_series import fleet_rows
from fleetmpc.gcs.metrics import pair_indices
from fleetmpc.gcs.palette import lighter, vehicle_colour
from fleetmpc.gcs.record import PERIOD_FIELDS, FlightRecord, LiveRows, RunConstants, period_rows
from fleetmpc.gcs.viewer import spawn_viewer as spawn_viewer_process

__all__ = [
    "APPLICATION_ID",
    "LEGACY_RECORD_ARRAYS",
    "LINK_NEAREST",
    "MIN_SEPARATION_COLUMN",
    "RECORD_ARRAYS",
    "RECORD_COLUMN",
    "log_events",
    "log_target_observations",
    "log_run_end",
    "MapExtent",
    "show_whole_flight",
    "log_map",
    "log_series",
    "log_meta",
    "open_recording",
    "map_from_ned",
    "record_layout",
    "sim_time_ns",
    "link_pairs",
]

APPLICATION_ID = "fleetmpc"
RECORD_ARRAYS = PERIOD_FIELDS
"""Per-period FlightRecord fields stored losslessly under `flight_record`."""
LEGACY_RECORD_ARRAYS = RECORD_ARRAYS[:-2]
"""The `flight_record` parts of a recording whose `meta` has no `prediction_horizon_periods`
(written before the agents' target prediction and plan ages were in it)."""
RECORD_COLUMN = "periods"
"""The `flight_record` component: one float64 list per period, the parts of `record_layout`
one after the other (qp_ok as 1.0 / 0.0)."""
MIN_SEPARATION_COLUMN = "min_separation_known_m"
"""The last part of a `flight_record` row: the run's minimum separation as known when the row
was logged (a growing record logs it with every slice, so the newest row has the whole run's).
It is the only copy: `meta` holds what does not change."""


def record_layout(
    n_vehicles: int, *, arrays: tuple[str, ...] = RECORD_ARRAYS
) -> tuple[tuple[str, tuple[int, ...]], ...]:
    """(name, per-period shape) of each part of a `flight_record` row, in order, for N vehicles:
    the `arrays` (RECORD_ARRAYS; a recording made before they held the agents' target
    prediction and plan ages, `LEGACY_RECORD_ARRAYS`), then MIN_SEPARATION_COLUMN."""
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
        "target_prediction": (2,),
        "plan_age_s": (n, max(n - 1, 0)),
    }
    return (*((name, shapes[name]) for name in arrays), (MIN_SEPARATION_COLUMN, (1,)))


_HEADING_ARROW_M = 2.0
LINK_NEAREST = 3
"""The map links each vehicle to this many of the slots nearest its own."""


_EAST_SOUTH = np.array([1.0, -1.0])
"""Signs of the map's axes from (East, North)."""


def map_from_ned(north_east_m: np.ndarray) -> np.ndarray:
    """(..., 2) North, East [m] -> (..., 2) viewer map x = East, y = South [m]."""
    return np.asarray(north_east_m, dtype=np.float64)[..., ::-1] * _EAST_SOUTH


def sim_time_ns(t_s: np.ndarray) -> np.ndarray:
    """Sample times [s] -> integer nanoseconds (int64) for the `sim_time` timeline."""
    return np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)


class _Slice:
    """Rows of periods on the `sim_time` timeline: sends each entity's columns of them with
    `rr.send_columns`."""

    def __init__(self, stream: rr.RecordingStream, t_ns: np.ndarray) -> None:
        self.stream = stream
        self.t_ns = np.asarray(t_ns, dtype=np.int64)
        self.rows = len(self.t_ns)

    def send(self, path: str, columns: list, *, rows: np.ndarray | None = None) -> None:
        """Send columns of every row (or of the rows selected by `rows`, a mask or indices)."""
        t_ns = self.t_ns if rows is None else self.t_ns[rows]
        index = rr.TimeColumn(TIMELINE, duration=t_ns.astype("timedelta64[ns]"))
        self.stream.send_columns(path, indexes=[index], columns=columns)

    def points(
        self,
        path: str,
        xy: np.ndarray,
        *,
        arrows: np.ndarray | None = None,
        rows: np.ndarray | None = None,
    ) -> None:
        """Points2D positions xy (R, n, 2), n in every row sent (every row, or those `rows`
        selects); with `arrows` (R, n, 2) also Arrows2D from those positions."""
        r, n = xy.shape[:2]
        flat = xy.reshape(-1, 2)
        columns = [*rr.Points2D.columns(positions=flat).partition([n] * r)]
        if arrows is not None:
            vectors = arrows.reshape(-1, 2)
            arrow = rr.Arrows2D.columns(origins=flat, vectors=vectors)
            columns += [*arrow.partition([n] * r)]
        self.send(path, columns, rows=rows)

    def strips(self, path: str, strips: np.ndarray, *, rows: np.ndarray | None = None) -> None:
        """LineStrips2D: strips (R, S, P, 2), S strips of P points in each row sent (every row,
        or those `rows` selects: nothing is logged at the others, so the viewer keeps what it
        had). A strip with a non-finite point is sent empty, so every strip keeps its instance's
        colour."""
        r, count = strips.shape[:2]
        lines = strips.reshape(r * count, -1, 2)
        finite = np.isfinite(lines).all(axis=(1, 2))
        if not finite.all():  # (one array of equal strips converts far faster than a list)
            lines = [s if ok else s[:0] for s, ok in zip(lines, finite, strict=True)]
        column = rr.LineStrips2D.columns(strips=lines).partition([count] * r)
        self.send(path, [*column], rows=rows)

    def scalars(self, path: str, values: np.ndarray) -> None:
        """Scalars: values (rows,) or (rows, lines), one line per column (an entity with several
        lines names them with a static SeriesLines). Rows with no finite value are not sent."""
        v = np.asarray(values, dtype=np.float64).reshape(self.rows, -1)
        keep = np.isfinite(v).any(axis=1)
        if keep.any():
            self.send(path, [*rr.Scalars.columns(scalars=v[keep])], rows=keep)

    def values(self, path: str, name: str, rows: np.ndarray) -> None:
        """AnyValues: a float64 list of width W per row, rows (rows, W), as component `name`."""
        width = rows.shape[1]
        column = rr.AnyValues.columns(**{name: rows.ravel()}).partition([width] * self.rows)
        self.send(path, [*column])


def log_meta(stream: rr.RecordingStream, constants: RunConstants, *, run_info: dict) -> None:
    """The static `meta`: the run's constants and facts about it (JSON-able: learning, seed,
    ...) that are not in the record; logged when a recording opens."""
    c = constants
    stream.log(
        "meta",
        rr.AnyValues(
            scenario=c.scenario,
            vehicle_ids=np.asarray(c.vehicle_ids, dtype=np.int64),
            desired_distance_m=np.asarray(c.desired_distance_m, dtype=np.float64).ravel(),
            trail_m=np.array([c.trail_m], dtype=np.float64),
            speed_max_m_s=np.array([c.speed_max_m_s], dtype=np.float64),
            yaw_rate_max_rad_s=np.array([c.yaw_rate_max_rad_s], dtype=np.float64),
            d_safe_m=np.array([c.d_safe_m], dtype=np.float64),
            prediction_horizon_periods=np.array([c.prediction_horizon_periods], dtype=np.int64),
            run_info_json=json.dumps(run_info, sort_keys=True),
        ),
        static=True,
    )


def _record_rows(columns: _Slice, rec: FlightRecord) -> None:
    """The record's periods as `flight_record` rows (`record_layout`)."""
    rows = columns.rows
    parts = [period_rows(rec, name).reshape(rows, -1) for name in RECORD_ARRAYS]
    parts.append(np.full((rows, 1), rec.min_separation_m))
    packed = np.concatenate(parts, axis=1, dtype=np.float64)
    columns.values("flight_record", RECORD_COLUMN, packed)


def _map(columns: _Slice, rec: FlightRecord, *, start: int) -> None:
    k, n = rec.truth.shape[:2]
    before = max(start - 1, 0)
    pos = map_from_ned(rec.truth[before:, :, :2])  # periods before .. k - 1
    here = pos[start - before :]
    # Each period's step: from the previous period's position (period 0: from itself).
    rows = np.arange(start - before, k - before)
    steps = pos[np.stack([np.maximum(rows - 1, 0), rows], axis=1)]  # (K, 2 points, N, 2)
    yaw = rec.truth[start:, :, 2]
    heading = map_from_ned(np.stack([np.cos(yaw), np.sin(yaw)], axis=-1) * _HEADING_ARROW_M)
    columns.points("map/vehicles", here, arrows=heading)
    columns.strips("map/trails", steps.transpose(0, 2, 1, 3))
    columns.points("map/slots", map_from_ned(rec.slots[start:]))
    columns.points("map/target", map_from_ned(rec.target[start:])[:, None, :])
    links = link_pairs(rec.desired_distance_m)
    if len(links):
        columns.strips("map/formation_links", here[:, links])  # (K, L, 2 points, 2)


def link_pairs(desired_distance_m: np.ndarray, *, nearest: int = LINK_NEAREST) -> np.ndarray:
    """(L, 2) the vehicle pairs the map links, in `pair_indices` order: each vehicle with the
    `nearest` slots closest to its own in the formation (so at most `nearest` x N links, not
    every pair: a fleet of 50 has 1,225)."""
    d = np.asarray(desired_distance_m, dtype=np.float64)
    n = len(d)
    pairs = set()
    for i in range(n):
        others = [j for j in np.argsort(d[i], kind="stable") if j != i][:nearest]
        pairs.update((min(i, j), max(i, j)) for j in others)
    return np.array(sorted(pairs), dtype=np.intp).reshape(-1, 2)


@lru_cache(maxsize=8)
def _pairs(n: int) -> np.ndarray:
    """(P, 2) the vehicle indices of every pair, in `pair_indices` order."""
    return np.array(pair_indices(n), dtype=np.intp).reshape(-1, 2)


def _norm2(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over a last axis of length 2."""
    return np.hypot(v[..., 0], v[..., 1])


def _series(
    columns: _Slice, rec: FlightRecord, live: LiveRows, *, plan_stale_s: float | None
) -> None:
    pos = rec.truth[:, :, :2]
    pairs = _pairs(len(rec.vehicle_ids))
    separation = _norm2(pos[:, pairs[:, 0]] - pos[:, pairs[:, 1]])
    if len(pairs):
        columns.scalars("series/separation", separation)
    fleet = fleet_rows(rec, live, separation_m=separation, plan_stale_s=plan_stale_s)
    for name, rows in fleet.items():
        columns.scalars(f"series/fleet/{name}", rows)
    centre = np.mean(pos - rec.slot_offsets_world, axis=1)
    columns.scalars("series/centre_distance", _norm2(centre - rec.target))
    columns.scalars("series/formation_error", _norm2(pos - rec.slots))
    columns.scalars("series/c_norm", _norm2(rec.c))
    columns.scalars("series/solve_time_ms", rec.step_time_ms)
    k = len(rec.t_s)
    for name, (p, q) in BETA_SERIES:
        # (K, N, 2 entries) -> (K, entry, vehicle), learned then truth
        learned = rec.beta[:, :, p : q + 1].transpose(0, 2, 1).reshape(k, -1)
        truth = rec.beta_truth[:, :, p : q + 1].transpose(0, 2, 1).reshape(k, -1)
        columns.scalars(f"series/beta/{name}", np.concatenate([learned, truth], axis=1))


def _plans(columns: _Slice, plans: np.ndarray) -> None:
    """Each vehicle's plan (K, N, M + 1, 2) as a bead per planned period after the first (the
    first is where the vehicle is), in a lighter shade of the vehicle's colour, so a plan
    straight ahead shows on the heading arrow it lies along. Rows where no vehicle has a plan
    are not logged; in the others a vehicle without one has no beads."""
    n = plans.shape[1]
    ahead = plans[:, :, 1:]
    has = np.isfinite(ahead).all(axis=(2, 3)) & (ahead.shape[2] > 0)  # (K, N)
    present = has.any(axis=1)
    if not present.any():
        return
    shade = np.array([lighter(vehicle_colour(i)) for i in range(n)], dtype=np.uint8)  # (N, 3)
    beads = ahead.shape[2]
    positions = map_from_ned(ahead[has]).reshape(-1, 2)  # (vehicle-plans x beads, 2)
    colours = np.repeat(shade[np.nonzero(has)[1]], beads, axis=0)
    counts = (has[present].sum(axis=1) * beads).tolist()
    column = rr.Points2D.columns(positions=positions, colors=colours).partition(counts)
    columns.send("map/plans", [*column], rows=present)


def _live_map(columns: _Slice, live: LiveRows) -> None:
    """Plans and the target predictions of a slice's live rows."""
    _plans(columns, live.plans)
    # Each row's prediction, made at its own time; rows before the first observation have none.
    known = np.isfinite(live.target_path).all(axis=(1, 2))
    if known.any():
        path = map_from_ned(live.target_path[known])[:, None]  # (rows, 1 strip, M + 1, 2)
        columns.strips("map/target_prediction", path, rows=known)
        columns.points("map/target_estimate", path[:, :, 0], rows=known)


def _live_series(columns: _Slice, live: LiveRows) -> None:
    """Setpoint rates and plan ages of a slice's live rows."""
    columns.scalars("series/setpoint_rate", live.setpoint_rate_hz)
    if live.plan_age_s.shape[2]:
        columns.scalars("series/plan_age", live.plan_age_s)


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


def log_target_observations(
    stream: rr.RecordingStream, observations: list[tuple[int, float, float]]
) -> None:
    """Log target observations (fleet time ns, North, East [m]) as received, each at its own
    time, to `map/target_observations` (one point per observation) in one column batch."""
    if not observations:
        return
    times, north, east = (np.array(part) for part in zip(*observations, strict=True))
    stream.send_columns(
        "map/target_observations",
        indexes=[rr.TimeColumn(TIMELINE, duration=times.astype("timedelta64[ns]"))],
        columns=rr.Points2D.columns(positions=map_from_ned(np.column_stack([north, east]))),
    )


def _qp_events(
    rec: FlightRecord, *, t_ns: np.ndarray, run_start: bool
) -> list[tuple[int, str, str]]:
    """Events of the record's rows (at times t_ns), the run's start first if they begin it."""
    events = []
    if run_start:
        events.append(
            (
                int(t_ns[0]),
                "INFO",
                f"run start: scenario {rec.scenario}, UAVs {list(rec.vehicle_ids)}",
            )
        )
    k_idx, i_idx = np.nonzero(~np.asarray(rec.qp_ok, dtype=bool))
    for k, i in zip(k_idx, i_idx, strict=True):
        events.append(
            (
                int(t_ns[k]),
                "WARN",
                f"UAV {rec.vehicle_ids[i]}: QP failed, fallback input applied",
            )
        )
    return events


def log_map(stream: rr.RecordingStream, rec: FlightRecord, live: LiveRows, *, head: bool) -> None:
    """The map of a slice of periods: the record's rows (with `head`, the first is only where
    the trail's first step starts: the period before the slice) and the live rows of the
    periods logged (plans, and each period's target prediction)."""
    start = 1 if head else 0
    columns = _Slice(stream, sim_time_ns(rec.t_s[start:]))
    _map(columns, rec, start=start)
    _live_map(columns, live)


def log_series(
    stream: rr.RecordingStream,
    rec: FlightRecord,
    live: LiveRows,
    *,
    run_start: bool,
    plan_stale_s: float | None = None,
) -> None:
    """The time series (the fleet's among them: `fleetmpc.gcs.fleet_series`, the stale plans
    those older than `plan_stale_s` [s]), the `flight_record` rows and the QP events of a slice
    of periods (the run's start event first when it begins the run)."""
    t_ns = sim_time_ns(rec.t_s)
    columns = _Slice(stream, t_ns)
    _record_rows(columns, rec)
    _series(columns, rec, live, plan_stale_s=plan_stale_s)
    _live_series(columns, live)
    log_events(stream, _qp_events(rec, t_ns=t_ns, run_start=run_start))


class MapExtent:
    """The box [m, map frame] that holds every vehicle, slot and target position logged on
    the map, with a margin for what is drawn around them (headings, plans, the target's
    prediction)."""

    MARGIN_M = 5.0

    def __init__(self) -> None:
        self.low = np.full(2, np.inf)
        self.high = np.full(2, -np.inf)

    def add(self, rec: FlightRecord) -> None:
        """Widen the box to the positions of `rec`'s periods."""
        ned = [rec.truth[..., :2].reshape(-1, 2), rec.slots.reshape(-1, 2), rec.target[:, :2]]
        points = map_from_ned(np.concatenate(ned))
        self.low = np.minimum(self.low, points.min(axis=0))
        self.high = np.maximum(self.high, points.max(axis=0))

    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]] | None:
        """((x min, x max), (y min, y max)) with the margin; None before any position."""
        if not np.all(np.isfinite(self.low)):
            return None
        margin = max(self.MARGIN_M, 0.05 * float(np.max(self.high - self.low)))
        low, high = self.low - margin, self.high + margin
        return (float(low[0]), float(high[0])), (float(low[1]), float(high[1]))


def show_whole_flight(
    stream: rr.RecordingStream,
    vehicle_ids: tuple[int, ...],
    extent: MapExtent,
    *,
    trail_window_s: float = TRAIL_WINDOW_S,
) -> None:
    """Send the blueprint again, its map fixed on everything flown (`MapExtent`), and make
    it the one a viewer shows: the recording then opens on the whole flight, and a jump of
    the time cursor redraws the map in one frame instead of easing the camera to a new fit.
    A viewer watching the run live switches to it when the run ends. `trail_window_s`: as
    `open_recording` was given it."""
    bounds = extent.bounds()
    if bounds is not None:
        view = fleet_blueprint(
            vehicle_ids=vehicle_ids, trail_window_s=trail_window_s, map_bounds=bounds
        )
        stream.send_blueprint(view, make_active=True, make_default=True)


def log_run_end(stream: rr.RecordingStream, facts: dict) -> None:
    """The static `run_end`: facts about the run known only when it ends (JSON-able: what the
    plan bus did), logged before the recording closes."""
    stream.log("run_end", rr.AnyValues(run_end_json=json.dumps(facts, sort_keys=True)), static=True)


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
    `spawn_viewer`: start a local viewer (`fleetmpc.gcs.viewer`: its analytics off) and
    stream to it;
    `trail_window_s`: length of the trail the map shows behind each vehicle [s].
    """
    stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or str(uuid.uuid4()))
    blueprint = fleet_blueprint(vehicle_ids=vehicle_ids, trail_window_s=trail_window_s)
    if spawn_viewer:
        viewer_url = viewer_url or spawn_viewer_process()
    sinks = []
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        sinks.append(rr.FileSink(path))
    if viewer_url is not None:
        sinks.append(rr.GrpcSink(viewer_url))
    if sinks:
        stream.set_sinks(*sinks, default_blueprint=blueprint)
    return stream
