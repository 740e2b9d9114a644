"""ZenohPlanBus: the PlanBus on eclipse-zenoh 1.x.

One session per bus, configured by `fleetmpc.protocol.zenoh_config.ZenohOptions` (explicit
endpoints, scouting off). The bus subscribes to the fleet's plan, status, target and epoch keys with
a callback (run on zenoh threads; the receive rules in `fleetmpc.onboard.planbus` hold a lock) and
ignores its own session's publications. `close` undeclares everything and closes the session: an
open session can hang interpreter exit.
"""

import contextlib
from collections.abc import Callable

import zenoh

from fleetmpc.onboard.faults import FaultLayer
from fleetmpc.onboard.planbus import PlanBus, PlanBusError
from fleetmpc.protocol.messages import Message
from fleetmpc.protocol.zenoh_config import ZenohOptions

__all__ = ["ZenohPlanBus"]


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
        try:
            for key in self._subscriptions():
                self._subscribers.append(
                    self._session.declare_subscriber(
                        key, self._on_sample, allowed_origin=zenoh.Locality.REMOTE
                    )
                )
            for key in self._keys.values():
                self._publishers[key] = self._session.declare_publisher(key)
        except zenoh.ZError as e:
            self._session.close()
            raise PlanBusError(f"cannot declare the fleet's keys: {e}") from None

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
