"""`fleetmpc up` following a recorded track live: the target process replays the walk with its
5 s dropout (scenarios/tracks/walk-dropout.toml) to three agents on our SITL, and the ground
station's recording meets the dropout's gates."""

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from helpers import fly_up, live_processes_naming, scenario_on_free_ports

from fleetmpc.gcs.rrd_reader import read_recording

ROOT = Path(__file__).resolve().parents[2]


def _event_texts(rrd: Path) -> list[str]:
    """Every event's text in a recording, in the order logged."""
    texts = []
    for chunk in rr.chunk.RrdReader(rrd).stream():
        if chunk.entity_path == "/events":
            batch = chunk.to_record_batch()
            for name in batch.schema.names:
                if name.endswith("TextLog:text"):
                    texts += [row[0] for row in batch.column(name).to_pylist() if row]
    return texts


@pytest.mark.slow
def test_up_follows_a_replayed_track_through_its_dropout(tmp_path):
    tracks = ROOT / "scenarios" / "tracks"
    scenario = scenario_on_free_ports(tracks / "walk-dropout.toml", tmp_path / "w.toml")
    shutil.copy(tracks / "walk-dropout.csv", tmp_path)
    run_dir = tmp_path / "run"
    done = fly_up(scenario, run_dir, speed=4, timeout_s=300, cwd=ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    assert live_processes_naming(str(scenario)) == []
    log = (run_dir / "logs" / "target.log").read_text()
    assert f"following track:{tmp_path / 'walk-dropout.csv'}" in log, log
    # The fixes up to the fleet's end, 106 s: 505 of the 526, or one fewer where the last one
    # falls after the fleet stopped the target (the count is the target process's, in wall time).
    counts = [(int(a), int(r)) for a, r in re.findall(r"(\d+) accepted, (\d+) rejected", log)]
    assert counts and all(rejected == 0 for _, rejected in counts), log
    assert 500 <= counts[-1][0] <= 505, log
    record = read_recording(run_dir / "run.rrd").record
    err = np.linalg.norm(record.truth[:, :, :2] - record.slots, axis=2)
    t = record.t_s
    assert record.min_separation_m >= 2.0
    assert err[(t >= 64.8) & (t <= 70.0)].max() < 1.0  # (measured: 0.51 m)
    back = (t >= 80.0) & (t <= 82.0)  # (10 s after the fixes resume at 70 s)
    assert np.sqrt(np.mean(err[back] ** 2)) < 0.2  # (measured: 0.13 m)
    # The recording shows each vehicle lose the target, get it back and track it again.
    events = _event_texts(run_dir / "run.rrd")
    for vid in (1, 2, 3):
        for state in ("predicting", "reacquiring", "tracking"):
            assert f"UAV {vid}: target {state}" in events, events
