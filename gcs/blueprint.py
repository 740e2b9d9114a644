"""How a fleet recording looks: the viewer's layout (the blueprint), and the colours, labels
and line names logged once when a recording opens.

Each vehicle keeps one colour everywhere (its point, heading, trail, slot and plan on the map,
its line in every per-vehicle series, and in the report's figures: `fleetmpc.gcs.palette`); a
series of pairs takes the colours after the vehicles'.
The map takes two fifths of the width above the event log; the time series sit in two columns
beside it, the legends of the many-line panels hidden so they do not cover the plot (a line
names itself on hover). `fleetmpc.gcs.recording` logs the data on these entities.
"""

import rerun as rr
import rerun.blueprint as rrb

from fleetmpc.gcs.metrics import pair_indices
from fleetmpc.gcs.palette import CENTRE_RGB, pair_colour, vehicle_colour

__all__ = [
    "BETA_SERIES",
    "TIMELINE",
    "TRAIL_WINDOW_S",
    "fleet_blueprint",
    "log_statics",
]

TIMELINE = "sim_time"
"""The recording's one timeline: fleet time, a duration in integer nanoseconds."""
BETA_SERIES = (("effectiveness", (0, 1)), ("drift_m_s", (2, 3)))
"""Entities `series/beta/<name>` and the beta entries each holds: its lines are the first entry
of every vehicle, then the second, learned; then the same of the truth."""
_BETA_LINE_NAMES = ("speed", "yaw rate", "drift North", "drift East")
TRAIL_WINDOW_S = 20.0
"""Default length of the trail the map shows behind each vehicle [s]."""


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
    # Panels with many lines hide their legend (it would cover the plot); the lines keep their
    # vehicles' map colours and name themselves on hover.
    hidden = rrb.PlotLegend(visible=False)
    series = [
        rrb.TimeSeriesView(origin="series/separation", name="separation [m]"),
        rrb.TimeSeriesView(origin="series/centre_distance", name="centre distance [m]"),
        rrb.TimeSeriesView(origin="series/formation_error", name="formation error [m]"),
        rrb.TimeSeriesView(origin="series/c_norm", name="||c||"),
        rrb.TimeSeriesView(
            origin="series/beta/effectiveness",
            name="effectiveness (learned, truth)",
            plot_legend=hidden,
        ),
        rrb.TimeSeriesView(
            origin="series/beta/drift_m_s", name="drift [m/s] (learned, truth)", plot_legend=hidden
        ),
        rrb.TimeSeriesView(origin="series/solve_time_ms", name="agent step [ms]"),
        rrb.TimeSeriesView(
            origin="series/plan_age", name="neighbour plan age [s]", plot_legend=hidden
        ),
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
            rrb.Grid(*series, grid_columns=2),
            column_shares=[2, 3],
        ),
    )


def _series_names(ids: tuple[int, ...]) -> dict[str, tuple[list[str], list[tuple[int, ...]]]]:
    """Line names and colours of every multi-line series entity (logged once, static)."""
    uav = [f"UAV {v}" for v in ids]
    rgb = [vehicle_colour(i) for i in range(len(ids))]
    pairs = pair_indices(len(ids))
    out = {
        "series/centre_distance": (["centre distance"], [CENTRE_RGB]),
        "series/separation": (
            [f"{ids[a]}-{ids[b]}" for a, b in pairs],
            [pair_colour(p, vehicles=len(ids)) for p in range(len(pairs))],
        ),
    }
    out["series/setpoint_rate"] = (uav, rgb)
    out["series/plan_age"] = (
        [f"UAV {v} sees {o}" for v in ids for o in ids if o != v],
        [vehicle_colour(i) for i, v in enumerate(ids) for o in ids if o != v],
    )
    for name in _PER_VEHICLE_SERIES:
        out[f"series/{name}"] = (uav, rgb)
    for name, entries in BETA_SERIES:
        # The second entry's lines a lighter shade of the vehicle's colour; the truth's faint.
        learned = [f"UAV {v} {_BETA_LINE_NAMES[e]}" for e in entries for v in ids]
        shades = rgb + [tuple((x + 255) // 2 for x in c) for c in rgb]
        colours = shades + [(*c, 110) for c in shades]
        out[f"series/beta/{name}"] = (learned + [f"{line} truth" for line in learned], colours)
    return out


def log_statics(stream: rr.RecordingStream, vehicle_ids: tuple[int, ...]) -> None:
    """Colours, labels and line names: logged once, when a recording opens (before the fleet
    flies, so that the first logging calls of a process, which are slow, are not paid in
    flight)."""
    ids = vehicle_ids
    rgb = [vehicle_colour(i) for i in range(len(ids))]
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
    stream.log("map/plans", rr.LineStrips2D.from_fields(colors=rgb), static=True)
    stream.log(
        "map/target_prediction",
        rr.LineStrips2D.from_fields(colors=[(0, 0, 0)], radii=[-1.0]),
        static=True,
    )
    for path, (names, colours) in _series_names(ids).items():
        stream.log(path, rr.SeriesLines(names=names, colors=colours), static=True)


_PER_VEHICLE_SERIES = ("formation_error", "c_norm", "solve_time_ms")
"""Series entities with one line per vehicle, besides beta and the live-only ones."""
