"""One telemetry path: the lockstep simulation and the ground station write the same recording.

The live side is a `GroundStation` fed what a fleet that flew the lockstep run would send it
(`fleetmpc.bench.telemetry.period_messages`), flushed as it flushes in flight."""

import numpy as np
import pytest
import rerun as rr

from fleetmpc.bench.telemetry import receive_period
from fleetmpc.errors import ConfigError
from fleetmpc.gcs.fleet_series import FLEET_SERIES
from fleetmpc.gcs.metrics import compute_metrics
from fleetmpc.gcs.rrd_reader import read_recording
from fleetmpc.gcs.station import GroundStation
from fleetmpc.gcs.telemetry import MemorySink, RerunSink, open_sink
from fleetmpc.lockstep.flight import run_lockstep

DURATION_S = 10.0


def _entities(path) -> dict[str, set[str]]:
    """Entity path -> the components logged on it, over the whole recording."""
    out: dict[str, set[str]] = {}
    for chunk in rr.chunk.RrdReader(path).stream():
        names = chunk.to_record_batch().schema.names
        out.setdefault(chunk.entity_path, set()).update(
            n for n in names if n != "rerun.controls.RowId" and n != "sim_time"
        )
    return out


@pytest.fixture(scope="module")
def recordings(paper, tmp_path_factory):
    """A lockstep recording of paper.toml, and the ground station's of the same flight."""
    tmp = tmp_path_factory.mktemp("telemetry")
    sim_rrd, live_rrd = tmp / "sim.rrd", tmp / "live.rrd"
    memory = MemorySink()
    rec = run_lockstep(
        paper, duration_s=DURATION_S, sinks=[RerunSink(path=sim_rrd), memory], run_info={}
    )
    gs = GroundStation(paper, speed=1.0, duration_s=DURATION_S)
    gs.open_sinks([RerunSink(path=live_rrd)])
    for k in range(len(rec.t_s)):
        # Each vehicle sees its neighbours' plans one period old.
        receive_period(gs, rec, k, plan_age_ns=200_000_000, setpoint_rate_hz=5.0)
        if k % 20 == 19:
            gs.flush()
    gs.flush(final=True)
    gs.close_sinks()
    return rec, memory, sim_rrd, live_rrd


def test_lockstep_and_live_recordings_hold_the_same_entities(recordings) -> None:
    _, _, sim_rrd, live_rrd = recordings
    sim, live = _entities(sim_rrd), _entities(live_rrd)
    assert sim == live
    for entity in ("/map/vehicles", "/map/plans", "/map/target_prediction", "/flight_record"):
        assert entity in sim
    for series in ("separation", "plan_age", "setpoint_rate", "beta/effectiveness"):
        assert f"/series/{series}" in sim


def test_both_read_back_into_the_record_the_metrics_read(recordings) -> None:
    rec, memory, sim_rrd, live_rrd = recordings
    sim, live = read_recording(sim_rrd).record, read_recording(live_rrd).record
    for back in (sim, live):
        assert back.truth.shape == rec.truth.shape
        np.testing.assert_array_equal(back.truth, rec.truth)  # the live telemetry is the truth
        assert compute_metrics(back)["min_separation_m"] > 0
    np.testing.assert_array_equal(sim.command, rec.command)
    np.testing.assert_array_equal(sim.beta, rec.beta)
    assert sim.min_separation_m == rec.min_separation_m
    # The memory sink holds the very samples the lockstep record stacks.
    np.testing.assert_array_equal(memory.record().truth, rec.truth)
    np.testing.assert_array_equal(memory.record().step_time_ms, rec.step_time_ms)


def _temporal_rows(path, entity: str, component: str) -> tuple[np.ndarray, list]:
    """The sim_time [ns] and the `component` values of every temporal row of `entity`, in time
    order, as the recording holds them."""
    times, values = [], []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            times.append(batch.column(batch.schema.get_field_index("sim_time")).cast("int64"))
            values += batch.column(batch.schema.names.index(component)).to_pylist()
    t_ns = np.concatenate([t.to_numpy() for t in times])
    order = np.argsort(t_ns, kind="stable")
    return t_ns[order], [values[i] for i in order]


@pytest.mark.parametrize("which", ["sim", "live"])
def test_the_map_holds_every_period_at_its_own_time(recordings, which) -> None:
    """The gate: from the first period on, every period's target prediction, plans, vehicles
    and target are on the map at that period's time, so what the map shows at any time is never
    older than one control period; each prediction starts where the target then is."""
    rec, _, sim_rrd, live_rrd = recordings
    path = sim_rrd if which == "sim" else live_rrd
    period_ns = round((rec.t_s[1] - rec.t_s[0]) * 1e9)
    want_ns = np.arange(len(rec.t_s)) * period_ns
    for entity, component in (
        ("/map/vehicles", "Points2D:positions"),
        ("/map/target", "Points2D:positions"),
        ("/map/plans", "Points2D:positions"),
        ("/map/target_prediction", "LineStrips2D:strips"),
    ):
        t_ns, _ = _temporal_rows(path, entity, component)
        np.testing.assert_array_equal(t_ns, want_ns, err_msg=entity)
    t_ns, strips = _temporal_rows(path, "/map/target_prediction", "LineStrips2D:strips")
    assert np.diff(t_ns).max() == period_ns and t_ns[0] == 0
    start = np.array([row[0][0] for row in strips])  # map x East, y South
    target = np.stack([rec.target[:, 1], -rec.target[:, 0]], axis=1)
    error = np.hypot(*(start - target).T)
    # (observed with 5 cm of noise; one prediction per flush ran up to 4 s, 3 m, behind)
    assert error.max() < 0.25 and np.median(error) < 0.05


@pytest.mark.parametrize("which", ["sim", "live"])
def test_the_fleet_series_hold_every_period(recordings, which) -> None:
    """The fleet-level series are in both recordings at every period's time: the closest pair
    of each period, the stale plans (none: each plan is one period old, within the agents'
    limit; the first period, before any plan, has none reported in lockstep)."""
    rec, _, sim_rrd, live_rrd = recordings
    path = sim_rrd if which == "sim" else live_rrd
    period_ns = round((rec.t_s[1] - rec.t_s[0]) * 1e9)
    want_ns = np.arange(len(rec.t_s)) * period_ns
    for name in FLEET_SERIES:
        t_ns, _ = _temporal_rows(path, f"/series/fleet/{name}", "Scalars:scalars")
        first = 1 if name == "stale_plans" and which == "sim" else 0
        np.testing.assert_array_equal(t_ns, want_ns[first:], err_msg=name)
    _, closest = _temporal_rows(path, "/series/fleet/min_separation", "Scalars:scalars")
    pos = rec.truth[:, :, :2]
    gaps = [np.linalg.norm(pos[:, a] - pos[:, b], axis=1) for a, b in ((0, 1), (0, 2), (1, 2))]
    np.testing.assert_allclose([row[0] for row in closest], np.min(gaps, axis=0), rtol=1e-12)
    _, stale = _temporal_rows(path, "/series/fleet/stale_plans", "Scalars:scalars")
    assert {row[0] for row in stale} == {0.0}


@pytest.mark.parametrize(
    ("url", "kind"),
    [("memory:", MemorySink), ("rrd:/tmp/x.rrd", RerunSink), ("spawn:", RerunSink)],
)
def test_a_sink_is_chosen_by_url(url, kind) -> None:
    assert isinstance(open_sink(url), kind)


@pytest.mark.parametrize("url", ["rrd:", "file.rrd", "http://127.0.0.1:9876", ""])
def test_a_bad_sink_url_names_the_field(url) -> None:
    with pytest.raises(ConfigError) as info:
        open_sink(url)
    assert info.value.field == "telemetry"


def test_a_viewer_already_listening_is_used_as_it_is() -> None:
    """`spawn_viewer` starts nothing when a viewer (here a bare socket) holds the port."""
    import socket

    from fleetmpc.gcs.viewer import spawn_viewer

    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        assert spawn_viewer(port=port) == f"rerun+http://127.0.0.1:{port}/proxy"


def test_report_works_on_both_recordings(recordings, tmp_path) -> None:
    from fleetmpc.cli import main

    _, _, sim_rrd, live_rrd = recordings
    for name, rrd in (("sim", sim_rrd), ("live", live_rrd)):
        out = tmp_path / name
        assert main(["report", str(rrd), "--out", str(out)]) == 0
        assert (out / "fig1_paths.png").is_file() and (out / "metrics.json").is_file()
