"""The processes `fleetmpc up` launches: each started as `python -m fleetmpc.cli ...` in a
session of its own with its output in a log, watched, restarted when asked, and stopped role by
role (the ground station first, the router and the vehicles last), SIGTERM then SIGKILL."""

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.launch.fleet import ProcessSpec

__all__ = ["Child", "ProcessFailed", "ProcessGroup", "log_tail"]

_STOP_ORDER = (("gcs",), ("agent", "target"), ("sitl", "router"))
"""Shutdown stages: the ground station (it closes the recording), then the agents (they command
HOLD while their autopilots still run) with the target, then the vehicles and the router."""
_GRACE_S = 3.0
"""How long a stage has to exit on SIGTERM before SIGKILL [s]."""
TAIL_LINES = 15
"""How much of a failed process's log is shown."""


@dataclass
class Child:
    """One launched process, its spec and its log."""

    spec: ProcessSpec
    proc: subprocess.Popen
    log: Path
    expected_exit: bool = False
    exit_handled: bool = False
    """Its exit is not a failure of the run: a fault killed it, or it was restarted."""


def log_tail(path: Path, lines: int = TAIL_LINES) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return "(no log)"
    return "\n".join("    " + line for line in text[-lines:]) or "    (empty log)"


class ProcessGroup:
    """The launched processes, started in order and stopped in reverse roles order."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.logs = run_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.children: list[Child] = []
        self.stage_s: dict[str, float] = {}

    def start(self, spec: ProcessSpec, *, again: bool = False) -> Child:
        """Start a process; `again`: a restart, whose output goes on in the same log."""
        log = self.logs / f"{spec.name}.log"
        with open(log, "a" if again else "w") as out:
            proc = subprocess.Popen(
                [sys.executable, "-m", "fleetmpc.cli", *spec.argv],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
        child = Child(spec, proc, log, expected_exit=spec.role == "target")
        self.children.append(child)
        return child

    def get(self, name: str) -> Child:
        """The newest process called `name` (a restarted one replaces its first)."""
        return [c for c in self.children if c.spec.name == name][-1]

    def restart(self, name: str) -> Child:
        """Start the process called `name` again (its old one's exit is then handled)."""
        old = self.get(name)
        old.exit_handled = True
        return self.start(old.spec, again=True)

    def wait_for_text(self, child: Child, text: str, *, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while text not in child.log.read_text(errors="replace"):
            if child.proc.poll() is not None:
                raise ProcessFailed(child)
            if time.monotonic() > deadline:
                raise ProcessFailed(child, f"did not print {text!r} within {timeout_s:g} s")
            time.sleep(0.05)

    def failed(self) -> Child | None:
        """The first child that exited when it should not have."""
        for c in self.children:
            rc = c.proc.poll()
            if c.exit_handled or rc is None or c.spec.role == "gcs":
                continue
            if rc != 0 or not c.expected_exit:
                return c
        return None

    def stop(self) -> dict[str, int | None]:
        """Stop every child (SIGTERM by role order, then SIGKILL); return the exit codes.

        `stage_s` keeps each stage's wall time (the first role of the stage names it).
        """
        for roles in _STOP_ORDER:
            t0 = time.monotonic()
            group = [c for c in self.children if c.spec.role in roles and c.proc.poll() is None]
            for c in group:
                c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + _GRACE_S
            for c in group:
                try:
                    c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    c.proc.kill()
                    c.proc.wait(timeout=5.0)
            self.stage_s[roles[0]] = time.monotonic() - t0
        return {c.spec.name: c.proc.returncode for c in self.children}


class ProcessFailed(Exception):
    def __init__(self, child: Child, why: str | None = None) -> None:
        self.child = child
        rc = child.proc.poll()
        self.why = why or f"exited with status {rc}"
        super().__init__(f"{child.spec.name} {self.why}")
