"""How a fleet recording looks: the viewer's layout (the blueprint), and the colours, labels
and line names logged once when a recording opens.

The map takes half the width above the event log; beside it two tabs of time series. The
first, shown, holds the fleet-level series (`fleetmpc.gcs.fleet_series`: a line or two
whatever the fleet's size); the second the per-vehicle and per-pair ones, which are in every
recording but drawn only when asked for (a fleet of 50 has 1,225 separations). No plot shows a
legend (each view's title names its lines, and a line names itself on hover), and the side
panels start collapsed, so the data has the screen. Each vehicle keeps one colour everywhere
(its point, heading, trail, slot and plan on the map, its line in every per-vehicle series, and
in the report's figures: `fleetmpc.gcs.palette`); a series of pairs takes the colours after the
vehicles'. Vehicles are named on the map up to `LABELLED_VEHICLES_MAX` of them (a larger
fleet's names are logged but not shown: `show_labels`); slots are never named (each sits under
its vehicle).
`fleetmpc.gcs.recording` logs the data on these entities.
"""

import rerun as rr
import rerun.blueprint as rrb

from fleetmpc.gcs.fleet_series import FLEET_SERIES
from fleetmpc.gcs.metrics import pair_indices
from fleetmpc.gcs.palette import (
    CENTRE_RGB,
    LABELLED_VEHICLES_MAX,
    TARGET_RGB,
    lighter,
    pair_colour,
    vehicle_colour,
)

__all__ = [
    "BETA_SERIES",
    "FLEET_TAB",
    "TIMELINE",
    "TRAIL_WINDOW_S",
    "VEHICLE_TAB",
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
FLEET_TAB = "fleet"
"""The tab of fleet-level series, shown when the viewer opens."""
VEHICLE_TAB = "per vehicle and pair"
"""The tab of per-vehicle and per-pair series."""
_FLEET_LINE_RGB = (CENTRE_RGB, lighter(CENTRE_RGB))
"""A fleet series' first line (the worst, or the only) and its second (a median): the
formation centre's cyan, which no vehicle wears."""
_LIMIT_RGB = (214, 39, 40)
"""A limit drawn as a line (d_safe)."""


def _series_view(origin: str, name: str) -> rrb.TimeSeriesView:
    """A time-series view without a legend (its title names its lines)."""
    return rrb.TimeSeriesView(origin=origin, name=name, plot_legend=rrb.PlotLegend(visible=False))


def _fleet_views() -> list[rrb.TimeSeriesView]:
    views = [_series_view("series/centre_distance", "centre distance to the target [m]")]
    views += [_series_view(f"series/fleet/{n}", title) for n, (title, _) in FLEET_SERIES.items()]
    return views


def _vehicle_views() -> list[rrb.TimeSeriesView]:
    return [
        _series_view("series/separation", "separation per pair [m]"),
        _series_view("series/formation_error", "formation error [m]"),
        _series_view("series/c_norm", "||c||"),
        _series_view("series/solve_time_ms", "agent step [ms]"),
        _series_view("series/beta/effectiveness", "effectiveness (learned, truth)"),
        _series_view("series/beta/drift_m_s", "drift [m/s] (learned, truth)"),
        _series_view("series/plan_age", "neighbour plan age [s]"),
        _series_view("series/setpoint_rate", "setpoint rate [Hz]"),
    ]


def fleet_blueprint(
    *,
    vehicle_ids: tuple[int, ...],
    trail_window_s: float = TRAIL_WINDOW_S,
    map_bounds: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> rrb.Blueprint:
    """The viewer layout: the map on the left, the time series on the right (the fleet's
    shown, the per-vehicle ones a tab away); the map shows `map/trails` and the target's raw
    observations over the last `trail_window_s` [s] before the time cursor; the side panels
    collapsed.

    `map_bounds` ((x min, x max), (y min, y max)) [m, map frame] fixes what the map shows;
    without it the viewer fits the map to what it shows at the time cursor, and eases the
    camera to each new fit over several frames (most of a second each with software
    rendering) whenever the cursor jumps."""
    bounds = {}
    if map_bounds is not None:
        x_range, y_range = map_bounds
        bounds["visual_bounds"] = rrb.VisualBounds2D(x_range=x_range, y_range=y_range)
    trail = rrb.VisibleTimeRanges(
        timeline=TIMELINE,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-trail_window_s),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    origin="map",
                    name=f"map ({len(vehicle_ids)} UAVs)",
                    overrides={"/map/trails": trail, "/map/target_observations": trail},
                    **bounds,
                ),
                rrb.TextLogView(origin="events", name="events"),
                row_shares=[4, 1],
            ),
            rrb.Tabs(
                rrb.Grid(*_fleet_views(), grid_columns=2, name=FLEET_TAB),
                rrb.Grid(*_vehicle_views(), grid_columns=2, name=VEHICLE_TAB),
                active_tab=0,
            ),
            column_shares=[1, 1],
        ),
        collapse_panels=True,
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
        shades = rgb + [lighter(c) for c in rgb]
        colours = shades + [(*c, 110) for c in shades]
        out[f"series/beta/{name}"] = (learned + [f"{line} truth" for line in learned], colours)
    for name, (_, lines) in FLEET_SERIES.items():
        colours = [_LIMIT_RGB] if name == "min_separation" else [_FLEET_LINE_RGB[1]]
        out[f"series/fleet/{name}"] = (list(lines), [_FLEET_LINE_RGB[0], *colours][: len(lines)])
    return out


def log_statics(stream: rr.RecordingStream, vehicle_ids: tuple[int, ...]) -> None:
    """Colours, labels and line names: logged once, when a recording opens (before the fleet
    flies, so that the first logging calls of a process, which are slow, are not paid in
    flight)."""
    ids = vehicle_ids
    rgb = [vehicle_colour(i) for i in range(len(ids))]
    stream.log(
        "map/vehicles",
        rr.Points2D.from_fields(
            colors=rgb,
            labels=[f"UAV {v}" for v in ids],
            show_labels=len(ids) <= LABELLED_VEHICLES_MAX,
            radii=[-4.0],
        ),
        static=True,
    )
    stream.log("map/vehicles", rr.Arrows2D.from_fields(colors=rgb), static=True)
    stream.log("map/trails", rr.LineStrips2D.from_fields(colors=rgb), static=True)
    stream.log("map/slots", rr.Points2D.from_fields(colors=rgb, radii=[-3.0]), static=True)
    stream.log(
        "map/formation_links",
        rr.LineStrips2D.from_fields(colors=[(128, 128, 128, 90)], radii=[-0.75]),
        static=True,
    )
    stream.log(
        "map/target", rr.Points2D.from_fields(colors=[TARGET_RGB], radii=[-5.0]), static=True
    )
    # A plan's beads (coloured row by row) over the heading arrows they lie along.
    stream.log("map/plans", rr.Points2D.from_fields(radii=[-2.0], draw_order=40.0), static=True)
    stream.log(
        "map/target_prediction",
        rr.LineStrips2D.from_fields(colors=[TARGET_RGB], radii=[-1.0]),
        static=True,
    )
    stream.log(
        "map/target_estimate",
        rr.Points2D.from_fields(colors=[TARGET_RGB], radii=[-3.0]),
        static=True,
    )
    stream.log(
        "map/target_observations",
        rr.Points2D.from_fields(colors=[(*TARGET_RGB, 110)], radii=[-1.5]),
        static=True,
    )
    for path, (names, colours) in _series_names(ids).items():
        stream.log(path, rr.SeriesLines(names=names, colors=colours), static=True)


_PER_VEHICLE_SERIES = ("formation_error", "c_norm", "solve_time_ms")
"""Series entities with one line per vehicle, besides beta and the live-only ones."""
