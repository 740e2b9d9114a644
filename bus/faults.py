"""Injected network faults: what a lossy, late or split network does to the plan bus.

A fault schedule lists faults, each active over a window of fleet time. Every bus of a faulty
run gets its own `FaultLayer`, which sits where payloads arrive, before the bus's receive rules
(`fleetmpc.bus.planbus`): the same code in the lockstep simulation (on the in-memory hub) and
in a live fleet (on Zenoh), so a fault does the same thing to both. A fault file is TOML:

    seed = 7                   # the faults' own random numbers (default: the run's seed)

    [[faults]]
    kind = "loss"              # loss | delay | duplicate | reorder | blackout | partition
    start_s = 20.0             # fleet time it starts [s] (default 0)
    duration_s = 10.0          # how long it lasts [s] (default: to the end of the run)
    vehicles = [2, 3]          # the vehicles it hits (default: all of them)
    probability = 0.3          # loss, duplicate, reorder: the share of messages hit

What each kind does to a message arriving at a vehicle it hits, while it is active:
- loss: drops it with `probability`;
- delay: holds it for `delay_s` plus a uniform jitter in [-`jitter_s`, `jitter_s`] (never less
  than nothing);
- duplicate: with `probability`, delivers it a second time right after the first;
- reorder: with `probability`, holds it back by up to `REORDER_HOLD_S`, so that later messages of
  its sender overtake it (the receive rules then drop it as out of order);
- blackout: the listed vehicles send and receive nothing: every message to them, and every
  message from them (plans and statuses, whose key names their sender), is dropped;
- partition: `groups = [[1, 2], [3, 4]]`; messages between vehicles of different groups are
  dropped (vehicles listed in no group form one more group together). `vehicles` does not apply.

A held message is delivered when the bus is next read at or after its release time (an agent
reads every period). The random numbers that decide a message's fate come from the schedule's
seed, the receiving vehicle's id and the message itself (its key, sequence number and stamp), so
a faulty run is reproducible, and the same message meets the same fate whatever order the
messages arrive in.
"""

import hashlib
import heapq
import math
import threading
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import KeyFormatError, parse_key
from fleetmpc.validate import in_range, positive

__all__ = [
    "FAULT_KINDS",
    "LINK_KINDS",
    "LinkFaults",
    "REORDER_HOLD_S",
    "Fault",
    "FaultLayer",
    "FaultSchedule",
    "load_faults",
    "parse_faults",
]

NETWORK_KINDS = ("loss", "delay", "duplicate", "reorder", "blackout", "partition")
PROCESS_KINDS = ("freeze", "kill", "restart", "clock_offset")
LINK_KINDS = ("link_loss", "link_blackout")
FAULT_KINDS = NETWORK_KINDS + PROCESS_KINDS + LINK_KINDS

REORDER_HOLD_S = 0.5
"""Longest hold of a reordered message [s]: long enough for a plan at 5 Hz to be overtaken."""

_KEYS = {
    "loss": {"probability"},
    "delay": {"delay_s", "jitter_s"},
    "duplicate": {"probability"},
    "reorder": {"probability"},
    "blackout": set(),
    "partition": {"groups"},
    "freeze": {"process"},
    "kill": {"process"},
    "restart": {"process"},
    "clock_offset": {"process", "offset_s"},
    "link_loss": {"probability"},
    "link_blackout": set(),
}
_COMMON = {"kind", "start_s", "duration_s", "vehicles"}


@dataclass(frozen=True)
class Fault:
    """One fault of a schedule (module docstring)."""

    kind: str
    start_s: float = 0.0
    duration_s: float = math.inf
    vehicles: tuple[int, ...] | None = None
    """The vehicles it hits; None: all of them."""
    probability: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    groups: tuple[tuple[int, ...], ...] = ()
    process: str = ""
    """The process a process fault hits (a name of `fleetmpc up`'s process list)."""
    offset_s: float = 0.0
    """clock_offset: how far the process's clock reads ahead of the fleet's [s] (host time)."""

    @property
    def network(self) -> bool:
        """True for a fault of the plan bus (not of a process)."""
        return self.kind in NETWORK_KINDS

    def active(self, t_ns: int) -> bool:
        """True at fleet time t_ns inside [start, start + duration) (whole nanoseconds)."""
        start_ns = round(self.start_s * 1e9)
        return start_ns <= t_ns and (
            math.isinf(self.duration_s) or t_ns < start_ns + round(self.duration_s * 1e9)
        )

    def hits(self, vehicle_id: int | None) -> bool:
        return vehicle_id is not None and (self.vehicles is None or vehicle_id in self.vehicles)

    def describe(self) -> str:
        """One line for a run's summary."""
        end = "the end" if math.isinf(self.duration_s) else f"{self.start_s + self.duration_s:g} s"
        who = "every vehicle" if self.vehicles is None else f"vehicles {list(self.vehicles)}"
        what = {
            "loss": f"{self.probability:.0%} loss",
            "delay": f"{self.delay_s * 1e3:g} ms delay ± {self.jitter_s * 1e3:g} ms",
            "duplicate": f"{self.probability:.0%} duplicated",
            "reorder": f"{self.probability:.0%} reordered",
            "blackout": "blackout",
            "partition": f"partition {[list(g) for g in self.groups]}",
            "freeze": "frozen (SIGSTOP)",
            "kill": "killed (SIGKILL)",
            "restart": "killed, then restarted",
            "clock_offset": f"clock {self.offset_s * 1e3:+g} ms",
            "link_loss": f"{self.probability:.0%} of the autopilot link's messages lost",
            "link_blackout": "autopilot link cut",
        }[self.kind]
        if self.kind == "partition":
            who = "the fleet"
        if self.kind in PROCESS_KINDS:
            who = self.process
            if self.kind == "kill":
                return f"{who} {what} at {self.start_s:g} s"
            if self.kind == "clock_offset":
                return f"{who} {what}, the whole run"
        return f"{what} for {who}, {self.start_s:g} s to {end}"


@dataclass(frozen=True)
class FaultSchedule:
    """The faults of a run and the seed of their random numbers (None: the run's)."""

    faults: tuple[Fault, ...]
    seed: int | None = None

    def seed_for(self, run_seed: int) -> int:
        """The seed of the faults' random numbers in a run seeded `run_seed`."""
        return run_seed if self.seed is None else self.seed


def _vehicle_list(field: str, value: Any, fleet: Sequence[int]) -> tuple[int, ...]:
    if not isinstance(value, list) or not value:
        raise ConfigError(field, f"must be a non-empty list of vehicle ids, got {value!r}")
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int) or v not in fleet:
            raise ConfigError(f"{field}[{i}]", f"is not a vehicle of the scenario ({list(fleet)})")
    if len(set(value)) != len(value):
        raise ConfigError(field, f"lists a vehicle twice: {value!r}")
    return tuple(value)


def _fault(
    table: Any,
    field: str,
    fleet: Sequence[int],
    processes: Sequence[str] | None,
    *,
    live_link: bool = False,
) -> Fault:
    """One fault table; `live_link`: an agent reads it (its link faults are its own)."""
    if not isinstance(table, dict):
        raise ConfigError(field, f"must be a table, got {table!r}")
    kind = table.get("kind")
    if not isinstance(kind, str) or kind not in _KEYS:
        raise ConfigError(f"{field}.kind", f"must be one of {', '.join(FAULT_KINDS)}, got {kind!r}")
    known = _known_keys(kind)
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(
            f"{field}.{unknown[0]}",
            f"unknown for a {kind} fault (known: {', '.join(sorted(known))})",
        )
    args: dict[str, Any] = {"kind": kind}
    args["start_s"] = positive(f"{field}.start_s", table.get("start_s", 0.0), allow_zero=True)
    if "duration_s" in table:
        args["duration_s"] = positive(f"{field}.duration_s", table["duration_s"])
    if "vehicles" in table:
        args["vehicles"] = _vehicle_list(f"{field}.vehicles", table["vehicles"], fleet)
    args |= _network_fields(kind, table, field, fleet)
    if kind in LINK_KINDS and processes is None and not live_link:
        raise ConfigError(
            f"{field}.kind",
            f"{kind} is an autopilot-link fault: only a live fleet (fleetmpc up) has it",
        )
    if kind in PROCESS_KINDS:
        args |= _process_fields(kind, table, field, processes)
    return Fault(**args)


def _known_keys(kind: str) -> set[str]:
    """The keys a fault table of `kind` may have."""
    known = _COMMON | _KEYS[kind]
    if kind == "partition" or kind in PROCESS_KINDS:
        known = known - {"vehicles"}
    if kind == "kill":
        known = known - {"duration_s"}
    if kind == "clock_offset":
        known = known - {"duration_s", "start_s"}
    return known


def _network_fields(kind: str, table: dict, field: str, fleet: Sequence[int]) -> dict[str, Any]:
    """The fields of a fault of messages or of the autopilot link: its probability (where its
    kind has one), a delay's delay and jitter, a partition's groups."""
    args: dict[str, Any] = {}
    if "probability" in _KEYS[kind]:
        if "probability" not in table:
            raise ConfigError(f"{field}.probability", f"a {kind} fault needs it (0 to 1)")
        args["probability"] = in_range(f"{field}.probability", table["probability"], 0.0, 1.0)
    if kind == "delay":
        if "delay_s" not in table:
            raise ConfigError(f"{field}.delay_s", "a delay fault needs it (seconds >= 0)")
        args["delay_s"] = positive(f"{field}.delay_s", table["delay_s"], allow_zero=True)
        args["jitter_s"] = positive(
            f"{field}.jitter_s", table.get("jitter_s", 0.0), allow_zero=True
        )
    if kind == "partition":
        groups = table.get("groups")
        if not isinstance(groups, list) or not groups:
            raise ConfigError(f"{field}.groups", f"must be a list of vehicle lists, got {groups!r}")
        parsed = [_vehicle_list(f"{field}.groups[{i}]", g, fleet) for i, g in enumerate(groups)]
        seen: set[int] = set()
        for i, g in enumerate(parsed):
            if seen & set(g):
                raise ConfigError(f"{field}.groups[{i}]", f"repeats vehicle {min(seen & set(g))}")
            seen |= set(g)
        args["groups"] = tuple(parsed)
    return args


def _process_fields(
    kind: str, table: dict, field: str, processes: Sequence[str] | None
) -> dict[str, Any]:
    """A process fault's process (one of the live fleet's `processes`) and clock offset."""
    if processes is None:
        raise ConfigError(
            f"{field}.kind",
            f"{kind} is a process fault: only a live fleet (fleetmpc up) has it",
        )
    name = table.get("process")
    if name not in processes:
        raise ConfigError(
            f"{field}.process",
            f"must be one of the fleet's processes, got {name!r} (known: {', '.join(processes)})",
        )
    if kind in ("freeze", "restart") and "duration_s" not in table:
        raise ConfigError(f"{field}.duration_s", f"a {kind} fault needs it (seconds > 0)")
    args: dict[str, Any] = {"process": name}
    if kind == "clock_offset":
        if not name.startswith("agent-"):
            raise ConfigError(f"{field}.process", f"a clock offset is an agent's, got {name!r}")
        if "offset_s" not in table:
            raise ConfigError(f"{field}.offset_s", "a clock_offset fault needs it (seconds)")
        args["offset_s"] = in_range(f"{field}.offset_s", table["offset_s"], -60.0, 60.0)
    return args


def parse_faults(
    doc: dict[str, Any],
    *,
    vehicle_ids: Sequence[int],
    processes: Sequence[str] | None = None,
    network_only: bool = False,
) -> FaultSchedule:
    """Validate a parsed fault file against the scenario's vehicle ids and, for a live fleet,
    its process names (without them a process fault is refused). `network_only`: leave the
    process faults out unread (an agent, given the file its launcher checked)."""
    unknown = sorted(set(doc) - {"seed", "faults"})
    if unknown:
        raise ConfigError(unknown[0], "unknown top-level key (known: faults, seed)")
    seed = doc.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        raise ConfigError("seed", f"must be a non-negative integer, got {seed!r}")
    tables = doc.get("faults")
    if not isinstance(tables, list) or not tables:
        raise ConfigError("faults", "must be a non-empty array of tables ([[faults]])")
    faults = tuple(
        _fault(t, f"faults[{i}]", vehicle_ids, processes, live_link=network_only)
        for i, t in enumerate(tables)
        if not (network_only and isinstance(t, dict) and t.get("kind") in PROCESS_KINDS)
    )
    return FaultSchedule(faults=faults, seed=seed)


def load_faults(
    path: str | Path,
    *,
    vehicle_ids: Sequence[int],
    processes: Sequence[str] | None = None,
    network_only: bool = False,
) -> FaultSchedule:
    """Read and validate a fault file (`parse_faults`); errors name the file and the field."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except OSError as e:
        raise ConfigError("--faults", f"cannot read {path}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ConfigError("--faults", f"{path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError("--faults", f"{path} is not valid TOML: {e}") from None
    try:
        return parse_faults(
            doc, vehicle_ids=vehicle_ids, processes=processes, network_only=network_only
        )
    except ConfigError as e:
        raise ConfigError(f"{path}: {e.field}", str(e).split(": ", 1)[1]) from None


def _sender(key: str) -> int | None:
    try:
        return parse_key(key).vehicle_id
    except KeyFormatError:
        return None


class FaultLayer:
    """The faults as vehicle `vehicle_id` receives: `arrive` each payload as it comes, `release`
    the held ones when the bus is read. `clock` gives fleet time [ns], None while it is not
    known (no fault applies then). Thread-safe: payloads may arrive on a transport's thread."""

    def __init__(
        self,
        schedule: FaultSchedule,
        *,
        vehicle_id: int,
        clock: Callable[[], int | None],
        seed: int,
    ) -> None:
        self.vehicle_id = vehicle_id
        self._faults = tuple(f for f in schedule.faults if f.network)
        self._clock = clock
        self._key = f"{schedule.seed_for(seed)}/{vehicle_id}".encode()
        """Keys the per-payload random numbers: another seed or vehicle, other draws."""
        self._lock = threading.Lock()
        self._held: list[tuple[int, int, str, bytes]] = []
        self._order = 0
        self.counts: dict[str, int] = {
            "lost": 0,
            "blacked_out": 0,
            "partitioned": 0,
            "delayed": 0,
            "duplicated": 0,
            "reordered": 0,
        }
        """What the layer did to the payloads that reached it, by effect."""

    def _group(self, fault: Fault, vehicle: int) -> int:
        for i, group in enumerate(fault.groups):
            if vehicle in group:
                return i
        return -1

    def _cut(self, fault: Fault, sender: int | None, draw: float) -> str | None:
        """Why `fault` stops a payload from `sender` reaching this vehicle, if it does."""
        if fault.kind == "blackout" and (fault.hits(self.vehicle_id) or fault.hits(sender)):
            return "blacked_out"
        if (
            fault.kind == "partition"
            and sender is not None
            and self._group(fault, sender) != self._group(fault, self.vehicle_id)
        ):
            return "partitioned"
        if fault.kind == "loss" and fault.hits(self.vehicle_id) and draw < fault.probability:
            return "lost"
        return None

    def _draws(self, key: str, payload: bytes, count: int) -> list[float]:
        """`count` uniform numbers in [0, 1) for one payload, from the layer's seed and the
        payload itself (its key, sequence number and stamp): the same message meets the same
        fate whatever order the messages arrive in."""
        digest = hashlib.blake2b(key.encode() + payload, key=self._key, digest_size=8).digest()
        return np.random.default_rng(int.from_bytes(digest)).random(count).tolist()

    def arrive(self, key: str, payload: bytes) -> list[tuple[str, bytes]]:
        """The payloads to deliver now for one that arrived (none, it, or it twice)."""
        now = self._clock()
        if now is None:
            return [(key, payload)]
        active = [f for f in self._faults if f.active(now)]
        if not active:
            return [(key, payload)]
        sender = _sender(key)
        draws = self._draws(key, payload, 2 * len(active))
        cut_draws, effect_draws, effects = draws[: len(active)], draws[len(active) :], []
        with self._lock:
            for fault, draw in zip(active, cut_draws, strict=True):
                cut = self._cut(fault, sender, draw)
                if cut is not None:
                    self.counts[cut] += 1
                    return []
            hold_ns, copies = 0, 1
            for fault, draw in zip(active, effect_draws, strict=True):
                if not fault.hits(self.vehicle_id):
                    continue
                if fault.kind == "delay":
                    jitter = fault.jitter_s * (2.0 * draw - 1.0)
                    hold_ns += max(0, round((fault.delay_s + jitter) * 1e9))
                    effects.append("delayed")
                elif fault.kind == "reorder" and draw < fault.probability:
                    hold_ns += round(REORDER_HOLD_S * draw / fault.probability * 1e9)
                    effects.append("reordered")
                elif fault.kind == "duplicate" and draw < fault.probability:
                    copies = 2
                    effects.append("duplicated")
            for effect in effects:
                self.counts[effect] += 1
            if hold_ns == 0:
                return [(key, payload)] * copies
            for _ in range(copies):
                heapq.heappush(self._held, (now + hold_ns, self._order, key, payload))
                self._order += 1
            return []

    def release(self) -> list[tuple[str, bytes]]:
        """The held payloads whose time has come, in the order they are due."""
        now = self._clock()
        out = []
        with self._lock:
            while self._held and (now is None or self._held[0][0] <= now):
                _, _, key, payload = heapq.heappop(self._held)
                out.append((key, payload))
        return out

    @property
    def held(self) -> int:
        """Payloads held back right now."""
        with self._lock:
            return len(self._held)


class LinkFaults:
    """The autopilot-link faults of vehicle `vehicle_id` (link_loss, link_blackout): `cut` says
    whether the MAVLink message at hand, either way, is lost. `clock` gives fleet time [ns],
    None while it is not known (nothing is cut then). Thread-safe."""

    def __init__(
        self,
        schedule: FaultSchedule,
        *,
        vehicle_id: int,
        clock: Callable[[], int | None],
        seed: int,
    ) -> None:
        self.vehicle_id = vehicle_id
        self._faults = tuple(f for f in schedule.faults if f.kind in LINK_KINDS)
        self._clock = clock
        self._rng = np.random.default_rng((schedule.seed_for(seed), vehicle_id, 1))
        self._lock = threading.Lock()
        self.counts = {"link_lost": 0, "link_blacked_out": 0}
        """Messages the link lost, by fault."""

    def cut(self) -> bool:
        """True if the message at hand is lost."""
        now = self._clock()
        if now is None:
            return False
        with self._lock:
            for fault in self._faults:
                if not (fault.active(now) and fault.hits(self.vehicle_id)):
                    continue
                if fault.kind == "link_blackout":
                    self.counts["link_blacked_out"] += 1
                    return True
                if self._rng.random() < fault.probability:
                    self.counts["link_lost"] += 1
                    return True
        return False
