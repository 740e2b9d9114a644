"""The whole fleet over real loopback MAVLink and Zenoh, against the lockstep run.

Processes: a Zenoh router, three SITLs (PX4 profile, x4), the target and three agents (Zenoh
clients of the router), all on fleet time from one epoch a few seconds ahead, so everything is
up and engaged when the target starts. A ground-station listener takes GLOBAL_POSITION_INT of
every SITL and stamps it in fleet time. Mid-run, malformed payloads are published on a plan key;
at the end agent 3 is SIGKILLed. Every process is killed by PID in a finalizer, also on failure.
"""

import dataclasses
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
import zenoh

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from gcs.lockstep import run_lockstep  # noqa: E402
from gcs.metrics import compute_metrics  # noqa: E402
from onboard.core.formation import Formation  # noqa: E402
from protocol.keys import plan_key  # noqa: E402
from protocol.mavlink_map import Autopilot, FlightMode, mode_from_custom, ned_from_geodetic  # noqa: E402
from protocol.zenoh_config import ZenohOptions  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = ROOT / "scenarios" / "paper.toml"
SPEED = 4.0
FLEET = "e2e"
WINDOW_S = (20.0, 30.0)
KILL_AT_S = 30.5
END_S = 35.0
SITL_LEAD_S = 2.0


def _free_port(kind: int) -> int:
    with closing(socket.socket(socket.AF_INET, kind)) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Processes:
    """Children started by this test; stopped by PID, SIGKILL if they do not stop in time."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, *args: str) -> subprocess.Popen:
        out = open(self.log_dir / f"{name}.out", "w")  # noqa: SIM115
        err = open(self.log_dir / f"{name}.err", "w")  # noqa: SIM115
        proc = subprocess.Popen(
            [sys.executable, "-m", "gcs.cli", *args], stdout=out, stderr=err, cwd=ROOT
        )
        self.procs[name] = proc
        return proc

    def stop(self, name: str, *, timeout_s: float = 5.0) -> int | None:
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5.0)
                return None
        return proc.returncode

    def stop_all(self) -> None:
        for name in reversed(list(self.procs)):
            self.stop(name)

    def text(self, name: str, stream: str = "out") -> str:
        return (self.log_dir / f"{name}.{stream}").read_text()

    def wait_for(self, name: str, text: str, *, timeout_s: float = 15.0) -> None:
        deadline = time.monotonic() + timeout_s
        while text not in self.text(name):
            assert self.procs[name].poll() is None, self.text(name, "err")
            assert time.monotonic() < deadline, f"{name} did not print {text!r}"
            time.sleep(0.05)


def _fleet_s(epoch_ns: int) -> float:
    return (time.time_ns() - epoch_ns) * SPEED * 1e-9


@pytest.fixture
def processes(tmp_path):
    procs = Processes(tmp_path)
    try:
        yield procs
    finally:
        procs.stop_all()
        for proc in procs.procs.values():
            if proc.poll() is None:  # last resort, by PID
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5.0)


def _lockstep_metrics(paper, starts: dict[int, list[float]] | None = None) -> dict:
    """Lockstep metrics from the scenario's start, or from the given (x, y, yaw) per vehicle."""
    if starts is not None:
        vehicles = tuple(
            dataclasses.replace(v, initial=tuple(starts[v.id])) for v in paper.vehicles
        )
        paper = dataclasses.replace(paper, vehicles=vehicles)
    m = compute_metrics(run_lockstep(paper, duration_s=WINDOW_S[1]))
    return {k: m[k] for k in ("separation_error_m", "centre_distance_error_m", "min_separation_m")}


def _formation_metrics(paper, tracks: dict[int, np.ndarray]) -> dict:
    """compute_metrics' formation numbers from GCS tracks (t_s, north, east) on a 0.2 s grid."""
    t = np.arange(WINDOW_S[0], WINDOW_S[1] + 1e-9, 0.2)
    ids = paper.vehicle_ids
    pos = np.stack(
        [
            np.stack([np.interp(t, tracks[i][:, 0], tracks[i][:, k]) for k in (1, 2)], axis=1)
            for i in ids
        ],
        axis=1,
    )  # (T, n, 2)
    formation = Formation(paper.formation)
    desired = formation.desired_distances()
    sep = {}
    for a in range(len(ids)):
        for b in range(a + 1, len(ids)):
            d = np.linalg.norm(pos[:, a] - pos[:, b], axis=1)
            sep[f"{ids[a]}-{ids[b]}"] = float(np.mean(np.abs(d - desired[a, b])))
    centre_err = []
    for k, t_s in enumerate(t):
        tgt, vel = paper.target.state_at(float(t_s))
        slots = formation.slots(tgt[None, :], vel)[0]
        course = formation.course(vel)
        centre = tgt - paper.formation.trail_m * np.array([math.cos(course), math.sin(course)])
        offsets = slots - centre[None, :]
        est_centre = np.mean(pos[k] - offsets, axis=0)
        centre_err.append(abs(np.linalg.norm(est_centre - tgt) - paper.formation.trail_m))
    return {"separation_error_m": sep, "centre_distance_error_m": float(np.mean(centre_err))}


@pytest.mark.slow
def test_fleet_flies_the_formation_over_mavlink_and_zenoh(paper, processes, tmp_path) -> None:
    router_port = _free_port(socket.SOCK_STREAM)
    gcs_port = _free_port(socket.SOCK_DGRAM)
    offboard = {v.id: _free_port(socket.SOCK_DGRAM) for v in paper.vehicles}
    epoch_ns = time.time_ns() + 4_000_000_000
    common = ["--scenario", str(SCENARIO)]
    timing = ["--epoch-ns", str(epoch_ns), "--speed", str(SPEED)]
    zenoh_args = ["--zenoh-connect", f"127.0.0.1:{router_port}", "--fleet", FLEET]
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs_port}", source_system=254)
    session = None
    try:
        processes.start("router", "zenoh-router", "--port", str(router_port))
        processes.wait_for("router", "listening")
        processes.start("target", "target", *common, *zenoh_args, *timing)
        for v in paper.vehicles:
            processes.start(
                f"agent{v.id}",
                "agent",
                *common,
                "--vehicle",
                str(v.id),
                "--mavlink",
                f"udpin:127.0.0.1:{offboard[v.id]}",
                *zenoh_args,
                *timing,
                "--record",
                str(tmp_path / f"agent{v.id}.jsonl"),
            )
        # The SITLs start last, just before the epoch: the truth plant drifts with the wind even
        # while disarmed or in HOLD, so every second before the epoch moves the start point.
        time.sleep(max(0.0, (epoch_ns - time.time_ns()) * 1e-9 - SITL_LEAD_S))
        for v in paper.vehicles:
            processes.start(
                f"sitl{v.id}",
                "sitl",
                *common,
                "--vehicle",
                str(v.id),
                "--speed",
                str(SPEED),
                "--offboard-port",
                str(offboard[v.id]),
                "--offboard-local-port",
                "0",
                "--gcs-port",
                str(gcs_port),
                "--gcs-local-port",
                "0",
            )
        conf = ZenohOptions(mode="client", connect=(f"tcp/127.0.0.1:{router_port}",)).to_config()
        session = zenoh.open(conf)
        tracks: dict[int, list] = defaultdict(list)
        modes_after_kill: dict[int, set] = defaultdict(set)
        garbage_sent = killed = False
        while (fleet_s := _fleet_s(epoch_ns)) < END_S:
            msg = gcs.recv_match(blocking=True, timeout=0.1)
            if not garbage_sent and fleet_s > 10.0:
                garbage_sent = True
                for payload in (b"\x00" * 7, b"FM" + os.urandom(300), os.urandom(266)):
                    session.put(plan_key(FLEET, 2), payload)
            if not killed and fleet_s > KILL_AT_S:
                killed = True
                os.kill(processes.procs["agent3"].pid, signal.SIGKILL)
            if msg is None:
                continue
            src = msg.get_srcSystem()
            if msg.get_type() == "GLOBAL_POSITION_INT":
                north, east = ned_from_geodetic(
                    msg.lat * 1e-7,
                    msg.lon * 1e-7,
                    home_lat_deg=paper.site.home_lat_deg,
                    home_lon_deg=paper.site.home_lon_deg,
                )
                tracks[src].append((fleet_s, north, east))
            elif msg.get_type() == "HEARTBEAT" and killed and msg.get_srcComponent() == 1:
                modes_after_kill[src].add(mode_from_custom(msg.custom_mode, Autopilot.PX4))
        summaries = {}
        for v in (1, 2):
            assert processes.stop(f"agent{v}") == 0, processes.text(f"agent{v}", "err")
            summaries[v] = json.loads(processes.text(f"agent{v}").strip().splitlines()[-1])
        for name in ("target", "sitl1", "sitl2", "sitl3", "router"):
            assert processes.stop(name) == 0, processes.text(name, "err")
    finally:
        if session is not None:
            session.close()
        gcs.close()

    arrays = {i: np.array(tracks[i]) for i in paper.vehicle_ids}
    live = _formation_metrics(paper, arrays)
    starts = {}
    for v in paper.vehicle_ids:
        first = json.loads((tmp_path / f"agent{v}.jsonl").read_text().splitlines()[0])
        starts[v] = first["pose"]
    ref = _lockstep_metrics(paper)
    ref_same_start = _lockstep_metrics(paper, starts)
    all_t = np.unique(np.concatenate([a[:, 0] for a in arrays.values()]))
    grid = all_t[(all_t > 0.0) & (all_t < KILL_AT_S)]
    pos = np.stack(
        [[np.interp(grid, arrays[i][:, 0], arrays[i][:, k]) for k in (1, 2)] for i in arrays],
        axis=0,
    )  # (n, 2, T)
    min_sep = min(
        float(np.min(np.linalg.norm(pos[a] - pos[b], axis=0)))
        for a in range(3)
        for b in range(a + 1, 3)
    )
    report = {
        "live": {**live, "min_separation_m": min_sep},
        "lockstep": ref,
        "lockstep_from_live_start": ref_same_start,
        "live_start": starts,
        "agents": summaries,
    }
    (tmp_path / "report.json").write_text(json.dumps(report, indent=1, default=str))
    print(json.dumps(report, default=str))

    # Every vehicle was engaged and stepping from fleet time 0 (else the comparison is void).
    for v in paper.vehicle_ids:
        first = json.loads((tmp_path / f"agent{v}.jsonl").read_text().splitlines()[0])
        assert first["stamp_ns"] == 0 and first["mode"] == "OFFBOARD", (v, first)
    # Formation: as good as the lockstep run, in absolute terms.
    assert all(e <= 0.1 for e in live["separation_error_m"].values()), report
    assert live["centre_distance_error_m"] <= 0.1, report
    assert min_sep >= paper.controller.d_safe_m, report
    # Malformed payloads were rejected and counted while the agents kept flying.
    for v in (1, 2):
        assert sum(summaries[v]["bus"]["rejected"].values()) >= 3, summaries[v]
    assert all(s["step_errors"] == 0 and s["overruns"] <= 2 for s in summaries.values())
    # SIGKILLed agent 3: its SITL failed safe to HOLD, the others saw its plan go stale.
    assert FlightMode.HOLD in modes_after_kill[3], modes_after_kill
    assert modes_after_kill[1] == {FlightMode.OFFBOARD}
    rows = [json.loads(line) for line in (tmp_path / "agent1.jsonl").read_text().splitlines()]
    last = rows[-1]
    assert last["neighbour_ages_s"]["2"] <= 0.5
    assert last["neighbour_ages_s"]["3"] >= 2.0
    assert last["neighbour_ages_s"]["3"] >= (END_S - KILL_AT_S) - 1.0
    # The stream to the autopilot never came close to PX4's 2 Hz floor.
    for s in summaries.values():
        assert s["setpoint_gap_wall_ms"]["max"] * SPEED < 500.0
