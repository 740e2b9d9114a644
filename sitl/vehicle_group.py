"""Several simulated vehicles in one process, as ArduPilot's and PX4's multi-instance SITLs run.

Each vehicle is still its own `VehicleServer`: its own system id, sockets, ports, signing key,
plant and autopilot; nothing of one reaches another. What they share is the loop: one wait until
the earliest plant tick is due or until a socket of any vehicle is readable, then every vehicle
advances to the clock's time, and those with a readable socket handle their input. The plants
of one scenario tick at the same instants (every plant starts at time 0 with the scenario's
tick), so one wake-up serves them all: a fleet of N vehicles wakes the host 1/N as often as N
processes would, which is what a large fleet on few cores spends most on
(docs/design.md, "Waking").

A vehicle's handler failing is counted in that vehicle's summary and the loop goes on, as in a
process of its own; a vehicle whose process is frozen or killed takes the others with it, which
is why `fleetmpc up` groups vehicles only where separate processes would cost too much
(`fleetmpc.launch.fleet.auto_vehicles_per_sitl`) or when asked (`--vehicles-per-sitl`).
"""

import selectors
from collections.abc import Callable, Sequence

from fleetmpc.clock import Clock
from fleetmpc.sitl.vehicle_server import VehicleServer

__all__ = ["serve_vehicles"]

_MAX_WAIT_S = 0.05  # wall-clock bound on one wait, so a stop request is seen promptly


def serve_vehicles(
    servers: Sequence[VehicleServer], clock: Clock, should_stop: Callable[[], bool]
) -> None:
    """Serve every vehicle of `servers` in one loop until `should_stop()` is true."""
    with selectors.DefaultSelector() as selector:
        for server in servers:
            selector.register(server, selectors.EVENT_READ, server)
        while not should_stop():
            wait_ns = min(s.next_tick_ns for s in servers) - clock.now_ns()
            wait_s = min(clock.wall_seconds(wait_ns), _MAX_WAIT_S) if wait_ns > 0 else 0.0
            readable = {key.data for key, _ in selector.select(wait_s)}
            now_ns = clock.now_ns()
            for server in servers:
                server.serve(now_ns, read=server in readable)
