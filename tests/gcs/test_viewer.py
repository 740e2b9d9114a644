"""What a user sees of a recording: the map and every time series of its blueprint drawn.

Each test serves a recording with Rerun's web viewer on loopback, opens it in headless
Chromium, waits until the page has loaded and stopped changing, finds the views of the
recording's own blueprint on a screenshot and says which drew data (`viewer` explains how).
The recordings: a lockstep `fleetmpc sim` run, a live `fleetmpc up` fleet at x4 (both of the
paper scenario, 20 s), and the live one with the map's and one series' entities dropped, which
must show exactly those views empty: the check sees an empty view as empty. And fifty vehicles
(`scenarios/scale/grid50.toml`, 20 s in lockstep), whose redraw after clicks on the time slider
is timed and printed (`viewer.Redraw`; the figures of `tools/viewer_bench.py`): the test asserts
only that each click is redrawn and the view still draws its data after, not how fast.

Screenshots of every page checked are kept in the test's tmp_path (under /tmp); a failure
names the file. Needs Chromium (Debian: `apt-get install chromium`); skipped without it.
"""

import contextlib
import os
import signal
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import rerun as rr
from helpers import ROOT, ProcessGroup, live_processes_naming, scenario_on_free_ports
from viewer import (
    CHROMIUM,
    FRAME_PROBE,
    Container,
    Ink,
    View,
    open_viewer,
    panel_ink,
    recorded_blueprint,
    rerun_binary,
    rerun_home,
    scrub_points,
)

pytestmark = [
    pytest.mark.viewer,
    pytest.mark.skipif(
        CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)"
    ),
]

PAPER = ROOT / "scenarios" / "paper.toml"
GRID50 = ROOT / "scenarios" / "scale" / "grid50.toml"
SCRUBS = 3
"""Clicks on the time slider timed in the fifty-vehicle recording."""
DURATION_S = 20.0
SPEED = 4.0
CHECKED = ("2D", "TimeSeries")
"""View classes whose data the tests look for: the map and the time series."""
DROPPED_SERIES = "series/centre_distance"
"""The series the negative case leaves out (with every `map/...` entity)."""


@pytest.fixture(scope="module")
def home(tmp_path_factory) -> dict[str, str]:
    """HOME (and the XDG folders) for the viewer, with Rerun's usage analytics off."""
    return rerun_home(tmp_path_factory.mktemp("viewer-home"))


def _sim(scenario: Path, rrd: Path, *, jobs: int = 1, timeout_s: float) -> Path:
    """`scenario` flown `DURATION_S` in lockstep (agents in `jobs` processes) into `rrd`."""
    argv = [sys.executable, "-m", "fleetmpc.cli", "sim", str(scenario), "--rrd", str(rrd)]
    argv += ["--quiet", "--duration", f"{DURATION_S:g}", "--jobs", str(jobs)]
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
    assert done.returncode == 0, done.stdout + done.stderr
    return rrd


@pytest.fixture(scope="module")
def sim_rrd(tmp_path_factory) -> Path:
    """The paper scenario, lockstep."""
    return _sim(PAPER, tmp_path_factory.mktemp("sim") / "sim.rrd", timeout_s=120)


@pytest.fixture(scope="module")
def grid50_rrd(tmp_path_factory) -> Path:
    """Fifty vehicles, lockstep."""
    return _sim(GRID50, tmp_path_factory.mktemp("grid50") / "grid50.rrd", jobs=2, timeout_s=300)


@pytest.fixture(scope="module")
def live_rrd(tmp_path_factory) -> Path:
    """The paper fleet as processes (`fleetmpc up` on free loopback ports), its recording."""
    tmp = tmp_path_factory.mktemp("live")
    scenario = scenario_on_free_ports(PAPER, tmp / "paper-viewer.toml")
    run_dir = tmp / "run"
    group = ProcessGroup(tmp / "logs")
    try:
        up = group.fleetmpc(
            "fleet", "up", str(scenario), "--run-dir", str(run_dir), "--speed", f"{SPEED:g}",
            "--duration", f"{DURATION_S:g}", "--viewer", "none", "--quiet",
        )  # fmt: skip
        try:
            rc = up.proc.wait(timeout=150)
        except subprocess.TimeoutExpired:
            rc = None
        assert rc == 0, f"fleetmpc up: exit {rc}\n{up.tail()}"
    finally:
        group.stop_all()
        for pid, _ in live_processes_naming(str(scenario)):  # its fleet, should `up` have died
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    return run_dir / "run.rrd"


def _checked_views(blueprint: Container) -> list[View]:
    return [v for v in blueprint.views() if v.kind in CHECKED]


@dataclass
class Seen:
    """What the viewer showed of a recording: the screenshot's file, each checked view's Ink."""

    shot: Path
    inks: dict[View, Ink]

    def empty(self) -> list[str]:
        """Titles of the checked views that drew no data, in the blueprint's order."""
        return [view.name for view, ink in self.inks.items() if not ink.drawn]

    def __str__(self) -> str:
        rows = "\n".join(f"  {view.name:34} {ink}" for view, ink in self.inks.items())
        return f"{self.shot}:\n{rows}"


def look(rrd: Path, workdir: Path, env: dict[str, str], name: str) -> Seen:
    """Open `rrd` in the viewer, wait until it settles, keep the screenshot as `name`.png;
    nothing the viewer needed may be left running, and nothing off this machine answered."""
    blueprint = recorded_blueprint(rrd)
    kinds = [view.kind for view in _checked_views(blueprint)]
    assert kinds.count("2D") == 1 and "TimeSeries" in kinds, f"{rrd}: a blueprint of {kinds}"
    with open_viewer(rrd, workdir, env) as viewer:
        seen = _settled(viewer, blueprint, name)
        answered = viewer.off_loopback(answered=True)
    _left_clean(answered, workdir)
    print(seen)
    return seen


def _settled(viewer, blueprint: Container, name: str, *, timeout_s: float = 90.0) -> Seen:
    """Wait until the viewer settles, keep the screenshot as `name`.png: what each checked
    view drew."""
    image, views = viewer.settle(blueprint, timeout_s=timeout_s)
    shot = viewer.save(image, name)
    return Seen(shot, {view: panel_ink(image, views[view]) for view in _checked_views(blueprint)})


def _left_clean(answered: list, workdir: Path) -> None:
    """Nothing off this machine answered the page, and nothing the viewer needed is running."""
    assert answered == [], f"the page got answers from off this machine: {answered}"
    left = live_processes_naming(str(workdir))
    assert left == [], f"processes left running: {left}"


def test_a_sim_recording_draws_the_map_and_every_time_series(sim_rrd, home, tmp_path):
    seen = look(sim_rrd, tmp_path, home, "sim")
    assert seen.empty() == [], f"empty views in {seen}"


def test_a_live_recording_draws_the_map_and_every_time_series(live_rrd, home, tmp_path):
    seen = look(live_rrd, tmp_path, home, "live")
    assert seen.empty() == [], f"empty views in {seen}"


def test_views_whose_data_is_missing_are_seen_empty(live_rrd, home, tmp_path):
    entities = {chunk.entity_path.strip("/") for chunk in rr.chunk.RrdReader(live_rrd).stream()}
    dropped = sorted(e for e in entities if e.startswith("map/") or e == DROPPED_SERIES)
    assert DROPPED_SERIES in dropped and len(dropped) > 1, sorted(entities)
    rrd = tmp_path / "without-map-and-c.rrd"
    argv = [str(rerun_binary()), "rrd", "filter", str(live_rrd), "-o", str(rrd)]
    for entity in dropped:
        argv += ["--drop-entity", f"/{entity}"]
    done = subprocess.run(
        argv, env={**os.environ, **home}, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    blueprint = recorded_blueprint(rrd)
    expected = [v.name for v in _checked_views(blueprint) if v.origin in ("map", DROPPED_SERIES)]
    assert len(expected) == 2, expected

    seen = look(rrd, tmp_path, home, "without-map-and-c")
    assert seen.empty() == expected, f"{expected} should be the empty views in {seen}"


def test_fifty_vehicles_are_drawn_and_redrawn_after_clicks_on_the_time_slider(
    grid50_rrd, home, tmp_path
):
    blueprint = recorded_blueprint(grid50_rrd)
    with open_viewer(grid50_rrd, tmp_path, home, on_new_document=FRAME_PROBE) as viewer:
        before = _settled(viewer, blueprint, "grid50", timeout_s=300.0)
        viewer.redraw_after(lambda: viewer.press(" ", "Space", 32, " "))  # pause the playback
        redraws = [
            viewer.redraw_after(lambda x=x, y=y: viewer.click(x, y))
            for x, y in scrub_points(SCRUBS)
        ]
        after = _settled(viewer, blueprint, "grid50-scrubbed", timeout_s=300.0)
        answered = viewer.off_loopback(answered=True)
    _left_clean(answered, tmp_path)
    print(
        f"fifty vehicles, redraw after a click on the time slider: {', '.join(map(str, redraws))}"
    )
    print(before, after, sep="\n")
    assert before.empty() == [] and after.empty() == [], f"empty views in {before} or {after}"
    assert all(r.drawn > 0 for r in redraws), f"a click the viewer did not redraw: {redraws}"
