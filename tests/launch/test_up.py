"""`fleetmpc up`: the whole fleet as OS processes, its gates, its recording and its shutdown.

Each test flies the paper fleet from a copy of `scenarios/paper.toml` whose ``[network]`` ports
are free ones, so it never meets another fleet on this machine. "Nothing left running" is
checked by looking for any process whose command line names that copy (every process `up`
starts is given it), which also catches grandchildren.
"""

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from helpers import live_processes_naming, scenario_on_free_ports

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper.toml"
SPEED = 4.0
FIGURES = (
    "fig1_paths.png",
    "fig2_c.png",
    "fig3_separation.png",
    "fig4_centre_distance.png",
    "fig5_beta.png",
)


@pytest.fixture
def scenario(tmp_path) -> Path:
    """paper.toml with its own free ports, in tmp_path."""
    return scenario_on_free_ports(PAPER, tmp_path / "paper-up.toml")


class Up:
    """One `fleetmpc up` run in the background; killed (with its fleet) if a test fails."""

    def __init__(self, scenario: Path, run_dir: Path, *extra: str) -> None:
        self.scenario = scenario
        self.run_dir = run_dir
        self.out_path = run_dir.parent / f"{run_dir.name}.out"
        self.err_path = run_dir.parent / f"{run_dir.name}.err"
        argv = [
            sys.executable, "-m", "fleetmpc.cli", "up", str(scenario),
            "--speed", f"{SPEED:g}", "--viewer", "none", "--quiet", "--run-dir", str(run_dir),
            *extra,
        ]  # fmt: skip
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen(argv, stdout=out, stderr=err, cwd=ROOT)

    def wait(self, timeout_s: float) -> int:
        return self.proc.wait(timeout=timeout_s)

    def text(self) -> str:
        return self.out_path.read_text() + self.err_path.read_text()

    def wait_flying(self, *, fleet_s: float, timeout_s: float = 60.0) -> None:
        """Until the ground station's status file shows the fleet flying past `fleet_s`."""
        status = self.run_dir / "status.json"
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.text()
            try:
                snap = json.loads(status.read_text())
            except (OSError, ValueError):
                snap = {}
            if snap.get("phase") == "flying" and (snap.get("fleet_s") or 0.0) >= fleet_s:
                return
            time.sleep(0.1)
        raise AssertionError(f"fleet not flying past {fleet_s} s:\n{self.text()}")

    def kill_all(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10.0)
        for pid, _ in live_processes_naming(str(self.scenario)):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


@pytest.fixture
def launch():
    runs: list[Up] = []

    def start(scenario: Path, run_dir: Path, *extra: str) -> Up:
        up = Up(scenario, run_dir, *extra)
        runs.append(up)
        return up

    yield start
    for up in runs:
        up.kill_all()


def _rrd_entities(path: Path) -> set[str]:
    return {chunk.entity_path for chunk in rr.chunk.RrdReader(path).stream()}


def _rrd_events(path: Path) -> list[tuple[str, str]]:
    """(level, text) of every event in a recording."""
    out = []
    for chunk in rr.chunk.RrdReader(path).stream():
        if chunk.entity_path == "/events" and not chunk.is_static:
            batch = chunk.to_record_batch()
            levels = batch.column(batch.schema.names.index("TextLog:level")).to_pylist()
            texts = batch.column(batch.schema.names.index("TextLog:text")).to_pylist()
            out += [(level[0], text[0]) for level, text in zip(levels, texts, strict=True)]
    return out


def test_up_flies_the_paper_fleet_within_the_gates(scenario, launch, tmp_path):
    run_dir, rrd, metrics = tmp_path / "run", tmp_path / "run.rrd", tmp_path / "metrics.json"
    up = launch(scenario, run_dir, "--duration", "30", "--rrd", str(rrd), "--metrics", str(metrics))
    rc = up.wait(timeout_s=180.0)
    leftover = live_processes_naming(str(scenario))
    assert rc == 0, up.text()
    assert leftover == [], leftover
    m = json.loads(metrics.read_text())
    assert m["source"] == "live" and m["periods_recorded"] == m["periods_expected"] == 151, m
    assert all(e <= 0.1 for e in m["separation_error_m"]), m["separation_error_m"]
    assert m["centre_distance_error_m"] <= 0.1, m
    assert m["min_separation_m"] >= 2.0, m
    assert "separation error 1-2" in up.text()  # the summary table of `fleetmpc sim`
    assert re.search(r"periods recorded +151 of 151", up.text())
    for name in ("zenoh-router", "target", "sitl-1", "agent-3", "gcs"):
        assert (run_dir / "logs" / f"{name}.log").is_file(), name

    # The recording holds every entity family the ground station logs.
    entities = _rrd_entities(rrd)
    expected = {"/map/target", "/map/target_prediction", "/map/formation_links"}
    expected |= {"/map/target_observations", "/map/target_estimate"}
    expected |= {"/series/centre_distance", "/events", "/flight_record", "/meta"}
    expected |= {"/map/vehicles", "/map/trails", "/map/slots", "/map/plans"}
    for family in ("separation", "formation_error", "c_norm", "solve_time_ms"):
        expected.add(f"/series/{family}")
    expected |= {"/series/setpoint_rate", "/series/plan_age"}
    expected |= {"/series/beta/effectiveness", "/series/beta/drift_m_s"}
    assert expected <= entities, sorted(expected - entities)
    assert rr.chunk.RrdReader(rrd).blueprints(), "no blueprint in the recording"
    events = _rrd_events(rrd)
    assert any("run start" in text for _, text in events), events
    assert [e for e in events if e[0] != "INFO"] == [], events  # a clean run warns of nothing

    # `report` regenerates the figures and the metrics from the recording alone.
    out = tmp_path / "report"
    done = subprocess.run(
        [sys.executable, "-m", "fleetmpc.cli", "report", str(rrd), "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    for name in FIGURES:
        assert (out / name).stat().st_size > 1000, name
    again = json.loads((out / "metrics.json").read_text())
    for key in ("centre_distance_error_m", "formation_rms_m", "min_separation_m"):
        assert again[key] == pytest.approx(m[key], abs=1e-9), key
    assert again["separation_error_m"] == pytest.approx(m["separation_error_m"], abs=1e-9)


def test_sigint_brings_everything_down_and_keeps_the_recording(scenario, launch, tmp_path):
    rrd = tmp_path / "cut.rrd"
    up = launch(scenario, tmp_path / "cut", "--duration", "120", "--rrd", str(rrd))
    up.wait_flying(fleet_s=6.0)
    t0 = time.monotonic()
    up.proc.send_signal(signal.SIGINT)
    rc = up.wait(timeout_s=30.0)
    down_s = time.monotonic() - t0
    leftover = live_processes_naming(str(scenario))
    assert rc == 130, up.text()
    assert down_s <= 5.0, f"shutdown took {down_s:.1f} s"
    assert leftover == [], leftover
    assert "interrupted" in up.text()
    entities = _rrd_entities(rrd)  # readable, and it holds the flight so far
    assert {"/flight_record", "/map/vehicles", "/series/separation"} <= entities


def test_a_dead_sitl_is_named_and_up_fails(scenario, launch, tmp_path):
    up = launch(scenario, tmp_path / "dead", "--duration", "120")
    up.wait_flying(fleet_s=4.0)
    (victim,) = [
        pid
        for pid, cmd in live_processes_naming(str(scenario))
        if " sitl " in cmd and "--vehicle 2 " in cmd
    ]
    os.kill(victim, signal.SIGKILL)
    rc = up.wait(timeout_s=60.0)
    text = up.text()
    assert rc == 1, text
    assert "FAILED: sitl-2" in text, text
    assert live_processes_naming(str(scenario)) == []


@pytest.mark.slow  # (46 s of two cores: the longest live fleet of the default suite)
def test_up_flies_the_mixed_fleet_at_x1_within_the_gates(launch, tmp_path):
    """The ArduPilot-profile vehicle's takeoff takes 6.7 s of fleet time: at x1 it used to be
    still climbing, flying none of its setpoints, when the fleet epoch came (its agent learned an
    effectiveness of 0.5 from it, and it flew 1 m off its slot)."""
    mixed = scenario_on_free_ports(
        ROOT / "scenarios" / "mixed-autopilots.toml", tmp_path / "m.toml"
    )
    metrics = tmp_path / "metrics.json"
    up = launch(mixed, tmp_path / "run", "--speed", "1", "--metrics", str(metrics))
    assert up.wait(timeout_s=180.0) == 0, up.text()
    m = json.loads(metrics.read_text())
    assert all(e <= 0.1 for e in m["separation_error_m"]), m["separation_error_m"]
    assert m["centre_distance_error_m"] <= 0.1, m
    assert m["min_separation_m"] >= 2.0, m
    log = (tmp_path / "run" / "logs" / "agent-2.log").read_text()
    assert "vehicle 2: engaged" in log


def test_an_ardupilot_answering_as_system_1_and_booted_elsewhere_flies_vehicle_2(launch, tmp_path):
    """A stock ArduCopter answers as system 1 and reports local position from where it booted.
    Here an ArduPilot-profile vehicle started by hand (not by `up`) serves vehicle 2's slot as
    system 1, its local origin 12 m East of its start (it was carried there after boot). The
    agent flies the first autopilot it hears and places it from its global position; the ground
    station knows it as vehicle 2 from the scenario's `system_id`; both see it at the same place."""
    from fleetmpc.gcs.rrd_reader import read_recording
    from fleetmpc.network import mavlink_url
    from fleetmpc.scenario import load_scenario

    mixed = scenario_on_free_ports(
        ROOT / "scenarios" / "mixed-autopilots.toml", tmp_path / "m.toml"
    )
    text = mixed.read_text()
    text = text.replace("[[vehicles]]\nid = 1\n", "[[vehicles]]\nid = 1\nsystem_id = 11\n", 1)
    text = text.replace("[[vehicles]]\nid = 2\n", "[[vehicles]]\nid = 2\nsystem_id = 1\n", 1)
    mixed.write_text(text)
    sc = load_scenario(mixed)
    v2 = sc.vehicle(2)
    assert (v2.autopilot, v2.mavlink_system_id, sc.vehicle(1).mavlink_system_id) == (
        "ardupilot",
        1,
        11,
    )
    url = mavlink_url(sc.network, v2)
    origin = f"{v2.initial[0]:.3f},{v2.initial[1] + 12.0:.3f}"
    sitl_log = (tmp_path / "sitl-2.log").open("w")  # noqa: SIM115 (closed below)
    sitl = subprocess.Popen(
        [sys.executable, "-m", "fleetmpc.cli", "sitl", "--scenario", str(mixed), "--vehicle", "2",
         "--speed", f"{SPEED:g}", "--boot-origin", origin],
        stdout=sitl_log, stderr=subprocess.STDOUT, cwd=ROOT,
    )  # fmt: skip
    try:
        metrics = tmp_path / "metrics.json"
        up = launch(mixed, tmp_path / "run", "--mavlink", f"2={url}", "--metrics", str(metrics),
                    "--agent-records")  # fmt: skip
        assert up.wait(timeout_s=180.0) == 0, up.text()
    finally:
        sitl.terminate()
        sitl.wait(timeout=10.0)
        sitl_log.close()
    log = (tmp_path / "run" / "logs" / "agent-2.log").read_text()
    assert "vehicle 2: engaged" in log
    m = json.loads(metrics.read_text())
    assert all(e <= 0.1 for e in m["separation_error_m"]), m["separation_error_m"]
    assert m["centre_distance_error_m"] <= 0.1, m
    assert m["min_separation_m"] >= 2.0, m
    # The ground station's position of vehicle 2 against its agent's, at the times the agent's
    # poses were measured (fleet time = autopilot boot time + the agent's clock offset).
    rec = read_recording(tmp_path / "run" / "run.rrd").record
    rows = [
        json.loads(line)
        for line in (tmp_path / "run" / "agents" / "agent-2.jsonl").read_text().splitlines()
    ]
    t = np.array([(r["time_boot_ns"] + r["offset_ns"]) * 1e-9 for r in rows if r["offset_ns"]])
    agent = np.array([r["pose"][:2] for r in rows if r["offset_ns"]], dtype=float)
    inside = (t >= rec.t_s[0] + 1.0) & (t <= rec.t_s[-1])
    ground = np.stack(
        [np.interp(t[inside], rec.t_s, rec.truth[:, 1, axis]) for axis in (0, 1)], axis=1
    )
    offset = agent[inside] - ground
    assert inside.sum() >= 100
    # (each side reads its own noisy telemetry: 5 cm of sensor noise per sample.) Across the
    # vehicle's track the two agree to 2 cm on average: a wrong frame would put them 12 m apart.
    # Along it they differ by the vehicle's speed times the error of the agent's estimate of its
    # autopilot's clock, a few milliseconds, more on a loaded host: up to 6 cm (40 ms at 1.5 m/s).
    velocity = np.stack(
        [
            np.interp(t[inside], rec.t_s, np.gradient(rec.truth[:, 1, axis], rec.t_s))
            for axis in (0, 1)
        ],
        axis=1,
    )
    along = velocity / np.maximum(np.hypot(velocity[:, 0], velocity[:, 1]), 1e-9)[:, None]
    mean_along = float(np.mean(np.sum(offset * along, axis=1)))
    mean_across = float(np.mean(offset[:, 0] * -along[:, 1] + offset[:, 1] * along[:, 0]))
    assert abs(mean_across) <= 0.02, (mean_across, mean_along)
    assert abs(mean_along) <= 0.06, (mean_across, mean_along)
    assert np.median(np.hypot(offset[:, 0], offset[:, 1])) <= 0.1


def test_a_px4_sitl_instance_flies_vehicle_2_through_refusals_next_to_our_vehicles(
    launch, tmp_path
):
    """The issue's fleet: vehicle 2 on a PX4 SITL instance 1 (system id 2, binding PX4's
    14580 + 1 and 18570 + 1, moved here with the test's free network), which refuses arming
    while its heading settles (here for 40 s of its time, so that the agent, started later,
    sees it) and whose first takeoff ends disarmed on the ground (COM_DISARM_PRFLT, 10 s). A
    PX4-profile vehicle started by hand stands in for it. `up` starts vehicles 1 and 3 next to
    it, and vehicle 2's agent asks again, starts over after the failed takeoff, and engages."""
    from fleetmpc.network import PX4_GCS_LOCAL_BASE_PORT, PX4_OFFBOARD_LOCAL_BASE_PORT, Network
    from fleetmpc.scenario import load_scenario

    paper = scenario_on_free_ports(PAPER, tmp_path / "paper.toml")
    net = load_scenario(paper).network
    # Where PX4 instance 1 binds on this network (PX4's distances from the ports streamed to).
    offboard_bound = (
        net.offboard_port(2) + PX4_OFFBOARD_LOCAL_BASE_PORT - Network.offboard_base_port
    )
    gcs_bound = net.gcs_port + PX4_GCS_LOCAL_BASE_PORT - Network.gcs_port + 1
    px4_log = (tmp_path / "px4-instance-1.log").open("w")  # noqa: SIM115 (closed below)
    px4 = subprocess.Popen(
        [sys.executable, "-m", "fleetmpc.cli", "sitl", "--scenario", str(paper), "--vehicle", "2",
         "--speed", f"{SPEED:g}", "--offboard-local-port", str(offboard_bound),
         "--gcs-local-port", str(gcs_bound), "--heading-ready", "40", "--takeoff-stall", "45",
         "--com-disarm-prflt", "10"],
        stdout=px4_log, stderr=subprocess.STDOUT, cwd=ROOT,
    )  # fmt: skip
    try:
        metrics = tmp_path / "metrics.json"
        url = f"udpin:{net.host}:{net.offboard_port(2)}"
        up = launch(paper, tmp_path / "run", "--mavlink", f"2={url}", "--metrics", str(metrics))
        assert up.wait(timeout_s=180.0) == 0, up.text()
    finally:
        px4.terminate()
        px4.wait(timeout=10.0)
        px4_log.close()
    log = (tmp_path / "run" / "logs" / "agent-2.log").read_text()
    assert "engage: arm: TEMPORARILY_REJECTED (Preflight Fail: heading estimate not stable)" in log
    assert "(Disarmed by auto preflight disarming); trying again" in log
    assert "vehicle 2: engaged" in log
    m = json.loads(metrics.read_text())
    assert m["periods_recorded"] == m["periods_expected"], m
    assert m["min_separation_m"] >= 2.0, m
