"""`fleetmpc up --faults`: the live fleet through the process faults of faults/live/.

Each test flies the paper fleet (on free ports, at x4 unless it says) through one fault file
and checks what a live fleet must do through it: no process crashes, `up` ends well and says
what it injected, the separation holds, and the fleet is back in formation after the fault
(formation RMS of the last 10 s at most 1.5 times a fault-free run's; `BASELINE_RMS_M` is the
fault-free figure measured here, with margin for the run-to-run spread of a live fleet).
"""

import json
from pathlib import Path

import pytest
from helpers import live_processes_naming, scenario_on_free_ports
from test_up import Up

pytestmark = pytest.mark.slow  # (about two minutes of two cores: seven live fleets)

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "scenarios" / "paper.toml"
FAULTS = ROOT / "faults" / "live"
BASELINE_RMS_M = 0.08
"""A fault-free live paper run's formation RMS (0.06-0.07 m at x1 and x4), rounded up."""


@pytest.fixture
def fly(tmp_path):
    runs: list[Up] = []

    def run(name: str, *extra: str) -> tuple[Up, int, dict | None]:
        scenario = scenario_on_free_ports(PAPER, tmp_path / "paper-up.toml")
        run_dir = tmp_path / name
        up = Up(scenario, run_dir, "--faults", str(FAULTS / f"{name}.toml"), *extra)
        runs.append(up)
        rc = up.wait(timeout_s=180.0)
        assert live_processes_naming(str(scenario)) == [], "processes left running"
        metrics = run_dir / "metrics.json"
        return up, rc, json.loads(metrics.read_text()) if metrics.is_file() else None

    yield run
    for up in runs:
        up.kill_all()


def _formation_back(m: dict) -> None:
    assert m["min_separation_m"] >= 2.0, m
    assert m["periods_recorded"] == m["periods_expected"], m
    assert m["formation_rms_m"] <= 1.5 * BASELINE_RMS_M, m


def test_a_frozen_agent_takes_its_vehicle_back(fly):
    up, rc, m = fly("freeze-agent")
    text = up.text()
    assert rc == 0, text
    assert "agent-2 frozen" in text and "agent-2 resumed" in text
    log = (up.run_dir / "logs" / "agent-2.log").read_text()
    assert "gap in its own setpoints; taking it back" in log and "re-engaged" in log, log
    summary = json.loads(log.strip().splitlines()[-1])
    assert summary["reengaged"] == 1 and summary["resumes"] >= 1, summary
    _formation_back(m)


@pytest.mark.parametrize("speed", [1, 4])
def test_a_restarted_router_is_rejoined(fly, speed):
    """The router is down for 3 s of fleet time and its restart takes some wall time more (at
    x4 four times as much fleet time); the vehicles fly the silence on their slots (each keeps
    clear of the others' regions: docs/design.md, "Silent neighbours") and the formation is
    back as good as without the fault."""
    up, rc, m = fly("restart-router", "--agent-records", "--speed", str(speed))
    assert rc == 0, up.text()
    assert "zenoh-router killed" in up.text() and "zenoh-router restarted" in up.text()
    _formation_back(m)
    # Every agent hears both others again (plans younger than 0.5 s) within 2 s of wall time
    # of the restart, which is at 13 s of fleet time.
    for vid in (1, 2, 3):
        rows = [
            json.loads(line)
            for line in (up.run_dir / "agents" / f"agent-{vid}.jsonl").read_text().splitlines()
        ]
        after = [r for r in rows if r["stamp_ns"] >= 13e9]
        fresh = [
            r["stamp_ns"] * 1e-9
            for r in after
            if len(r["neighbour_ages_s"]) == 2
            and all(a is not None and a < 0.5 for a in r["neighbour_ages_s"].values())
        ]
        assert fresh and fresh[0] <= 13.0 + 2.0 * speed, (vid, fresh[:3])


def test_the_fleet_flies_on_without_its_ground_station(fly):
    up, rc, m = fly("kill-ground-station")
    text = up.text()
    assert rc == 0, text
    assert "the ground station is gone; the fleet flies on" in text
    assert "no metrics: a fault killed the ground station" in text
    for vid in (1, 2, 3):
        log = (up.run_dir / "logs" / f"agent-{vid}.log").read_text()
        summary = json.loads(log.strip().splitlines()[-1])
        assert summary["steps"] >= 140 and summary["failure"] is None, summary


def test_a_killed_agent_leaves_its_vehicle_holding_and_the_others_clear(fly):
    up, rc, m = fly("kill-agent")
    assert rc == 0, up.text()
    assert "agent-2 killed" in up.text()
    assert m["min_separation_m"] >= 2.0, m
    assert m["periods_recorded"] == m["periods_expected"], m


def test_an_agent_whose_clock_runs_fast_is_still_avoided_and_flown_with(fly):
    up, rc, m = fly("clock-offset", "--agent-records")
    assert rc == 0, up.text()
    assert "agent-2 clock +300 ms, the whole run" in up.text()
    # Not back in formation: agent 2 flies to where the target will be 1.2 s of fleet time
    # later (docs/design.md, "Injected faults"); the fleet keeps its distance from it.
    assert m["min_separation_m"] >= 2.0, m
    assert m["periods_recorded"] == m["periods_expected"], m
    # Agent 2's plans are stamped 0.3 s x 4 (its fleet time runs ahead) in the others' future:
    # they still fly with it (its formation term counts) rather than ignoring it.
    rows = [
        json.loads(line)
        for line in (up.run_dir / "agents" / "agent-1.jsonl").read_text().splitlines()
    ]
    flying = [r for r in rows if r["stamp_ns"] >= 5e9]
    ages = [r["neighbour_ages_s"]["2"] for r in flying if r["neighbour_ages_s"].get("2")]
    assert ages and min(ages) < -0.5, ages[:5]
    assert all(r["formation_terms"] == 2 for r in flying[-50:])


def test_a_short_cut_in_an_autopilot_link_is_flown_through(fly):
    up, rc, m = fly("link-blackout")
    assert rc == 0, up.text()
    _formation_back(m)
    log = (up.run_dir / "logs" / "agent-2.log").read_text()
    summary = json.loads(log.strip().splitlines()[-1])
    assert summary["link_faults"]["link_blacked_out"] > 0, summary
    assert summary["mode"] != "HOLD" or not summary["mode_lost"], summary
    assert "mode lost" not in log


def test_two_agents_starved_of_cpu_keep_their_distance(fly):
    """Two agents get no CPU at all for 4 s (SIGSTOP): their vehicles hold (the autopilots'
    offboard loss), the agents resume late, know it, take their vehicles back, and nobody comes
    closer than d_safe. (Formation is lost for a while: the held vehicles fall 5-6 m behind.)"""
    up, rc, m = fly("starve-two-agents")
    assert rc == 0, up.text()
    assert "agent-1 frozen" in up.text() and "agent-2 resumed" in up.text()
    assert m["min_separation_m"] >= 2.0, m
    assert m["periods_recorded"] == m["periods_expected"], m
    for vid in (1, 2):
        log = (up.run_dir / "logs" / f"agent-{vid}.log").read_text()
        assert f"vehicle {vid}: re-engaged" in log
        summary = json.loads(log.strip().splitlines()[-1])
        assert summary["resumes"] >= 1 and summary["failure"] is None, summary
