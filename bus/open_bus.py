"""Opening a PlanBus: by URL, or as a fleet process's command line asks for it.

``mem://NAME`` opens an `InMemoryPlanBus` on the hub called NAME of the runner's `MemoryHubs`;
``zenoh`` / ``zenoh://HOST:PORT?...`` (or a `ZenohOptions`) opens a `ZenohPlanBus`, see
`fleetmpc.protocol.zenoh_config` for the URL form. Zenoh is imported only when it is asked for.
"""

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHubs
from fleetmpc.bus.planbus import PlanBus
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import validate_fleet
from fleetmpc.protocol.messages import Message

if TYPE_CHECKING:
    import argparse

    from fleetmpc.protocol.zenoh_config import ZenohOptions
    from fleetmpc.scenario import Scenario

__all__ = ["add_bus_arguments", "open_fleet_bus", "open_plan_bus"]


def add_bus_arguments(parser: "argparse.ArgumentParser") -> None:
    """The Zenoh options every fleet process takes (`open_fleet_bus` reads them)."""
    zenoh = parser.add_mutually_exclusive_group()
    zenoh.add_argument(
        "--zenoh-config",
        type=Path,
        metavar="FILE",
        help="Zenoh config file (a secured fleet's: SECRETS/zenoh-<user>.json5)",
    )
    zenoh.add_argument(
        "--zenoh-connect",
        metavar="HOST:PORT[,...]",
        help="comma-separated router endpoints (client mode); default: a member of the"
        " fleet's peer mesh",
    )
    zenoh.add_argument(
        "--zenoh-secrets",
        type=Path,
        metavar="DIR",
        help="the run's secrets (`fleetmpc keys`): in the fleet's peer mesh, log in to the"
        " other members with this process's user and let in only the fleet's users",
    )
    parser.add_argument("--fleet", default=None, help="fleet name on Zenoh (default: scenario)")


def open_plan_bus(
    url_or_options: "str | ZenohOptions",
    *,
    fleet: str,
    vehicle_id: int | None,
    hubs: MemoryHubs | None = None,
    on_accept: Callable[[Message], None] | None = None,
) -> PlanBus:
    """Open the PlanBus a URL names: ``mem://NAME`` (needs `hubs`), ``zenoh[://...]``.

    A `fleetmpc.protocol.zenoh_config.ZenohOptions` may be given instead of a zenoh URL.
    `on_accept`: see `fleetmpc.bus.planbus`.
    """
    if isinstance(url_or_options, str) and url_or_options.startswith("mem://"):
        if hubs is None:
            raise ConfigError("hubs", "a mem:// plan bus needs the runner's MemoryHubs")
        name = url_or_options.removeprefix("mem://")
        validate_fleet(name, field="plan_bus_url")
        return InMemoryPlanBus(
            hubs.hub(name), fleet=fleet, vehicle_id=vehicle_id, on_accept=on_accept
        )
    from fleetmpc.bus.zenoh_bus import ZenohPlanBus
    from fleetmpc.protocol.zenoh_config import ZenohOptions

    if isinstance(url_or_options, ZenohOptions):
        options = url_or_options
    elif isinstance(url_or_options, str) and (
        url_or_options == "zenoh" or url_or_options.startswith("zenoh://")
    ):
        options = ZenohOptions.from_url(url_or_options)
    else:
        raise ConfigError(
            "plan_bus_url",
            f"unknown plan bus {url_or_options!r} (known: mem://NAME, zenoh, zenoh://HOST:PORT)",
        )
    return ZenohPlanBus(options, fleet=fleet, vehicle_id=vehicle_id, on_accept=on_accept)


def open_fleet_bus(
    args: "argparse.Namespace",
    scenario: "Scenario",
    *,
    sender_id: int,
    on_accept: Callable[[Message], None] | None = None,
) -> PlanBus:
    """The Zenoh plan bus of a fleet process, as its command line asks for it.

    `args` holds the options of `add_bus_arguments` (`fleetmpc.protocol.zenoh_config.
    options_from_args` says what they mean); the fleet name defaults to the scenario's, and
    `sender_id` is the bus identity, the peer-mesh member
    (`fleetmpc.protocol.zenoh_config.peer_mesh_index`) and, with ``--zenoh-secrets``, the user
    it logs in as (`fleetmpc.security.zenoh_access.zenoh_user`).
    """
    from fleetmpc.protocol.zenoh_config import MeshLogin, options_from_args, peer_mesh_index
    from fleetmpc.security.zenoh_access import zenoh_user
    from fleetmpc.security.zenoh_security import ZenohSecurity

    login = None
    if getattr(args, "zenoh_secrets", None) is not None:
        security = ZenohSecurity.load(args.zenoh_secrets, field="--zenoh-secrets")
        login = MeshLogin(
            user_config=str(security.client_config(zenoh_user(sender_id))),
            users_file=str(security.dictionary_file),
        )
    options = options_from_args(
        args.zenoh_config,
        args.zenoh_connect,
        host=scenario.network.host,
        base_port=scenario.network.zenoh_port,
        size=len(scenario.vehicles) + 2,
        member_index=peer_mesh_index(scenario.vehicle_ids, sender_id),
        login=login,
    )
    return open_plan_bus(
        options, fleet=args.fleet or scenario.name, vehicle_id=sender_id, on_accept=on_accept
    )
