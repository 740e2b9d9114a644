"""The report's figures wear the viewer's colours; their legends stand beside the data, never on
it, and name at most as many vehicles as the map does."""

import dataclasses

import matplotlib.colors as mcolors
import numpy as np
import pytest
import rerun as rr

from fleetmpc.gcs import figures
from fleetmpc.gcs.palette import LABELLED_VEHICLES_MAX, vehicle_colour
from fleetmpc.gcs.telemetry import write_recording
from fleetmpc.lockstep.flight import run_lockstep


@pytest.fixture(scope="module")
def run(paper):
    return run_lockstep(paper, duration_s=2.0)


def _drawn(monkeypatch, rec, out) -> dict[str, object]:
    """The figures `write_figures` draws, by file name, kept open."""
    kept = {}
    save = figures._save

    def keep(fig, path):
        kept[path.name] = fig
        fig.canvas.draw()  # (the legend as it is saved)
        return save(fig, path)

    monkeypatch.setattr(figures, "_save", keep)
    monkeypatch.setattr(figures.plt, "close", lambda fig: None)
    figures.write_figures(rec, out)
    return kept


def _rgb(colour) -> tuple[int, int, int]:
    return tuple(round(255 * c) for c in mcolors.to_rgb(colour))


def _static_colours(path, entity: str, component: str) -> list[tuple[int, int, int]]:
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path == entity and chunk.is_static:
            batch = chunk.to_record_batch()
            if component in batch.schema.names:
                packed = batch.column(batch.schema.names.index(component)).to_pylist()[0]
                return [((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for c in packed]
    raise AssertionError(f"no {component} on {entity}")


def test_each_vehicle_and_pair_wears_its_viewer_colour(run, tmp_path, monkeypatch):
    rec = run
    path = tmp_path / "run.rrd"
    write_recording(rec, path)
    map_rgb = _static_colours(path, "/map/vehicles", "Points2D:colors")
    pair_rgb = _static_colours(path, "/series/separation", "SeriesLines:colors")
    drawn = _drawn(monkeypatch, rec, tmp_path / "figs")
    paths = drawn["fig1_paths.png"].axes[0]
    lines = {line.get_label(): _rgb(line.get_color()) for line in paths.get_lines()}
    for i, vid in enumerate(rec.vehicle_ids):
        assert lines[f"UAV {vid}"] == map_rgb[i], vid
    separation = drawn["fig3_separation.png"].axes[0]
    lines = {line.get_label(): _rgb(line.get_color()) for line in separation.get_lines()}
    ids = rec.vehicle_ids
    pairs = [f"UAV {ids[a]}-{ids[b]}" for a in range(len(ids)) for b in range(a + 1, len(ids))]
    assert [lines[p] for p in pairs] == pair_rgb
    assert not set(pair_rgb) & set(map_rgb)  # a pair never wears a vehicle's colour
    legends = 0
    for name, fig in drawn.items():
        for ax in fig.axes:
            legend = ax.get_legend()
            if legend is not None:
                legends += 1
                colours = [_rgb(h.get_color()) for h in legend.legend_handles]
                assert len(set(colours)) == len(colours), (name, colours)
                # Beside the plot: the legend's box and the axes' do not overlap.
                box, plot = legend.get_window_extent(), ax.get_window_extent()
                assert box.x0 >= plot.x1, (name, box, plot)
    assert legends == 5


def _wide(rec, n: int):
    """The record's first vehicle n times over, as a fleet of n (colours and legends are all
    that matter here)."""
    wide = {
        name: np.repeat(getattr(rec, name)[:, :1], n, axis=1)
        for name in ("truth", "slots", "slot_offsets_world", "c", "beta", "beta_truth")
    }
    return dataclasses.replace(
        rec, vehicle_ids=tuple(range(1, n + 1)), desired_distance_m=np.ones((n, n)), **wide
    )


def test_a_fleet_the_map_does_not_label_draws_no_legend_of_its_vehicles(run, tmp_path, monkeypatch):
    n = LABELLED_VEHICLES_MAX + 1
    drawn = _drawn(monkeypatch, _wide(run, n), tmp_path / "figs")
    assert drawn["fig1_paths.png"].axes[0].get_legend() is None
    assert drawn["fig3_separation.png"].axes[0].get_legend() is None
    assert drawn["fig4_centre_distance.png"].axes[0].get_legend() is not None
    # Every vehicle still wears its own colour, none another's.
    paths = drawn["fig1_paths.png"].axes[0]
    rgb = [_rgb(line.get_color()) for line in paths.get_lines()[: 2 * n : 2]]
    assert rgb == [vehicle_colour(i) for i in range(n)] and len(set(rgb)) == n


def test_a_fleet_of_twelve_is_named_in_the_legend(run, tmp_path, monkeypatch):
    drawn = _drawn(monkeypatch, _wide(run, LABELLED_VEHICLES_MAX), tmp_path / "figs")
    legend = drawn["fig1_paths.png"].axes[0].get_legend()
    names = [t.get_text() for t in legend.get_texts()]
    assert names[:LABELLED_VEHICLES_MAX] == [f"UAV {v}" for v in range(1, 13)]
