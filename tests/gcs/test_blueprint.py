"""A view that scales: what a recording of a fleet of 50 shows by default, and what it keeps.

A synthetic fleet of 50 on a 5 x 10 grid of slots 4 m apart (its vehicles on their slots)
written as `fleetmpc sim --rrd` writes a record, read back as the viewer reads it: the map's
links, labels and colours, and the blueprint stored with it."""

import numpy as np
import pytest
import rerun as rr
from viewer import blueprint_fields, recorded_blueprint

from fleetmpc.gcs.blueprint import FLEET_TAB, VEHICLE_TAB
from fleetmpc.gcs.palette import LABELLED_VEHICLES_MAX, vehicle_colour
from fleetmpc.gcs.record import FlightRecord
from fleetmpc.gcs.recording import LINK_NEAREST, link_pairs
from fleetmpc.gcs.telemetry import write_recording

PERIODS = 4
SPACING_M = 4.0


def _grid(n: int) -> FlightRecord:
    """N vehicles on their slots in rows of ten, the formation moving North at 1 m/s."""
    offsets = np.array([[-(i // 10), i % 10] for i in range(n)], dtype=float) * SPACING_M
    t = np.arange(PERIODS) * 0.2
    centre = np.stack([t, np.zeros(PERIODS)], axis=1)
    slots = centre[:, None] + offsets[None]
    return FlightRecord(
        scenario="grid",
        vehicle_ids=tuple(range(1, n + 1)),
        t_s=t,
        truth=np.concatenate([slots, np.zeros((PERIODS, n, 1))], axis=2),
        target=centre + [5.0, 0.0],
        target_velocity=np.tile([1.0, 0.0], (PERIODS, 1)),
        slots=slots,
        command=np.tile([1.0, 0.0], (PERIODS, n, 1)),
        c=np.zeros((PERIODS, n, 2)),
        beta=np.tile([1.0, 1.0, 0.0, 0.0], (PERIODS, n, 1)),
        beta_truth=np.tile([1.0, 1.0, 0.0, 0.0], (PERIODS, n, 1)),
        qp_ok=np.ones((PERIODS, n), dtype=bool),
        step_time_ms=np.ones((PERIODS, n)),
        desired_distance_m=np.linalg.norm(offsets[:, None] - offsets[None], axis=2),
        trail_m=5.0,
        slot_offsets_world=np.broadcast_to(offsets, (PERIODS, n, 2)).copy(),
        min_separation_m=SPACING_M,
        speed_max_m_s=2.0,
        yaw_rate_max_rad_s=0.5,
        d_safe_m=1.0,
    )


@pytest.fixture(scope="module")
def fleets(tmp_path_factory) -> dict[int, tuple[FlightRecord, object]]:
    """Recordings of a fleet of 50 and of the largest fleet the map names (12), by size."""
    tmp = tmp_path_factory.mktemp("fleets")
    out = {}
    for n in (50, LABELLED_VEHICLES_MAX):
        rec = _grid(n)
        write_recording(rec, tmp / f"grid{n}.rrd")
        out[n] = (rec, tmp / f"grid{n}.rrd")
    return out


def _component(path, entity: str, component: str, *, static: bool) -> list:
    """Every row of `component` on `entity` (its static rows, or its temporal ones)."""
    rows = []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path == entity and chunk.is_static == static:
            batch = chunk.to_record_batch()
            if component in batch.schema.names:
                rows += batch.column(batch.schema.names.index(component)).to_pylist()
    return rows


def _rgb(packed: int) -> tuple[int, int, int]:
    return ((packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255)


def test_the_map_links_each_vehicle_to_its_nearest_slots_only(fleets):
    rec, path = fleets[50]
    links = link_pairs(rec.desired_distance_m)
    assert len(links) <= LINK_NEAREST * 50 and len(links) < 50 * 49 // 2 / 10  # (not 1,225)
    d = rec.desired_distance_m
    linked = {tuple(p) for p in links.tolist()}
    for i in range(50):
        nearest = sorted((j for j in range(50) if j != i), key=lambda j: (d[i, j], j))
        assert all((min(i, j), max(i, j)) in linked for j in nearest[:LINK_NEAREST]), i
    # Only neighbours are linked: no link spans more than two steps of the grid.
    assert max(d[a, b] for a, b in linked) <= 2 * SPACING_M
    rows = _component(path, "/map/formation_links", "LineStrips2D:strips", static=False)
    assert len(rows) == PERIODS and all(len(row) == len(links) for row in rows)
    # A small fleet still has every pair linked.
    assert len(link_pairs(np.ones((3, 3)) - np.eye(3))) == 3


@pytest.mark.parametrize(("n", "shown"), [(50, False), (LABELLED_VEHICLES_MAX, True)])
def test_vehicles_are_named_up_to_twelve_and_slots_never(fleets, n, shown):
    _, path = fleets[n]
    labels = _component(path, "/map/vehicles", "Points2D:labels", static=True)
    assert labels == [[f"UAV {v}" for v in range(1, n + 1)]]  # (kept, shown or not)
    assert _component(path, "/map/vehicles", "Points2D:show_labels", static=True) == [[shown]]
    assert _component(path, "/map/slots", "Points2D:labels", static=True) == []


def test_each_of_fifty_vehicles_wears_its_own_colour(fleets):
    _, path = fleets[50]
    for entity, component in (
        ("/map/vehicles", "Points2D:colors"),
        ("/map/slots", "Points2D:colors"),
        ("/map/trails", "LineStrips2D:colors"),
        ("/series/formation_error", "SeriesLines:colors"),
    ):
        (packed,) = _component(path, entity, component, static=True)
        assert [_rgb(c) for c in packed] == [vehicle_colour(i) for i in range(50)], entity
    assert len({vehicle_colour(i) for i in range(50)}) == 50


def _views_by_tab(path) -> dict[str, list]:
    root = recorded_blueprint(path)
    (tabs,) = [c for c in root.children if getattr(c, "kind", "") == "tabs"]
    assert tabs.children[tabs.active].name == FLEET_TAB  # (the tab the viewer opens on)
    return {tab.name: tab.views(hidden=True) for tab in tabs.children}


def test_the_viewer_opens_on_the_fleet_series_the_rest_a_tab_away(fleets):
    _, path = fleets[50]
    tabs = _views_by_tab(path)
    assert set(tabs) == {FLEET_TAB, VEHICLE_TAB}
    fleet = {v.origin for v in tabs[FLEET_TAB]}
    assert fleet == {"series/centre_distance"} | {
        f"series/fleet/{name}"
        for name in (
            "min_separation",
            "formation_error",
            "step_time_ms",
            "stale_plans",
            "learning_error",
        )
    }
    per_vehicle = {v.origin for v in tabs[VEHICLE_TAB]}
    assert {"series/separation", "series/plan_age", "series/formation_error"} <= per_vehicle
    # Every series entity of the recording is in one tab or the other.
    entities = {
        chunk.entity_path.strip("/")
        for chunk in rr.chunk.RrdReader(path).stream()
        if chunk.entity_path.startswith("/series/")
    }
    assert entities == fleet | per_vehicle


def test_no_legend_covers_a_plot_and_the_side_panels_start_collapsed(fleets):
    _, path = fleets[50]
    fields = blueprint_fields(path)
    series = [v for vs in _views_by_tab(path).values() for v in vs if v.kind == "TimeSeries"]
    assert len(series) == 14
    for view in series:
        assert fields[f"{view.path}/PlotLegend"]["visible"] == [False], view.name
    for panel in ("blueprint_panel", "selection_panel", "time_panel"):
        assert fields[panel]["state"] == [2], panel  # rerun's PanelState.Collapsed


def test_the_map_is_fixed_on_the_whole_flight(fleets):
    """The blueprint the recording opens with fixes the map on every vehicle, slot and target
    position flown (with a margin), so a jump of the time cursor does not ease the camera."""
    rec, path = fleets[50]
    fields = blueprint_fields(path)
    (view,) = [v for v in recorded_blueprint(path).views() if v.origin == "map"]
    (bounds,) = fields[f"{view.path}/VisualBounds2D"]["range"]
    east = np.concatenate([rec.truth[..., 1].ravel(), rec.target[:, 1]])
    south = -np.concatenate([rec.truth[..., 0].ravel(), rec.target[:, 0]])
    for (low, high), values in ((bounds["x_range"], east), (bounds["y_range"], south)):
        assert low <= values.min() - 5.0 and high >= values.max() + 5.0
        assert high - low <= np.ptp(values) + 2 * 5.0 + 1e-9  # (a 5 m margin at this size)
