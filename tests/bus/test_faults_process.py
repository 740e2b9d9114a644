"""Process faults in a fault file (freeze, kill, restart): their validation, who reads them (a
live fleet's launcher, not `fleetmpc sim`, not an agent's plan bus), and how they are described.
"""

import math
from pathlib import Path

import pytest

from fleetmpc.bus.faults import (
    FAULT_KINDS,
    Fault,
    FaultLayer,
    FaultSchedule,
    load_faults,
    parse_faults,
)
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import plan_key, status_key

FLEET = "test"
FLEET_IDS = (1, 2, 3)
PROCESSES = ("zenoh-router", "target", "sitl-1", "agent-1", "sitl-2", "agent-2", "gcs")
S = 1_000_000_000

FREEZE = {"kind": "freeze", "process": "agent-2", "start_s": 10.0, "duration_s": 2.0}
KILL = {"kind": "kill", "process": "agent-2", "start_s": 10.0}
RESTART = {"kind": "restart", "process": "zenoh-router", "start_s": 10.0, "duration_s": 3.0}
LOSS = {"kind": "loss", "probability": 0.3}


def live(*faults: dict) -> FaultSchedule:
    """Parse as `fleetmpc up` does: with the launch's process names."""
    return parse_faults({"faults": list(faults)}, vehicle_ids=FLEET_IDS, processes=PROCESSES)


def refused(doc: dict, **kwargs) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        parse_faults(doc, vehicle_ids=FLEET_IDS, **kwargs)
    return info.value


def test_the_process_kinds_are_fault_kinds() -> None:
    assert {"freeze", "kill", "restart"} <= set(FAULT_KINDS)
    assert not any(Fault(k, process="gcs").network for k in ("freeze", "kill", "restart"))
    assert all(Fault(k).network for k in ("loss", "delay", "duplicate", "reorder", "blackout"))
    assert Fault("partition").network


def test_live_process_faults_parse_with_their_defaults() -> None:
    got = live(FREEZE, KILL, RESTART, {"kind": "kill", "process": "gcs"}, LOSS)
    assert got == FaultSchedule(
        faults=(
            Fault("freeze", start_s=10.0, duration_s=2.0, process="agent-2"),
            Fault("kill", start_s=10.0, process="agent-2"),
            Fault("restart", start_s=10.0, duration_s=3.0, process="zenoh-router"),
            Fault("kill", start_s=0.0, process="gcs"),
            Fault("loss", probability=0.3),
        )
    )
    kill = got.faults[1]
    assert kill.duration_s == math.inf and kill.vehicles is None
    assert [f.network for f in got.faults] == [False, False, False, False, True]


def test_the_live_fault_files_of_the_repository_parse(paper) -> None:
    """faults/live/*.toml, against the paper fleet's process names (as `fleetmpc up` names
    them, `fleetmpc.launch.fleet`)."""
    folder = Path(__file__).resolve().parents[2] / "faults" / "live"
    names = ["zenoh-router", "target", "gcs"]
    names += [f"{role}-{v}" for v in paper.vehicle_ids for role in ("sitl", "agent")]
    files = sorted(folder.glob("*.toml"))
    assert len(files) >= 4
    for path in files:
        got = load_faults(path, vehicle_ids=paper.vehicle_ids, processes=names)
        assert got.faults and all(not f.network for f in got.faults), path


@pytest.mark.parametrize("fault", [FREEZE, KILL, RESTART])
def test_a_simulation_refuses_a_process_fault(fault) -> None:
    """`fleetmpc sim` parses without process names: a process fault has nothing to hit."""
    err = refused({"faults": [fault]})
    assert err.field == "faults[0].kind"
    assert str(err).startswith("faults[0].kind: ")
    assert fault["kind"] in str(err) and "fleetmpc up" in str(err)
    # The field counts the faults of the file.
    err = refused({"faults": [LOSS, fault]})
    assert err.field == "faults[1].kind"


@pytest.mark.parametrize("fault", [FREEZE, KILL, RESTART])
@pytest.mark.parametrize("name", ["agent-9", "AGENT-2", "", 2, None])
def test_a_process_the_fleet_does_not_have_is_refused(fault, name) -> None:
    doc = {"faults": [{**fault, "process": name}]}
    err = refused(doc, processes=PROCESSES)
    assert err.field == "faults[0].process"
    assert repr(name) in str(err) and "agent-2" in str(err)  # what it got, and what is known


@pytest.mark.parametrize("fault", [FREEZE, KILL, RESTART])
def test_a_process_fault_needs_its_process(fault) -> None:
    doc = {"faults": [{k: v for k, v in fault.items() if k != "process"}]}
    assert refused(doc, processes=PROCESSES).field == "faults[0].process"


@pytest.mark.parametrize("kind", ["freeze", "restart"])
def test_freeze_and_restart_need_a_duration(kind) -> None:
    doc = {"faults": [{"kind": kind, "process": "agent-1", "start_s": 5.0}]}
    err = refused(doc, processes=PROCESSES)
    assert err.field == "faults[0].duration_s"
    assert kind in str(err)
    for bad in (0.0, -1.0, math.nan, math.inf, "long"):
        doc = {"faults": [{"kind": kind, "process": "agent-1", "duration_s": bad}]}
        assert refused(doc, processes=PROCESSES).field == "faults[0].duration_s", bad


@pytest.mark.parametrize(
    ("fault", "field"),
    [
        ({**KILL, "duration_s": 3.0}, "faults[0].duration_s"),  # a kill is for good
        ({**KILL, "vehicles": [2]}, "faults[0].vehicles"),  # a process, not vehicles
        ({**FREEZE, "vehicles": [2]}, "faults[0].vehicles"),
        ({**RESTART, "vehicles": [1, 2]}, "faults[0].vehicles"),
        ({**KILL, "probability": 0.5}, "faults[0].probability"),
        ({**FREEZE, "groups": [[1], [2]]}, "faults[0].groups"),
        ({**LOSS, "process": "agent-1"}, "faults[0].process"),  # only process faults name one
        ({"kind": "blackout", "process": "agent-1"}, "faults[0].process"),
        ({**KILL, "start_s": -1.0}, "faults[0].start_s"),
    ],
)
def test_a_key_a_process_fault_does_not_have_is_refused(fault, field) -> None:
    err = refused({"faults": [fault]}, processes=PROCESSES)
    assert err.field == field
    assert str(err).startswith(f"{field}: ")


def test_kill_names_its_known_keys_when_it_refuses_one() -> None:
    err = refused({"faults": [{**KILL, "duration_s": 3.0}]}, processes=PROCESSES)
    assert "unknown for a kill fault" in str(err)
    assert "known: kind, process, start_s" in str(err)  # neither duration_s nor vehicles


def test_load_faults_names_the_file_and_the_process_field(tmp_path) -> None:
    path = tmp_path / "f.toml"
    path.write_text('[[faults]]\nkind = "kill"\nprocess = "agent-7"\nstart_s = 3.0\n')
    with pytest.raises(ConfigError) as info:
        load_faults(path, vehicle_ids=FLEET_IDS, processes=PROCESSES)
    assert info.value.field == f"{path}: faults[0].process"
    path.write_text('[[faults]]\nkind = "kill"\nprocess = "agent-1"\nstart_s = 3.0\n')
    got = load_faults(path, vehicle_ids=FLEET_IDS, processes=PROCESSES)
    assert got.faults == (Fault("kill", start_s=3.0, process="agent-1"),)


# An agent, given the file its launcher checked, keeps the network faults only. ---------------
# BUG: `parse_faults` (and `load_faults`) accept `network_only` but never use it: the process
# faults are still validated, and refused without process names (see the report).


def test_network_only_drops_the_process_faults_and_keeps_the_network_ones() -> None:
    doc = {"faults": [FREEZE, LOSS, KILL, {"kind": "blackout", "vehicles": [2]}, RESTART]}
    got = parse_faults(doc, vehicle_ids=FLEET_IDS, network_only=True)
    assert got.faults == (Fault("loss", probability=0.3), Fault("blackout", vehicles=(2,)))


def test_network_only_does_not_validate_the_process_faults() -> None:
    """The launcher checked them against its process names; an agent does not know them."""
    doc = {
        "seed": 4,
        "faults": [
            {"kind": "kill", "process": "no-such-process", "duration_s": 5.0},
            {"kind": "freeze", "process": "agent-1"},  # no duration
            LOSS,
        ],
    }
    got = parse_faults(doc, vehicle_ids=FLEET_IDS, network_only=True)
    assert got == FaultSchedule(faults=(Fault("loss", probability=0.3),), seed=4)


def test_an_agent_loads_a_mixed_live_fault_file(tmp_path) -> None:
    """What `fleetmpc agent --faults FILE` does (`onboard/cli.py`) with a file `fleetmpc up`
    hands it when the file has network faults beside process ones."""
    path = tmp_path / "mixed.toml"
    path.write_text(
        '[[faults]]\nkind = "loss"\nprobability = 0.2\n\n'
        '[[faults]]\nkind = "kill"\nprocess = "agent-2"\nstart_s = 10.0\n'
    )
    got = load_faults(path, vehicle_ids=FLEET_IDS, network_only=True)
    assert got.faults == (Fault("loss", probability=0.2),)


def test_network_only_still_validates_the_network_faults() -> None:
    err = refused({"faults": [{"kind": "loss", "probability": 2.0}]}, network_only=True)
    assert err.field == "faults[0].probability"


def test_network_only_keeps_a_file_of_network_faults_whole() -> None:
    doc = {"faults": [LOSS, {"kind": "delay", "delay_s": 0.1}]}
    got = parse_faults(doc, vehicle_ids=FLEET_IDS, network_only=True)
    assert got.faults == (Fault("loss", probability=0.3), Fault("delay", delay_s=0.1))


# A plan bus's fault layer --------------------------------------------------------------------


def test_a_fault_layer_ignores_process_faults() -> None:
    """A schedule of process faults only lets every payload through, at every time, both ways
    (a kill of agent-2 is not a blackout of vehicle 2)."""
    sched = live(KILL, {**FREEZE, "process": "agent-1", "start_s": 0.0}, RESTART)
    clock = [0]
    for vehicle in (1, 2):
        layer = FaultLayer(sched, vehicle_id=vehicle, clock=lambda: clock[0], seed=0)
        for t_s in (0.0, 5.0, 10.0, 11.0, 12.5, 100.0):
            clock[0] = round(t_s * S)
            for sender in (1, 2, 3):
                for key in (plan_key(FLEET, sender), status_key(FLEET, sender)):
                    payload = f"{sender}@{t_s}".encode()
                    assert layer.arrive(key, payload) == [(key, payload)]
            assert layer.release() == []
        assert layer.held == 0
        assert set(layer.counts.values()) == {0}


def test_a_fault_layer_applies_the_network_faults_beside_process_ones() -> None:
    sched = live(KILL, {"kind": "blackout", "vehicles": [2], "start_s": 10.0}, FREEZE)
    clock = [11 * S]
    layer = FaultLayer(sched, vehicle_id=1, clock=lambda: clock[0], seed=0)
    assert layer.arrive(plan_key(FLEET, 2), b"x") == []  # vehicle 2 blacked out
    assert layer.arrive(plan_key(FLEET, 3), b"y") == [(plan_key(FLEET, 3), b"y")]
    assert layer.counts["blacked_out"] == 1


# Descriptions --------------------------------------------------------------------------------


def test_a_process_fault_describes_the_process_it_hits() -> None:
    kill, freeze, restart = live(KILL, FREEZE, RESTART).faults
    assert kill.describe() == "agent-2 killed (SIGKILL) at 10 s"
    assert freeze.describe() == "frozen (SIGSTOP) for agent-2, 10 s to 12 s"
    assert restart.describe() == "killed, then restarted for zenoh-router, 10 s to 13 s"
    for f in (kill, freeze, restart):
        assert "vehicle" not in f.describe()


def test_a_clock_offset_is_an_agents_and_needs_its_offset():
    fault = live({"kind": "clock_offset", "process": "agent-2", "offset_s": 0.3}).faults[0]
    assert fault.offset_s == 0.3 and not fault.network
    assert fault.describe() == "agent-2 clock +300 ms, the whole run"
    for table, field in (
        ({"kind": "clock_offset", "process": "gcs", "offset_s": 0.3}, "faults[0].process"),
        ({"kind": "clock_offset", "process": "agent-1"}, "faults[0].offset_s"),
        ({"kind": "clock_offset", "process": "agent-1", "offset_s": 99.0}, "faults[0].offset_s"),
        ({"kind": "clock_offset", "process": "agent-1", "offset_s": 0.1, "start_s": 1.0},
         "faults[0].start_s"),
    ):  # fmt: skip
        with pytest.raises(ConfigError) as e:
            live(table)
        assert e.value.field == field


def test_link_faults_cut_the_hit_vehicles_link_inside_their_window():
    from fleetmpc.bus.faults import LinkFaults

    doc = {
        "faults": [
            {"kind": "link_blackout", "vehicles": [2], "start_s": 10.0, "duration_s": 1.0},
            {"kind": "link_loss", "vehicles": [3], "probability": 1.0},
        ]
    }
    schedule = live(*doc["faults"])
    now = [0]
    two = LinkFaults(schedule, vehicle_id=2, clock=lambda: now[0], seed=0)
    three = LinkFaults(schedule, vehicle_id=3, clock=lambda: now[0], seed=0)
    one = LinkFaults(schedule, vehicle_id=1, clock=lambda: now[0], seed=0)
    assert not two.cut() and three.cut() and not one.cut()
    now[0] = 10 * S
    assert two.cut() and not one.cut()
    now[0] = 11 * S
    assert not two.cut()
    assert two.counts == {"link_lost": 0, "link_blacked_out": 1}
    assert three.counts["link_lost"] == 1
    with pytest.raises(ConfigError) as e:  # a simulation has no autopilot link
        parse_faults({"faults": doc["faults"][:1]}, vehicle_ids=FLEET_IDS)
    assert e.value.field == "faults[0].kind"
    kept = parse_faults({"faults": doc["faults"]}, vehicle_ids=FLEET_IDS, network_only=True)
    assert [f.kind for f in kept.faults] == ["link_blackout", "link_loss"]  # an agent's own
