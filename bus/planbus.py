"""PlanBus: how a vehicle exchanges assumed trajectories, status and target observations.

One small interface with two transports, chosen by URL with
`fleetmpc.bus.open_bus.open_plan_bus`:

- ``mem://NAME``: `fleetmpc.bus.memory.InMemoryPlanBus` on a hub of the runner's
  registry; synchronous and deterministic (lockstep simulation, tests);
- ``zenoh`` / ``zenoh://HOST:PORT?...``: `fleetmpc.bus.zenoh_bus.ZenohPlanBus`.

Receive-side rules, the same for every implementation: a payload on an unknown key, or that does
not decode, or whose sender differs from the id in its key, is rejected and counted by reason; a
message from this bus's own vehicle id is ignored; a message whose sequence number is not newer
than the latest accepted one of the same sender and kind is dropped and counted as a duplicate
(same seq) or out of order (older seq), unless its timestamp is newer, which means the sender
restarted (accepted and counted). Nothing raises into the caller's loop; transport callbacks may
run on other threads, so the receive state is guarded by a lock. Staleness is the caller's call:
`latest_plans(now_ns, max_age_ns)` returns what is fresh enough and nothing else. A ground
station that must see every message, not just the latest, passes `on_accept`: it is called with
each accepted message, on the transport's thread, outside the bus's lock. A bus given a
`fleetmpc.bus.faults.FaultLayer` passes every arriving payload through it first (injected
network faults); payloads it holds back reach the receive rules when the bus is next read.
"""

import functools
import math
import numbers
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Self

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.protocol.codec import DecodeError, decode, encode, plan_start
from fleetmpc.protocol.key_expressions import (
    KeyFormatError,
    all_plans_key,
    all_statuses_key,
    epoch_key,
    parse_key,
    plan_key,
    status_key,
    target_observation_key,
    validate_fleet,
)
from fleetmpc.protocol.messages import (
    GROUND_STATION_ID,
    MAX_SENDER_ID,
    MIN_SENDER_ID,
    TARGET_ID,
    FleetEpoch,
    Message,
    MessageKind,
    PlanMessage,
    PlanStatus,
    RejectReason,
    StatusMessage,
    TargetObservation,
    VehicleStatus,
)
from fleetmpc.protocol.plan import Plan

if TYPE_CHECKING:
    from fleetmpc.bus.faults import FaultLayer

__all__ = [
    "BusCounters",
    "PlanBus",
    "PlanBusClosedError",
    "PlanBusError",
]

_U32 = 2**32


class PlanBusError(FleetMpcError):
    """A plan bus could not be opened or used."""


class PlanBusClosedError(PlanBusError):
    """Publishing on a bus that has been closed."""


@dataclass(frozen=True)
class BusCounters:
    """A snapshot of a bus's counters.

    received == accepted + duplicates + out_of_order + own_ignored + filtered + rejected_total.
    """

    published: int = 0
    """Messages handed to the transport."""
    publish_errors: int = 0
    """Messages the transport refused to send."""
    received: int = 0
    """Payloads that arrived from other endpoints."""
    accepted: int = 0
    """Messages stored as the latest of their sender and kind."""
    duplicates: int = 0
    """Dropped: same sequence number as the latest accepted of that sender and kind."""
    out_of_order: int = 0
    """Dropped: older sequence number (and timestamp) than the latest accepted."""
    sender_restarts: int = 0
    """Accepted although their seq was not newer, because their timestamp was (sender restart)."""
    own_ignored: int = 0
    """Valid messages carrying this bus's own vehicle id (another process using the same id)."""
    listener_errors: int = 0
    """Accepted messages whose `on_accept` listener raised (a bug in the listener)."""
    filtered: int = 0
    """Valid plans dropped: their sender was beyond the bus's interest (`PlanBus.listen_near`)."""
    rejected: Mapping[RejectReason, int] = field(default_factory=lambda: MappingProxyType({}))
    """Rejected payloads by reason."""

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


def _check_vehicle_id(vehicle_id: int | None) -> int | None:
    if vehicle_id is None:
        return None
    if (
        isinstance(vehicle_id, bool)
        or not isinstance(vehicle_id, int)
        or not MIN_SENDER_ID <= vehicle_id <= MAX_SENDER_ID
    ):
        raise ConfigError(
            "vehicle_id", f"must be None or an integer in [1, 250], got {vehicle_id!r}"
        )
    return vehicle_id


def _check_ns(name: str, value: int, *, minimum: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ConfigError(name, f"must be an integer number of nanoseconds, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(name, f"must be >= {minimum}, got {value}")
    return int(value)


Decoder = Callable[[bytes, MessageKind], Message]
"""Decodes a payload expected to be of a kind (`fleetmpc.protocol.codec.decode`)."""


def decode_as(payload: bytes, kind: MessageKind) -> Message:
    """`decode` with the kind the payload's key announces."""
    return decode(payload, expect=kind)


class _Inbox:
    """Thread-safe receive side: validation, duplicate rules, latest message per sender."""

    def __init__(
        self,
        *,
        fleet: str,
        vehicle_id: int | None,
        on_accept: Callable[[Message], None] | None = None,
        decoder: Decoder = decode_as,
    ) -> None:
        self._fleet = fleet
        self._own = vehicle_id
        self._decoder = decoder
        self._on_accept = on_accept
        self._listener_errors = 0
        self._lock = threading.Lock()
        self._latest: dict[tuple[MessageKind, int], Message] = {}
        self._rejected: dict[RejectReason, int] = {}
        self._received = self._accepted = self._duplicates = 0
        self._out_of_order = self._restarts = self._own_ignored = self._filtered = 0
        self._interest: tuple[float, float, float, frozenset[int]] | None = None

    def listen_near(
        self, centre: tuple[float, float], radius_m: float, always: frozenset[int]
    ) -> None:
        """From now on, drop the valid plans of senders not in `always` that start farther than
        `radius_m` from `centre`, and forget such a sender's last plan."""
        self._interest = (float(centre[0]), float(centre[1]), float(radius_m), always)

    def _far(self, message: Message) -> bool:
        """True for a plan beyond the interest."""
        if message.kind != MessageKind.PLAN:
            return False
        return self._beyond(message.sender_id, *message.plan.states[0, :2].tolist())

    def _beyond(self, sender: int, x: float, y: float) -> bool:
        """True for a plan of `sender` starting at (x, y) beyond the interest (never for a
        sender always heard, nor before there is an interest)."""
        interest = self._interest
        if interest is None:
            return False
        cx, cy, radius, always = interest
        return sender not in always and math.hypot(x - cx, y - cy) > radius

    def _far_unread(self, key: str, payload: bytes) -> bool:
        """True for a plan that can be dropped without decoding it: framed as a plan of the
        sender its key names, starting beyond the interest, from a sender of whom nothing is
        held (the plan that would make this bus forget one is decoded first: "listen_near")."""
        if self._interest is None:
            return False
        try:
            parsed = _parse_key(key)
        except KeyFormatError:
            return False
        sender = parsed.vehicle_id
        if parsed.kind != MessageKind.PLAN or parsed.fleet != self._fleet or sender == self._own:
            return False
        start = plan_start(payload)
        if start is None or start[0] != sender:
            return False
        with self._lock:
            if (MessageKind.PLAN, sender) in self._latest:
                return False
        return self._beyond(*start)

    def receive(self, key: str, payload: bytes) -> None:
        """Handle one payload that arrived on `key`; never raises."""
        try:
            if self._far_unread(key, payload):
                with self._lock:
                    self._received += 1
                    self._filtered += 1
                return
            reason, message = self._check(key, payload)
        except Exception:  # a bug in the checks must not kill a transport thread
            reason, message = RejectReason.INTERNAL, None
        with self._lock:
            self._received += 1
            accepted = False
            if reason is not None:
                self._rejected[reason] = self._rejected.get(reason, 0) + 1
            elif message.sender_id == self._own:
                self._own_ignored += 1
            elif self._far(message):  # (only a valid plan, true to its key, is dropped so)
                self._filtered += 1
                self._latest.pop((MessageKind.PLAN, message.sender_id), None)
            else:
                accepted = self._store(message)
        if accepted and self._on_accept is not None:
            try:
                self._on_accept(message)
            except Exception:  # the listener's bug must not kill a transport thread
                with self._lock:
                    self._listener_errors += 1

    def _check(self, key: str, payload: bytes) -> tuple[RejectReason | None, Message | None]:
        try:
            parsed = _parse_key(key)
        except KeyFormatError:
            return RejectReason.KEY, None
        if parsed.fleet != self._fleet:
            return RejectReason.KEY, None
        try:
            if isinstance(payload, bytes):
                message = self._decoder(payload, parsed.kind)
            else:
                message = decode(payload, expect=parsed.kind)
        except DecodeError as e:
            return e.reason, None
        if parsed.vehicle_id is not None and message.sender_id != parsed.vehicle_id:
            return RejectReason.KEY_MISMATCH, None
        return None, message

    def _store(self, message: Message) -> bool:
        """Apply the sequence rules; True if stored. Called with the lock held."""
        slot = (message.kind, message.sender_id)
        latest = self._latest.get(slot)
        if latest is None or message.seq > latest.seq:
            pass
        elif message.stamp_ns > latest.stamp_ns:
            self._restarts += 1
        elif message.seq == latest.seq:
            self._duplicates += 1
            return False
        else:
            self._out_of_order += 1
            return False
        self._latest[slot] = message
        self._accepted += 1
        return True

    def latest(self, kind: MessageKind, now_ns: int, max_age_ns: int) -> dict[int, Message]:
        """Latest accepted message of `kind` per sender with |now - stamp| <= max_age."""
        now_ns = _check_ns("now_ns", now_ns)
        max_age_ns = _check_ns("max_age_ns", max_age_ns, minimum=0)
        with self._lock:
            items = sorted((s, m) for (k, s), m in self._latest.items() if k == kind)
        return {s: m for s, m in items if abs(now_ns - m.stamp_ns) <= max_age_ns}

    def snapshot(self, *, published: int, publish_errors: int) -> BusCounters:
        with self._lock:
            return BusCounters(
                published=published,
                publish_errors=publish_errors,
                received=self._received,
                accepted=self._accepted,
                duplicates=self._duplicates,
                out_of_order=self._out_of_order,
                sender_restarts=self._restarts,
                own_ignored=self._own_ignored,
                listener_errors=self._listener_errors,
                filtered=self._filtered,
                rejected=MappingProxyType(dict(sorted(self._rejected.items()))),
            )


_parse_key = functools.lru_cache(maxsize=4096)(parse_key)
"""`parse_key`, remembered: a fleet has a few keys, each heard every period."""


class PlanBus(ABC):
    """Publish this vehicle's plan, status and target observations; read the neighbours' latest.

    `vehicle_id` None makes a listen-only bus (e.g. a ground station) that cannot publish.
    A bus is a context manager; `close` is idempotent; what was received stays readable.
    """

    def __init__(
        self,
        *,
        fleet: str,
        vehicle_id: int | None,
        on_accept: Callable[[Message], None] | None = None,
        faults: "FaultLayer | None" = None,
        decoder: Decoder = decode_as,
    ) -> None:
        self._fleet = validate_fleet(fleet)
        self._vehicle_id = _check_vehicle_id(vehicle_id)
        self._inbox = _Inbox(
            fleet=self._fleet, vehicle_id=self._vehicle_id, on_accept=on_accept, decoder=decoder
        )
        self.faults = faults
        """The injected faults payloads pass through on arrival (None: none)."""
        self._send_lock = threading.Lock()
        self._seq = dict.fromkeys(MessageKind, 0)
        self._keys: dict[MessageKind, str] = {}
        if self._vehicle_id is not None:
            self._keys = {
                MessageKind.PLAN: plan_key(self._fleet, self._vehicle_id),
                MessageKind.STATUS: status_key(self._fleet, self._vehicle_id),
                MessageKind.TARGET_OBSERVATION: target_observation_key(self._fleet),
                MessageKind.FLEET_EPOCH: epoch_key(self._fleet),
            }
        self._published = 0
        self._publish_errors = 0
        self._closed = False

    # Transport, provided by implementations.
    @abstractmethod
    def _send(self, key: str, payload: bytes) -> bool:
        """Send `payload` on `key`; False if the transport refused (never raises)."""

    @abstractmethod
    def _shutdown(self) -> None:
        """Release the transport; called once."""

    def _deliver(self, key: str, payload: bytes) -> None:
        """Hand a payload that arrived on `key` to the receive rules (any thread), through the
        injected faults if there are any."""
        arrived = [(key, payload)] if self.faults is None else self.faults.arrive(key, payload)
        for k, p in arrived:
            self._inbox.receive(k, p)

    def _pull(self) -> None:
        """Hand what the transport queued for the reader to `_deliver` (a transport that does not
        queue delivers as payloads arrive, and has nothing to do here)."""
        return

    def _release_held(self) -> None:
        """Before a read: take what the transport queued, then hand the payloads the injected
        faults held back and are now due to the receive rules."""
        self._pull()
        if self.faults is not None:
            for k, p in self.faults.release():
                self._inbox.receive(k, p)

    def _subscriptions(self) -> tuple[str, ...]:
        """What the bus hears: plans, the target, the epoch, and, on a ground station's bus (or
        a listen-only one), the vehicles' statuses, which no agent reads (in a fleet of N they
        are half of what each agent would otherwise decode). The target's bus hears only the
        epoch (the secured bus's access list allows it nothing else)."""
        f = self._fleet
        if self._vehicle_id == TARGET_ID:
            return (epoch_key(f),)
        keys = (all_plans_key(f), target_observation_key(f), epoch_key(f))
        if self._vehicle_id in (None, GROUND_STATION_ID):
            return (*keys, all_statuses_key(f))
        return keys

    @property
    def fleet(self) -> str:
        return self._fleet

    @property
    def vehicle_id(self) -> int | None:
        return self._vehicle_id

    @property
    def closed(self) -> bool:
        return self._closed

    def _publish(self, kind: MessageKind, make: Callable[[int], Message]) -> None:
        if self._vehicle_id is None:
            raise ConfigError("vehicle_id", "a listen-only bus (vehicle_id None) cannot publish")
        with self._send_lock:
            if self._closed:
                raise PlanBusClosedError(f"bus of vehicle {self._vehicle_id} is closed")
            payload = encode(make(self._seq[kind]))
            self._seq[kind] = (self._seq[kind] + 1) % _U32
            if self._send(self._keys[kind], payload):
                self._published += 1
            else:
                self._publish_errors += 1

    def publish_plan(self, plan: Plan, status: PlanStatus | None = None) -> None:
        """Broadcast this vehicle's assumed trajectory (ConfigError if it is invalid)."""
        if self._vehicle_id is not None and plan.vehicle_id != self._vehicle_id:
            raise ConfigError(
                "plan.vehicle_id", f"is {plan.vehicle_id}, this bus is vehicle {self._vehicle_id}"
            )
        status = PlanStatus() if status is None else status

        def make(seq: int) -> Message:
            return PlanMessage(seq=seq, plan=plan, status=status)

        self._publish(MessageKind.PLAN, make)

    def publish_status(self, status: VehicleStatus, *, stamp_ns: int) -> None:
        """Broadcast this vehicle's status at simulated time `stamp_ns`."""

        def make(seq: int) -> Message:
            return StatusMessage(
                sender_id=self._vehicle_id, seq=seq, stamp_ns=stamp_ns, status=status
            )

        self._publish(MessageKind.STATUS, make)

    def publish_target(
        self,
        *,
        stamp_ns: int,
        north_m: float,
        east_m: float,
        noise_std_m: float = 0.0,
        velocity_m_s: tuple[float, float] | None = None,
    ) -> None:
        """Broadcast an observation of the target, sent as this bus's vehicle id."""

        def make(seq: int) -> Message:
            return TargetObservation(
                sender_id=self._vehicle_id,
                seq=seq,
                stamp_ns=stamp_ns,
                north_m=north_m,
                east_m=east_m,
                noise_std_m=noise_std_m,
                velocity_m_s=velocity_m_s,
            )

        self._publish(MessageKind.TARGET_OBSERVATION, make)

    def publish_epoch(self, *, epoch_ns: int, speed: float) -> None:
        """Announce the fleet's epoch (wall-clock ns of fleet time 0) and speed."""

        def make(seq: int) -> Message:
            return FleetEpoch(sender_id=self._vehicle_id, seq=seq, epoch_ns=epoch_ns, speed=speed)

        self._publish(MessageKind.FLEET_EPOCH, make)

    def latest_epoch(self) -> FleetEpoch | None:
        """The newest epoch announcement (any sender), or None before the first."""
        self._release_held()
        announced = self._inbox.latest(MessageKind.FLEET_EPOCH, 0, 0)
        return max(announced.values(), key=lambda m: (m.seq, -m.sender_id), default=None)

    def latest_plan_messages(self, now_ns: int, max_age_ns: int) -> dict[int, PlanMessage]:
        """Latest accepted plan message per neighbour, if |now_ns - stamp| <= max_age_ns."""
        self._release_held()
        return self._inbox.latest(MessageKind.PLAN, now_ns, max_age_ns)

    def listen_near(
        self, centre: tuple[float, float], radius_m: float, always: frozenset[int] = frozenset()
    ) -> None:
        """Subscribe by distance: from now on the plans of vehicles (other than those in
        `always`) that start farther than `radius_m` from `centre` are dropped (counted as
        `filtered`, never stored), and such a vehicle's last plan is forgotten. An agent calls
        it every period with where its vehicle is, so that what it holds and reads grows with
        its neighbourhood, not with the fleet. A far plan from a vehicle of which nothing is
        held is dropped unread (its first position read from its bytes, `plan_start`), so that
        a far vehicle costs the agent a look at a few bytes, not a decode; only a plan that
        decodes and matches its key makes a vehicle forget (a forged far payload cannot erase
        a neighbour)."""
        self._inbox.listen_near(centre, radius_m, always)

    def latest_plans(self, now_ns: int, max_age_ns: int) -> dict[int, Plan]:
        """Latest accepted plan per neighbour id whose age is at most `max_age_ns`.

        Age is `now_ns - plan.stamp_ns` in simulated time; a plan stamped more than
        `max_age_ns` in the future is left out as well. Plans' arrays are read-only.
        """
        return {i: m.plan for i, m in self.latest_plan_messages(now_ns, max_age_ns).items()}

    def latest_statuses(self, now_ns: int, max_age_ns: int) -> dict[int, StatusMessage]:
        """Latest accepted status per vehicle id, with the same age rule as `latest_plans`."""
        self._release_held()
        return self._inbox.latest(MessageKind.STATUS, now_ns, max_age_ns)

    def latest_target(self, now_ns: int, max_age_ns: int) -> TargetObservation | None:
        """The newest target observation (any sender) within `max_age_ns`, or None."""
        self._release_held()
        fresh = self._inbox.latest(MessageKind.TARGET_OBSERVATION, now_ns, max_age_ns)
        return max(fresh.values(), key=lambda m: (m.stamp_ns, -m.sender_id), default=None)

    def counters(self) -> BusCounters:
        """A snapshot of the counters (of what has reached the bus until now)."""
        self._release_held()
        with self._send_lock:
            published, errors = self._published, self._publish_errors
        return self._inbox.snapshot(published=published, publish_errors=errors)

    def close(self) -> None:
        """Release the transport; idempotent. Received messages stay readable."""
        with self._send_lock:
            if self._closed:
                return
            self._closed = True
        self._shutdown()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()
