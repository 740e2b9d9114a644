"""A minimal Zenoh router run in-process: the hub of a compose deployment or of a test.

Clients connect with ``zenoh://HOST:PORT?mode=client``. The router listens only on the endpoint
it is given (loopback by default) and never scouts.

    python -m fleetmpc.protocol.zenoh_router --port 7447

With ``--security DIR`` (a directory of `fleetmpc.security.zenoh_security.make_zenoh_security`)
every session must log in as one of the fleet's users, the fleet's access list applies, and the
router listens on ``tls/HOST:PORT`` if the directory has TLS material; HOST and PORT default to
the directory's router address. Clients then connect with ``--zenoh-config DIR/zenoh-<user>.json5``.
"""

import argparse
import json
import signal
import threading
from pathlib import Path

import zenoh

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.zenoh_config import DEFAULT_HOST, DEFAULT_PORT, disable_scouting, endpoint
from fleetmpc.security.zenoh_security import ZenohSecurity, router_security_config

__all__ = ["main", "open_router", "router_config", "serve"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""


def router_config(
    *, port: int, host: str = DEFAULT_HOST, security: str | Path | None = None
) -> zenoh.Config:
    """Config of a router listening on tcp/HOST:PORT, connecting nowhere, scouting off.

    With `security` (a directory of `fleetmpc.security.zenoh_security.make_zenoh_security`):
    users and passwords, the fleet's access list, and tls/HOST:PORT if it has TLS material
    (`fleetmpc.security.zenoh_security.router_security_config`).
    """
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ConfigError("port", f"must be a port number, got {port!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["{endpoint(host, port)}"]')
    conf.insert_json5("connect/endpoints", "[]")
    if security is not None:
        router_security_config(conf, security)
    return disable_scouting(conf)


def open_router(
    *, port: int, host: str = DEFAULT_HOST, security: str | Path | None = None
) -> zenoh.Session:
    """Open a router session and return it; the caller closes it (it is a context manager).

    `security`: see `router_config`.
    """
    return _open(router_config(port=port, host=host, security=security))


def _open(conf: zenoh.Config) -> zenoh.Session:
    zenoh.init_log_from_env_or("error")
    return zenoh.open(conf)


def serve(
    port: int,
    *,
    host: str = DEFAULT_HOST,
    stop: threading.Event | None = None,
    security: str | Path | None = None,
) -> None:
    """Run a router until SIGINT or SIGTERM (or until `stop` is set), then close it.

    Signal handlers are installed only when called from the main thread. `security`: see
    `router_config`.
    """
    conf = router_config(port=port, host=host, security=security)
    listening = ", ".join(json.loads(conf.get_json("listen/endpoints")))
    stop = stop if stop is not None else threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        with _open(conf):
            print(f"zenoh router listening on {listening}", flush=True)
            while not stop.wait(0.5):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `fleetmpc zenoh-router`."""
    parser.add_argument(
        "--host", help=f"address to listen on (default: --security's router, else {DEFAULT_HOST})"
    )
    parser.add_argument(
        "--port",
        type=int,
        help=f"TCP port to listen on (default: --security's router, else {DEFAULT_PORT})",
    )
    parser.add_argument(
        "--security",
        type=Path,
        metavar="DIR",
        help="secure the bus with this directory of zenoh_security.make_zenoh_security: users,"
        " the fleet's access list, TLS",
    )


def run(args: argparse.Namespace) -> int:
    """Run a router on --host/--port (secured with --security) until SIGINT or SIGTERM."""
    host, port = DEFAULT_HOST, DEFAULT_PORT
    if args.security is not None:
        security = ZenohSecurity.load(args.security, field="--security")
        host, port = security.router_host, security.router_port
    host = args.host if args.host is not None else host
    port = args.port if args.port is not None else port
    serve(port, host=host, security=args.security)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Command line: run a router on --host/--port until interrupted."""
    parser = argparse.ArgumentParser(prog="zenoh-router", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
