"""Helpers shared by the tests: polling, free loopback ports and supervised child processes.

Importable from any test module as ``helpers`` (the tests folder is on the import path through
its conftest). `ProcessGroup` is also the `processes` fixture of ``tests/conftest.py``.
"""

import contextlib
import os
import random
import re
import signal
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from fleetmpc.network import SITL_GCS_LOCAL_BASE_PORT, SITL_OFFBOARD_LOCAL_BASE_PORT, Network

__all__ = [
    "ROOT",
    "Child",
    "ProcessGroup",
    "free_port",
    "free_port_block",
    "live_processes_naming",
    "port_is_free",
    "scenario_on_free_ports",
    "wait_until",
]

ROOT = Path(__file__).resolve().parents[1]
"""The repository (children run with it as their working directory)."""

_EPHEMERAL_FLOOR = 32768
"""Linux's default lowest ephemeral port; blocks are picked below it."""


def wait_until(
    predicate: Callable[[], bool],
    *,
    timeout_s: float = 5.0,
    interval_s: float = 0.02,
    tick: Callable[[], None] = lambda: None,
) -> bool:
    """Poll `predicate` (calling `tick` before each poll) until it holds or `timeout_s` passes.

    Returns the predicate's last value, so ``assert wait_until(...)`` reads as the condition.
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        tick()
        if predicate():
            return True
        time.sleep(interval_s)
    return bool(predicate())


def port_is_free(port: int, kind: int = socket.SOCK_DGRAM) -> bool:
    """True if `port` can be bound on 127.0.0.1 for `kind` (SOCK_DGRAM or SOCK_STREAM) now."""
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port the kernel had free on 127.0.0.1 a moment ago (from the ephemeral range)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ephemeral_floor() -> int:
    try:
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return _EPHEMERAL_FLOOR
    return low if low > 20000 else _EPHEMERAL_FLOOR


def free_port_block(
    offsets: Iterable[int] = (0,),
    *,
    kinds: Sequence[int] = (socket.SOCK_DGRAM,),
    avoid: Iterable[int] = (),
) -> int:
    """A base port b such that b + o is free for every offset o and every socket kind, and
    none of them is in `avoid` (ports already handed out for something else).

    Picked at random below the kernel's ephemeral range, so ports handed out to other sockets
    bound to port 0 (a colleague's test, a SITL's "any port") cannot take it in the meantime.
    """
    offsets, avoid = tuple(offsets), set(avoid)
    top = _ephemeral_floor() - max(offsets) - 1
    for _ in range(500):
        base = random.randrange(10000, top)
        if avoid.isdisjoint(base + o for o in offsets) and all(
            port_is_free(base + o, kind) for o in offsets for kind in kinds
        ):
            return base
    raise AssertionError(f"no free block of ports at offsets {offsets}")


def live_processes_naming(text: str) -> list[tuple[int, str]]:
    """(pid, command line) of every live (non-zombie) process whose command line contains `text`.

    Name a file unique to the test (e.g. a scenario copy in tmp_path) in every child's command
    line, and this finds whatever is left of them, grandchildren included.
    """
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue
        if text in cmdline and state != "Z":
            found.append((int(entry.name), cmdline.strip()))
    return found


def fly_up(scenario: Path, run_dir: Path, *, speed: float, timeout_s: float, cwd: Path):
    """`fleetmpc up SCENARIO` headless and quiet into `run_dir`, to its end: the finished
    process (its output captured)."""
    argv = [
        sys.executable, "-m", "fleetmpc.cli", "up", str(scenario), "--speed", f"{speed:g}",
        "--viewer", "none", "--quiet", "--run-dir", str(run_dir),
    ]  # fmt: skip
    return subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=timeout_s)


def scenario_on_free_ports(source: Path, dest: Path) -> Path:
    """Write `source` (a scenario without a [network] table) to `dest` with free loopback ports.

    Every port the fleet's processes use is free when this returns: the router's (or the N + 2
    of the default peer mesh, `fleetmpc.protocol.zenoh_config.peer_mesh_index`), the ground-station
    port, each vehicle's offboard port and ArduPilot TCP port, and the ports the PX4-profile
    SITLs bind (they move with the network's, see `fleetmpc.sitl.cli`), for vehicle ids 1..N.
    Returns `dest`.
    """
    text = Path(source).read_text()
    doc = tomllib.loads(text)
    if "network" in doc:
        raise ValueError(f"{source} has a [network] table already")
    if "vehicles" in doc:
        n = max(v["id"] for v in doc["vehicles"])
    else:  # (a pattern: vehicles 1..count)
        n = doc["formation"]["pattern"]["count"]
    px4 = Network()
    offboard_bound = SITL_OFFBOARD_LOCAL_BASE_PORT - px4.offboard_base_port
    gcs_bound = SITL_GCS_LOCAL_BASE_PORT - px4.gcs_port
    udp, tcp = (socket.SOCK_DGRAM,), (socket.SOCK_STREAM,)
    offboard_offsets = [*range(n), *(offboard_bound + i for i in range(n))]
    offboard = free_port_block(offboard_offsets, kinds=udp)
    network = {
        "offboard_base_port": offboard,
        "gcs_port": free_port_block(
            [0, *(gcs_bound + i for i in range(n))],
            kinds=udp,
            avoid=[offboard + o for o in offboard_offsets],
        ),
        "ardupilot_tcp_base_port": free_port_block([10 * i for i in range(n)], kinds=tcp),
        "zenoh_port": free_port_block(range(n + 2), kinds=tcp),
    }
    table = "\n".join(f"{k} = {v}" for k, v in network.items())
    Path(dest).write_text(f"{text}\n[network]\n{table}\n")
    return Path(dest)


@dataclass
class Child:
    """One child process; its stdout and stderr go to ``<log_dir>/<name>.out`` and ``.err``."""

    name: str
    argv: tuple[str, ...]
    proc: subprocess.Popen
    out_path: Path
    err_path: Path

    @property
    def pid(self) -> int:
        return self.proc.pid

    def out(self) -> str:
        """Everything the child wrote to stdout so far."""
        return self.out_path.read_text(errors="replace")

    def err(self) -> str:
        """Everything the child wrote to stderr so far."""
        return self.err_path.read_text(errors="replace")

    def tail(self, lines: int = 30) -> str:
        """The last lines of both streams, for assertion messages."""
        text = []
        for label, body in (("stdout", self.out()), ("stderr", self.err())):
            text.append(f"--- {self.name} {label}:\n" + "\n".join(body.splitlines()[-lines:]))
        return "\n".join(text)

    def wait_for(
        self, pattern: str, *, stream: str = "out", timeout_s: float = 20.0
    ) -> re.Match[str]:
        """Wait until a line of `stream` ("out" or "err") matches the regex `pattern`."""
        regex = re.compile(pattern)
        read = self.out if stream == "out" else self.err
        deadline = time.monotonic() + timeout_s
        while True:
            match = regex.search(read())
            if match:
                return match
            if self.proc.poll() is not None:
                match = regex.search(read())
                if match:
                    return match
                raise AssertionError(
                    f"{self.name} exited ({self.proc.returncode}) before printing "
                    f"{pattern!r}\n{self.tail()}"
                )
            if time.monotonic() > deadline:
                raise AssertionError(f"{self.name} did not print {pattern!r}\n{self.tail()}")
            time.sleep(0.05)


class ProcessGroup:
    """Children started by one test, stopped by PID: SIGTERM first, SIGKILL after a grace time.

    Use it through the `processes` fixture, whose finalizer calls `stop_all`, so nothing a test
    started outlives it, also when the test fails.
    """

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[str, Child] = {}

    def start(self, name: str, argv: Sequence[str], *, env: dict[str, str] | None = None) -> Child:
        """Start `argv` (a full command line) in the repository as child `name`."""
        if name in self.children:
            raise ValueError(f"a child called {name!r} was already started")
        out_path, err_path = self.log_dir / f"{name}.out", self.log_dir / f"{name}.err"
        with open(out_path, "w") as out, open(err_path, "w") as err:
            proc = subprocess.Popen(
                list(argv),
                stdout=out,
                stderr=err,
                stdin=subprocess.DEVNULL,
                cwd=ROOT,
                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            )
        child = Child(name, tuple(argv), proc, out_path, err_path)
        self.children[name] = child
        return child

    def fleetmpc(self, name: str, *args: str, env: dict[str, str] | None = None) -> Child:
        """Start ``fleetmpc ARGS...`` (this interpreter's ``-m fleetmpc.cli``) as child `name`."""
        return self.start(name, [sys.executable, "-m", "fleetmpc.cli", *args], env=env)

    def __getitem__(self, name: str) -> Child:
        return self.children[name]

    def kill(self, name: str) -> None:
        """SIGKILL child `name` by its PID (no clean-up in the child) and reap it."""
        child = self.children[name]
        if child.proc.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
        child.proc.wait(timeout=10.0)

    def stop(self, *names: str, timeout_s: float = 5.0) -> dict[str, int | None]:
        """SIGTERM the named children together, wait up to `timeout_s`, then SIGKILL the rest.

        Returns their exit codes by name (None for a child that had to be killed).
        """
        running = [self.children[n] for n in names if self.children[n].proc.poll() is None]
        for child in running:
            os.kill(child.pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        killed = set()
        for child in running:
            try:
                child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.kill(child.pid, signal.SIGKILL)
                child.proc.wait(timeout=10.0)
                killed.add(child.name)
        return {n: None if n in killed else self.children[n].proc.returncode for n in names}

    def stop_all(self, *, timeout_s: float = 5.0) -> dict[str, int | None]:
        """Stop every child still running (see `stop`); every child's exit code by name."""
        return self.stop(*self.children, timeout_s=timeout_s)


@contextlib.contextmanager
def router_process(*args: str) -> Iterator[subprocess.Popen]:
    """`fleetmpc zenoh-router ARGS` as a child process (stdout and stderr piped); killed and its
    pipes closed on leaving, whatever happened."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "fleetmpc.protocol.zenoh_router", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()
