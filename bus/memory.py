"""The in-process PlanBus: buses on a shared hub, with no threads and no sockets.

A `MemoryHub` is a broadcast medium matching keys the way Zenoh does for the fleet's keys; a
`MemoryHubs` registry (the runner's) names the hubs that ``mem://NAME`` URLs resolve to; an
`InMemoryPlanBus` is the PlanBus on one hub, with the receive rules of `fleetmpc.bus.planbus`.
Delivery is synchronous, or queued until `MemoryHub.flush` for a lockstep simulation.
"""

import functools
import threading
from collections.abc import Callable

from fleetmpc.bus.faults import FaultLayer
from fleetmpc.bus.planbus import PlanBus, decode_as
from fleetmpc.protocol.key_expressions import validate_fleet
from fleetmpc.protocol.messages import Message

__all__ = ["InMemoryPlanBus", "MemoryHub", "MemoryHubs"]


def _matches(pattern: str, key: str) -> bool:
    """Key-expression match for patterns whose only wildcard is a whole-chunk ``*``."""
    p, k = pattern.split("/"), key.split("/")
    return len(p) == len(k) and all(a == "*" and b or a == b for a, b in zip(p, k, strict=True))


class MemoryHub:
    """An in-process broadcast medium that several InMemoryPlanBus attach to.

    `put` delivers synchronously to every other attached bus whose subscriptions match, in
    attach order. With `deliver_immediately=False` payloads queue until `flush`, so a lockstep
    runner can let every agent of a tick see the same neighbour plans whatever their order.
    """

    def __init__(self, name: str = "default", *, deliver_immediately: bool = True) -> None:
        self.name = validate_fleet(name, field="hub name")
        self.deliver_immediately = deliver_immediately
        self._lock = threading.RLock()
        self._subscribers: list[tuple[tuple[str, ...], object, Callable[[str, bytes], None]]] = []
        self._queue: list[tuple[str, bytes, object]] = []
        self._routes: dict[tuple[str, int], list[Callable[[str, bytes], None]]] = {}
        """The callbacks a key reaches from an origin (by id), found once per key and origin."""
        self.decode = functools.lru_cache(maxsize=4096)(decode_as)
        """The buses' decoder, remembered by payload: every bus of the hub hears one payload
        object, which is decoded once, not once per bus (messages are immutable; a payload that
        does not decode is not remembered)."""

    def attach(
        self, patterns: tuple[str, ...], owner: object, callback: Callable[[str, bytes], None]
    ) -> None:
        """Deliver payloads on keys matching `patterns` to `callback`, except `owner`'s own."""
        with self._lock:
            self._subscribers.append((tuple(patterns), owner, callback))
            self._routes.clear()

    def detach(self, owner: object) -> None:
        with self._lock:
            self._subscribers = [s for s in self._subscribers if s[1] is not owner]
            self._routes.clear()

    def put(self, key: str, payload: bytes, *, origin: object = None) -> None:
        """Publish raw bytes on `key`; origin None (an outside sender) reaches every bus."""
        with self._lock:
            if not self.deliver_immediately:
                self._queue.append((key, bytes(payload), origin))
                return
        self.dispatch(key, bytes(payload), origin=origin)

    def flush(self) -> int:
        """Deliver every queued payload in publication order; return how many."""
        queue = self.take()
        for key, payload, origin in queue:
            self.dispatch(key, payload, origin=origin)
        return len(queue)

    def take(self) -> list[tuple[str, bytes, object]]:
        """Take the queued payloads (key, payload, origin) in publication order, undelivered:
        for a simulation that carries them to buses on other hubs (`dispatch` there)."""
        with self._lock:
            queue, self._queue = self._queue, []
        return queue

    @property
    def pending(self) -> int:
        with self._lock:
            return len(self._queue)

    def dispatch(self, key: str, payload: bytes, *, origin: object = None) -> None:
        """Deliver `payload` now to every attached bus whose subscriptions match `key`, except
        `origin` (None: a sender not on this hub)."""
        with self._lock:
            targets = self._routes.get((key, id(origin)))
            if targets is None:
                targets = self._routes[(key, id(origin))] = [
                    cb
                    for patterns, owner, cb in self._subscribers
                    if owner is not origin and any(_matches(p, key) for p in patterns)
                ]
        for callback in targets:
            callback(key, payload)


class MemoryHubs:
    """The runner's registry of named hubs, resolved by ``mem://NAME`` URLs."""

    def __init__(self, *, deliver_immediately: bool = True) -> None:
        self._deliver_immediately = deliver_immediately
        self._hubs: dict[str, MemoryHub] = {}
        self._lock = threading.Lock()

    def hub(self, name: str) -> MemoryHub:
        """The hub called `name`, created on first use."""
        with self._lock:
            if name not in self._hubs:
                self._hubs[name] = MemoryHub(name, deliver_immediately=self._deliver_immediately)
            return self._hubs[name]


class InMemoryPlanBus(PlanBus):
    """A PlanBus on a MemoryHub: no threads, no sockets, deterministic."""

    def __init__(
        self,
        hub: MemoryHub,
        *,
        fleet: str,
        vehicle_id: int | None,
        on_accept: Callable[[Message], None] | None = None,
        faults: FaultLayer | None = None,
    ) -> None:
        super().__init__(
            fleet=fleet,
            vehicle_id=vehicle_id,
            on_accept=on_accept,
            faults=faults,
            decoder=hub.decode,
        )
        self._hub = hub
        hub.attach(self._subscriptions(), self, self._deliver)

    def _send(self, key: str, payload: bytes) -> bool:
        self._hub.put(key, payload, origin=self)
        return True

    def _shutdown(self) -> None:
        self._hub.detach(self)
