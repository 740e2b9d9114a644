"""`fleetmpc up` of a ten-vehicle fleet: every control period recorded, the formation held.

The fleet of ``data/grid10.toml`` (ten SITLs and ten agents beside the router, the target and the
ground station: 23 processes on one host) flies its 50 s at x4 and at x1, from a copy of the
scenario on free ports. The ground station must record every period of the run, and the run must
pass the gates: safety (no two vehicles closer than d_safe) and periods, which `up` applies
itself, and the formation gates of a composed fleet's ground station (every separation error and
the centre-distance error within `GATE_FORMATION_M` over the last 10 s), applied here to its
metrics with the ground station's own `gate_failures`, with the suite's bound on the formation
RMS.

The ground station judges the flight by the SITL's ground truth (docs/design.md, "Ground
truth"), as the lockstep simulation does. At x4 the fleet needs several times the CPU it needs
at x1, and twenty-five vehicles at x1 about as much: recording every period, keeping d_safe and
the formation gates are asserted on any host. Only at twenty-five is one thing left to a host
with the cores for it: no autopilot leaving OFFBOARD (an agent starved long enough that its
setpoint stream stalls); on a smaller one that is reported as an expected failure that names
it (`_quality`).

Whatever the outcome nothing is left running: `up` is stopped by PID (it stops its fleet in
order), then any process whose command line names the scenario copy, or the router's port (its
command line does not name the scenario), is killed.
"""

import contextlib
import json
import os
import signal
from pathlib import Path

import pytest
from helpers import Child, live_processes_naming, scenario_on_free_ports

from fleetmpc.gcs.station import gate_failures
from fleetmpc.launch.compose import ComposeOptions
from fleetmpc.lockstep.suite import SLOT_RMS_MAX_M
from fleetmpc.scenario import Scenario, load_scenario

GRID10 = Path(__file__).resolve().parent / "data" / "grid10.toml"
GRID25 = Path(__file__).resolve().parent / "data" / "grid25.toml"
GATE_FORMATION_M = ComposeOptions.gate_formation_m
"""The formation gate of a composed fleet's ground station [m]."""
ENGAGE_TIMEOUT_S = 60.0
"""Wall seconds `up` gives each of the ten agents to engage (its default)."""
MARGIN_S = 90.0
"""Wall seconds allowed beyond engagement and the flight, for start-up and shutdown."""


def _fleet_processes(copy: Path, scenario: Scenario) -> list[tuple[int, str]]:
    """The live processes of the fleet flown from `copy`: those naming it, and its router."""
    net = scenario.network
    router = f"zenoh-router --host {net.host} --port {net.zenoh_port}"
    return live_processes_naming(str(copy)) + live_processes_naming(router)


def _verdict(up: Child, run_dir: Path) -> str:
    """What `up` said about the run's end, and each autopilot that left OFFBOARD (from its agent's
    log), for a failure message."""
    keep = ("gate", "FAILED", "exit codes", "interrupted")
    lines = [line for line in (up.out() + up.err()).splitlines() if any(k in line for k in keep)]
    for log in sorted((run_dir / "logs").glob("agent-*.log")):
        lost = [line for line in log.read_text().splitlines() if "Offboard lost" in line]
        lines += [f"{log.stem}: {line}" for line in lost]
    return "\n".join(lines) or up.tail()


@pytest.fixture
def fleet(tmp_path, processes):
    """Start ``fleetmpc up`` of a free-ports copy of grid10 at a speed; returns (child, copy,
    its scenario). At teardown `up` gets SIGTERM, then anything left of the fleet is killed."""
    started: list[tuple[Path, Scenario]] = []

    def start(speed: float, source: Path = GRID10) -> tuple[Child, Path, Scenario]:
        copy = scenario_on_free_ports(source, tmp_path / f"{source.stem}-up.toml")
        scenario = load_scenario(copy)
        started.append((copy, scenario))
        up = processes.fleetmpc(
            "up",
            "up", str(copy),
            "--speed", f"{speed:g}", "--viewer", "none", "--quiet",
            "--engage-timeout", f"{ENGAGE_TIMEOUT_S:g}", "--run-dir", str(tmp_path / "run"),
        )  # fmt: skip
        return up, copy, scenario

    yield start
    processes.stop_all(timeout_s=20.0)
    for copy, scenario in started:
        for pid, _ in _fleet_processes(copy, scenario):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def _quality(failures: list[str], cores_needed: int) -> None:
    """Assert `failures` empty; on a host of fewer than `cores_needed` cores, a miss is an
    expected failure instead (the test still ran every other assertion before)."""
    cores = os.cpu_count() or 1
    if failures and cores < cores_needed:
        pytest.xfail(f"on {cores} cores (of {cores_needed} needed): {'; '.join(failures[:3])}")
    assert failures == []


@pytest.mark.slow
@pytest.mark.parametrize("speed", [4.0, 1.0], ids=["x4", "x1"])
def test_up_records_every_period_of_ten_vehicles_within_the_gates(fleet, tmp_path, speed):
    up, copy, scenario = fleet(speed)
    rc = up.proc.wait(timeout=ENGAGE_TIMEOUT_S + scenario.duration_s / speed + MARGIN_S)
    leftover = _fleet_processes(copy, scenario)
    run_dir = tmp_path / "run"
    assert rc == 0, _verdict(up, run_dir)
    assert leftover == [], leftover
    m = json.loads((run_dir / "metrics.json").read_text())
    expected = round(scenario.duration_s / scenario.controller.period_s) + 1
    assert m["source"] == "live", m
    assert m["periods_recorded"] == m["periods_expected"] == expected, m
    assert m["min_separation_m"] >= scenario.controller.d_safe_m, m
    assert len(m["separation_error_m"]) == 45, m["separation_pairs"]  # every pair of the ten
    assert m["ground_truth"] == list(scenario.vehicle_ids), m["ground_truth"]
    assert gate_failures(m, scenario, formation_m=GATE_FORMATION_M) == []
    assert m["formation_rms_m"] <= SLOT_RMS_MAX_M, m["formation_rms_m"]


LIVE_25_CORES = 4
"""Cores twenty-five live vehicles need for no autopilot to leave OFFBOARD every time. On two,
their steps come late in a third of the periods and the worst setpoint gap p99 reached 95 ms of
the 100 ms allowed, though no autopilot left offboard in the last eight runs; before the fleet
woke less (docs/design.md, "Waking"), an agent's setpoints stalled now and then and its
autopilot left offboard."""


@pytest.mark.slow
def test_up_flies_twenty_five_vehicles_recording_every_period_and_keeping_d_safe(fleet, tmp_path):
    """Twenty-five vehicles at x1 (29 processes): every period recorded, d_safe kept, the
    formation gates held; on a host with the cores for it, no vehicle out of offboard."""
    up, copy, scenario = fleet(1.0, GRID25)
    rc = up.proc.wait(timeout=ENGAGE_TIMEOUT_S + scenario.duration_s + MARGIN_S)
    run_dir = tmp_path / "run"
    assert rc == 0, _verdict(up, run_dir)
    assert _fleet_processes(copy, scenario) == []
    m = json.loads((run_dir / "metrics.json").read_text())
    expected = round(scenario.duration_s / scenario.controller.period_s) + 1
    assert m["periods_recorded"] == m["periods_expected"] == expected, m
    assert m["min_separation_m"] >= scenario.controller.d_safe_m, m
    assert m["ground_truth"] == list(scenario.vehicle_ids), m["ground_truth"]
    assert gate_failures(m, scenario, formation_m=GATE_FORMATION_M) == []
    failures = []
    for log in sorted((run_dir / "logs").glob("agent-*.log")):
        summary = json.loads(log.read_text().splitlines()[-1])
        if summary["mode_lost"]:
            failures.append(f"{log.stem}: its autopilot left offboard")
    _quality(failures, LIVE_25_CORES)
