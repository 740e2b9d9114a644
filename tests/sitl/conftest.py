"""Fixtures of the SITL tests: loopback ports and child processes that are always cleaned up."""

import queue
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from sim_client import IDEAL_SCENARIO

ROOT = Path(__file__).resolve().parents[2]
SUMMARY = re.compile(
    r"received (?P<messages>\d+) messages \((?P<bytes>\d+) bytes\), dropped (?P<bad>\d+) bad frames"
    r" and (?P<unknown>\d+) unknown, (?P<commands>\d+) commands.*loop errors: (?P<errors>\d+)"
)


@dataclass
class Child:
    """A child process whose stdout and stderr are drained into line lists by threads."""

    proc: subprocess.Popen
    stdout: "queue.Queue[str]" = field(default_factory=queue.Queue)
    stderr_lines: list[str] = field(default_factory=list)
    stdout_lines: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        threading.Thread(target=self._drain, args=(self.proc.stdout, True), daemon=True).start()
        threading.Thread(target=self._drain, args=(self.proc.stderr, False), daemon=True).start()

    def _drain(self, pipe, is_stdout: bool) -> None:
        for line in pipe:
            if is_stdout:
                self.stdout_lines.append(line)
                self.stdout.put(line)
            else:
                self.stderr_lines.append(line)

    def wait_line(self, pattern: str, *, timeout_s: float = 30.0) -> re.Match:
        deadline = time.monotonic() + timeout_s
        regex = re.compile(pattern)
        while time.monotonic() < deadline:
            try:
                line = self.stdout.get(timeout=0.1)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            match = regex.search(line)
            if match:
                return match
        raise AssertionError(
            f"no line matching {pattern!r} (exit code {self.proc.poll()}); stderr:\n"
            + "".join(self.stderr_lines[-20:])
        )

    def stop(self, sig: int = signal.SIGTERM, *, timeout_s: float = 10.0) -> int:
        """Send `sig`, wait for the exit code (kill after `timeout_s`)."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            rc = self.proc.wait(timeout=5)
        time.sleep(0.05)  # let the drain threads read the last lines
        return rc

    @property
    def stderr(self) -> str:
        return "".join(self.stderr_lines)

    def summary(self) -> dict[str, int]:
        """Counters of the vehicle's exit summary (call after stop())."""
        match = SUMMARY.search(self.stderr)
        assert match, f"no exit summary in stderr:\n{self.stderr}"
        return {k: int(v) for k, v in match.groupdict().items()}


@pytest.fixture
def spawn() -> Iterator:
    """Start child processes; every one is stopped (then killed) when the test ends."""
    children: list[Child] = []

    def _spawn(argv: list[str], *, cwd: Path = ROOT, env: dict | None = None) -> Child:
        proc = subprocess.Popen(
            argv,
            cwd=cwd,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        child = Child(proc)
        children.append(child)
        return child

    yield _spawn
    for child in reversed(children):
        if child.proc.poll() is None:
            child.proc.terminate()
    for child in children:
        try:
            child.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            child.proc.kill()
            child.proc.wait(timeout=5)


@pytest.fixture
def start_sitl(spawn) -> Iterator:
    """Start `fleetmpc sitl` on the ideal test scenario and wait until it is ready."""

    def _start(*args: str, scenario: Path = IDEAL_SCENARIO) -> tuple[Child, re.Match]:
        argv = [sys.executable, "-m", "fleetmpc.cli", "sitl", "--scenario", str(scenario), *args]
        child = spawn(argv)
        return child, child.wait_line(r"fleetmpc sitl: .* ready: (?P<endpoints>.*)")

    yield _start
