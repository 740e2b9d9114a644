"""Process faults of a live fleet: what `fleetmpc up --faults FILE` does to its processes.

The fault file's process faults (`fleetmpc.bus.faults`, kinds freeze, kill and restart) each
name a process of the launch (``agent-2``, ``sitl-3``, ``zenoh-router``, ``gcs``, ...) and a
start in fleet time:
- freeze: SIGSTOP, then SIGCONT `duration_s` later (a stalled process: every thread stops);
- kill: SIGKILL, for good;
- restart: SIGKILL, then the same process started again `duration_s` later.

Fleet time comes from the epoch the ground station announces (its status file carries it); the
launcher keeps it once known, so faults keep their times after the ground station is gone. The
driver only acts; the launcher decides what an exit means (`ProcessFaults.killed` says which
exits were injected).
"""

import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

from fleetmpc.bus.faults import Fault

__all__ = ["ProcessFaults"]


@dataclass
class _Pending:
    at_s: float
    fault: Fault
    action: str
    """``stop``, ``cont``, ``kill`` or ``start``."""


@dataclass
class ProcessFaults:
    """Applies process faults at their fleet times.

    `signal_process(name, signum)` signals the running process called `name`;
    `start_process(name)` starts it again; `log(text)` reports each action.
    """

    KINDS: ClassVar[tuple[str, ...]] = ("freeze", "kill", "restart")
    """The fault kinds it applies (a clock offset is given to its process at launch)."""

    faults: tuple[Fault, ...]
    signal_process: Callable[[str, int], None]
    start_process: Callable[[str], None]
    log: Callable[[str], None]
    speed: float = 1.0
    epoch_ns: int | None = None
    killed: set[str] = field(default_factory=set)
    """Processes a fault has killed and not (yet) restarted."""
    frozen: set[str] = field(default_factory=set)
    """Processes a fault has stopped and not (yet) resumed."""
    done: list[str] = field(default_factory=list)
    """What was done, with its fleet time, for the run's report."""

    def __post_init__(self) -> None:
        self._pending: list[_Pending] = []
        for f in self.faults:
            if f.kind == "freeze":
                self._pending += [
                    _Pending(f.start_s, f, "stop"),
                    _Pending(f.start_s + f.duration_s, f, "cont"),
                ]
            elif f.kind == "kill":
                self._pending.append(_Pending(f.start_s, f, "kill"))
            elif f.kind == "restart":
                self._pending += [
                    _Pending(f.start_s, f, "kill"),
                    _Pending(f.start_s + f.duration_s, f, "start"),
                ]
        self._pending.sort(key=lambda p: p.at_s)

    def fleet_s(self) -> float | None:
        """Fleet time now [s], None before the epoch is known."""
        if self.epoch_ns is None:
            return None
        return (time.time_ns() - self.epoch_ns) * self.speed * 1e-9

    @property
    def pending(self) -> int:
        return len(self._pending)

    def expects_exit(self, name: str) -> bool:
        """True if a fault killed `name` (or is restarting it)."""
        return name in self.killed

    def poll(self) -> None:
        """Apply every action whose time has come."""
        now = self.fleet_s()
        while now is not None and self._pending and self._pending[0].at_s <= now:
            p = self._pending.pop(0)
            name = p.fault.process
            if p.action == "stop":
                self.signal_process(name, signal.SIGSTOP)
                self.frozen.add(name)
            elif p.action == "cont":
                self.signal_process(name, signal.SIGCONT)
                self.frozen.discard(name)
            elif p.action == "kill":
                self.killed.add(name)
                self.signal_process(name, signal.SIGKILL)
            else:
                self.start_process(name)
                self.killed.discard(name)
            text = {"stop": "frozen", "cont": "resumed", "kill": "killed", "start": "restarted"}
            self.done.append(f"{now:.1f} s: {name} {text[p.action]}")
            self.log(self.done[-1])

    def release(self) -> None:
        """Resume every frozen process (before the launcher stops the fleet)."""
        for name in sorted(self.frozen):
            self.signal_process(name, signal.SIGCONT)
        self.frozen.clear()
