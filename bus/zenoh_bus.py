"""ZenohPlanBus: the PlanBus on eclipse-zenoh 1.x.

One session per bus, configured by `fleetmpc.protocol.zenoh_config.ZenohOptions` (explicit
endpoints, scouting off). The bus subscribes to the fleet's plan, status, target and epoch keys and
ignores its own session's publications. How samples reach the receive rules of
`fleetmpc.bus.planbus` depends on who reads them:

- a bus with `on_accept` (a ground station, which must see every message as it comes) takes each
  sample in a callback, on a zenoh thread (the receive rules hold a lock);
- any other bus (an agent's, the target's) reads only the latest messages, once a period: its
  samples wait in a ring of `QUEUED_SAMPLES` per subscription, in zenoh, and the reader takes
  them all when it reads. A Python thread woken for every sample (in a fleet of 25 at 5 Hz, 120
  plans a second) cost an agent more than its controller did; the ring costs no wake-up at all
  (docs/design.md, "Waking"). A reader that falls so far behind that a ring fills loses the
  oldest samples, which newer ones of the same senders supersede.

`close` undeclares everything and closes the session: an open session can hang interpreter exit.
"""

import contextlib
from collections.abc import Callable

import zenoh

from fleetmpc.bus.faults import FaultLayer
from fleetmpc.bus.planbus import PlanBus, PlanBusError
from fleetmpc.protocol.messages import Message
from fleetmpc.protocol.zenoh_config import ZenohOptions

__all__ = ["QUEUED_SAMPLES", "ZenohPlanBus"]

QUEUED_SAMPLES = 2048
"""Samples a subscription of a bus without `on_accept` holds for its reader: several seconds of
a hundred vehicles' plans at 5 Hz, so a reader stalled that long loses none."""


class ZenohPlanBus(PlanBus):
    """A PlanBus over a Zenoh session."""

    def __init__(
        self,
        options: ZenohOptions,
        *,
        fleet: str,
        vehicle_id: int | None,
        on_accept: Callable[[Message], None] | None = None,
        faults: FaultLayer | None = None,
    ) -> None:
        super().__init__(fleet=fleet, vehicle_id=vehicle_id, on_accept=on_accept, faults=faults)
        self.options = options
        config = options.to_config()
        zenoh.init_log_from_env_or("error")
        try:
            self._session = zenoh.open(config)
        except zenoh.ZError as e:
            raise PlanBusError(f"cannot open a zenoh session with {options}: {e}") from None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._subscribers: list[zenoh.Subscriber] = []
        self._queued = on_accept is None
        try:
            for key in self._subscriptions():
                handler = (
                    zenoh.handlers.RingChannel(QUEUED_SAMPLES) if self._queued else self._on_sample
                )
                self._subscribers.append(
                    self._session.declare_subscriber(
                        key, handler, allowed_origin=zenoh.Locality.REMOTE
                    )
                )
            for key in self._keys.values():
                self._publishers[key] = self._session.declare_publisher(key)
        except zenoh.ZError as e:
            self._session.close()
            raise PlanBusError(f"cannot declare the fleet's keys: {e}") from None

    def _pull(self) -> None:
        if not self._queued or self.closed:
            return
        for subscriber in self._subscribers:
            try:
                while (sample := subscriber.try_recv()) is not None:
                    self._on_sample(sample)
            except zenoh.ZError:  # (undeclared meanwhile)
                continue

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
        except Exception:  # never raise into a zenoh thread
            key, payload = "", b""
        self._deliver(key, payload)

    def _send(self, key: str, payload: bytes) -> bool:
        try:
            self._publishers[key].put(payload)
        except zenoh.ZError:
            return False
        return True

    def _shutdown(self) -> None:
        for entity in (*self._subscribers, *self._publishers.values()):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self._session.close()
