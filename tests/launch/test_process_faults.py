"""ProcessFaults, the driver of a live fleet's process faults, on recorders instead of processes.

Fleet time is set by hand before each poll: the epoch is placed so that fleet time reads a chosen
value then (`at`). The checks keep whole fleet seconds between the polls and the actions' times,
so a slow machine (a poll some milliseconds after its epoch was set) changes nothing.
"""

import re
import signal
import time

import pytest

from fleetmpc.bus.faults import Fault
from fleetmpc.launch.process_faults import ProcessFaults

PROCESSES = ("zenoh-router", "target", "sitl-1", "agent-1", "agent-2", "gcs")


class Recorder:
    """What the driver did to the processes, in order: ("signal", name, signum) and
    ("start", name); and the lines it logged."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.logged: list[str] = []

    def signal_process(self, name: str, signum: int) -> None:
        self.calls.append(("signal", name, signum))

    def start_process(self, name: str) -> None:
        self.calls.append(("start", name))


def driver(*faults: Fault, speed: float = 1.0) -> tuple[ProcessFaults, Recorder]:
    rec = Recorder()
    pf = ProcessFaults(
        faults,
        signal_process=rec.signal_process,
        start_process=rec.start_process,
        log=rec.logged.append,
        speed=speed,
    )
    return pf, rec


def at(pf: ProcessFaults, t_s: float) -> None:
    """Place the epoch so that fleet time is `t_s` now, then poll (a millisecond of fleet time
    later, so that an action due at `t_s` is due whatever the clock's resolution)."""
    pf.epoch_ns = time.time_ns() - round((t_s + 1e-3) * 1e9 / pf.speed)
    pf.poll()


def done_times(pf: ProcessFaults) -> list[tuple[float, str]]:
    """`done` as (fleet time, what) pairs."""
    out = []
    for line in pf.done:
        m = re.fullmatch(r"(-?\d+\.\d) s: (.+)", line)
        assert m is not None, line
        out.append((float(m.group(1)), m.group(2)))
    return out


FREEZE = Fault("freeze", start_s=10.0, duration_s=2.0, process="agent-2")
KILL = Fault("kill", start_s=10.0, process="agent-2")
RESTART = Fault("restart", start_s=10.0, duration_s=3.0, process="zenoh-router")


def test_nothing_happens_before_the_epoch_is_known() -> None:
    pf, rec = driver(FREEZE, KILL, RESTART)
    assert pf.fleet_s() is None
    for _ in range(3):
        pf.poll()
    assert rec.calls == [] and rec.logged == [] and pf.done == []
    assert pf.pending == 5  # freeze: stop + cont; kill; restart: kill + start
    assert not pf.frozen and not pf.killed


def test_fleet_time_follows_the_epoch_and_the_speed() -> None:
    pf, _ = driver(FREEZE, speed=4.0)
    pf.epoch_ns = time.time_ns() - 2_000_000_000  # 2 s of wall time ago: 8 s of fleet time
    assert 8.0 <= pf.fleet_s() < 9.0
    pf.epoch_ns = time.time_ns() + 1_000_000_000  # an epoch a second of wall time ahead
    assert -4.0 <= pf.fleet_s() < -3.0


def test_nothing_happens_before_a_faults_start() -> None:
    pf, rec = driver(FREEZE, KILL, RESTART)
    at(pf, -5.0)  # an epoch announced ahead of time: fleet time is negative
    at(pf, 0.0)
    at(pf, 9.0)
    assert rec.calls == [] and pf.done == [] and pf.pending == 5


def test_a_freeze_stops_the_process_then_resumes_it_after_its_duration() -> None:
    pf, rec = driver(FREEZE)
    at(pf, 10.0)
    assert rec.calls == [("signal", "agent-2", signal.SIGSTOP)]
    assert pf.frozen == {"agent-2"} and pf.pending == 1
    assert not pf.expects_exit("agent-2")  # a frozen process is not expected to exit
    at(pf, 11.0)  # still inside the freeze
    assert len(rec.calls) == 1
    at(pf, 12.0)
    assert rec.calls[1:] == [("signal", "agent-2", signal.SIGCONT)]
    assert pf.frozen == set() and pf.pending == 0
    at(pf, 30.0)
    assert len(rec.calls) == 2  # nothing more
    assert [what for _, what in done_times(pf)] == ["agent-2 frozen", "agent-2 resumed"]
    assert rec.logged == pf.done


def test_a_kill_sends_sigkill_once_and_the_exit_is_expected() -> None:
    pf, rec = driver(KILL)
    assert not pf.expects_exit("agent-2")
    at(pf, 10.0)
    assert rec.calls == [("signal", "agent-2", signal.SIGKILL)]
    assert pf.expects_exit("agent-2") and pf.killed == {"agent-2"}
    assert not pf.expects_exit("agent-1")
    at(pf, 100.0)
    assert len(rec.calls) == 1 and pf.pending == 0
    assert pf.expects_exit("agent-2")  # for good: a kill is never undone


def test_a_restart_kills_then_starts_the_process_after_its_duration() -> None:
    pf, rec = driver(RESTART)
    at(pf, 10.0)
    assert rec.calls == [("signal", "zenoh-router", signal.SIGKILL)]
    assert pf.expects_exit("zenoh-router") and pf.pending == 1
    at(pf, 12.0)  # 1 s before it is due
    assert len(rec.calls) == 1 and "zenoh-router" in pf.killed
    at(pf, 13.0)
    assert rec.calls[1:] == [("start", "zenoh-router")]
    assert pf.killed == set() and not pf.expects_exit("zenoh-router") and pf.pending == 0
    assert [what for _, what in done_times(pf)] == ["zenoh-router killed", "zenoh-router restarted"]


def test_actions_come_in_time_order_whatever_the_order_of_the_faults() -> None:
    faults = (
        Fault("restart", start_s=20.0, duration_s=5.0, process="zenoh-router"),  # 20 kill, 25 start
        Fault("freeze", start_s=2.0, duration_s=30.0, process="agent-1"),  # 2 stop, 32 cont
        Fault("kill", start_s=15.0, process="gcs"),  # 15
        Fault("freeze", start_s=8.0, duration_s=1.0, process="agent-2"),  # 8 stop, 9 cont
    )
    expected = [
        ("signal", "agent-1", signal.SIGSTOP),
        ("signal", "agent-2", signal.SIGSTOP),
        ("signal", "agent-2", signal.SIGCONT),
        ("signal", "gcs", signal.SIGKILL),
        ("signal", "zenoh-router", signal.SIGKILL),
        ("start", "zenoh-router"),
        ("signal", "agent-1", signal.SIGCONT),
    ]
    # Polled late, all at once: still in time order.
    pf, rec = driver(*faults)
    assert pf.pending == 7
    at(pf, 100.0)
    assert rec.calls == expected and pf.pending == 0
    # Polled every second: the same order, each action at its own time.
    pf, rec = driver(*faults)
    pending = [pf.pending]
    for t in range(40):
        at(pf, float(t))
        pending.append(pf.pending)
    assert rec.calls == expected
    assert [t for t, _ in done_times(pf)] == pytest.approx([2, 8, 9, 15, 20, 25, 32], abs=0.5)
    assert [what for _, what in done_times(pf)] == [
        "agent-1 frozen",
        "agent-2 frozen",
        "agent-2 resumed",
        "gcs killed",
        "zenoh-router killed",
        "zenoh-router restarted",
        "agent-1 resumed",
    ]
    # `pending` only counts down, one per action, to zero.
    assert pending[0] == 7 and pending[-1] == 0
    assert all(b <= a for a, b in zip(pending, pending[1:], strict=False))
    assert sum(a - b for a, b in zip(pending, pending[1:], strict=False)) == 7


def test_done_lists_each_action_with_the_fleet_time_it_was_done() -> None:
    pf, rec = driver(FREEZE, RESTART, speed=4.0)
    at(pf, 10.0)
    at(pf, 12.0)
    at(pf, 13.0)
    got = done_times(pf)
    # (At 10 s the freeze's stop and the restart's kill are both due.)
    assert sorted(got[:2], key=lambda x: x[1]) == [
        (pytest.approx(10.0, abs=0.5), "agent-2 frozen"),
        (pytest.approx(10.0, abs=0.5), "zenoh-router killed"),
    ]
    assert got[2] == (pytest.approx(12.0, abs=0.5), "agent-2 resumed")
    assert got[3] == (pytest.approx(13.0, abs=0.5), "zenoh-router restarted")
    assert rec.logged == pf.done  # each line is logged as it is done


def test_release_resumes_every_frozen_process() -> None:
    pf, rec = driver(
        FREEZE,
        Fault("freeze", start_s=5.0, duration_s=60.0, process="agent-1"),
        Fault("kill", start_s=6.0, process="sitl-1"),
    )
    at(pf, 11.0)
    assert pf.frozen == {"agent-1", "agent-2"} and pf.killed == {"sitl-1"}
    rec.calls.clear()
    pf.release()
    assert sorted(rec.calls) == [
        ("signal", "agent-1", signal.SIGCONT),
        ("signal", "agent-2", signal.SIGCONT),
    ]
    assert pf.frozen == set()
    assert pf.killed == {"sitl-1"}  # a killed process is not resumed
    rec.calls.clear()
    pf.release()
    assert rec.calls == []  # nothing frozen any more: nothing to resume


def test_release_without_a_freeze_signals_nothing() -> None:
    pf, rec = driver(KILL)
    pf.release()
    at(pf, 20.0)
    pf.release()
    assert rec.calls == [("signal", "agent-2", signal.SIGKILL)]


def test_only_process_faults_act() -> None:
    """A network fault handed to the driver by mistake makes no action."""
    pf, rec = driver(Fault("loss", probability=0.5), Fault("blackout", vehicles=(1,)), KILL)
    assert pf.pending == 1
    at(pf, 50.0)
    assert rec.calls == [("signal", "agent-2", signal.SIGKILL)]
