"""A minimal Zenoh router run in-process: the hub of a compose deployment or of a test.

Clients connect with ``zenoh://HOST:PORT?mode=client``. The router listens only on the endpoint
it is given (loopback by default) and never scouts.

    python -m fleetmpc.protocol.zenoh_router --port 7447
"""

import argparse
import signal
import threading

import zenoh

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.zenoh_config import DEFAULT_HOST, DEFAULT_PORT, disable_scouting, endpoint

__all__ = ["main", "open_router", "router_config", "serve"]

EXIT_WITHOUT_TEARDOWN = True
"""A fleet process: `fleetmpc.cli.entry` skips the interpreter's teardown once `run` returns."""


def router_config(*, port: int, host: str = DEFAULT_HOST) -> zenoh.Config:
    """Config of a router listening on tcp/HOST:PORT, connecting nowhere, scouting off."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ConfigError("port", f"must be a port number, got {port!r}")
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["{endpoint(host, port)}"]')
    conf.insert_json5("connect/endpoints", "[]")
    return disable_scouting(conf)


def open_router(*, port: int, host: str = DEFAULT_HOST) -> zenoh.Session:
    """Open a router session and return it; the caller closes it (it is a context manager)."""
    zenoh.init_log_from_env_or("error")
    return zenoh.open(router_config(port=port, host=host))


def serve(port: int, *, host: str = DEFAULT_HOST, stop: threading.Event | None = None) -> None:
    """Run a router until SIGINT or SIGTERM (or until `stop` is set), then close it.

    Signal handlers are installed only when called from the main thread.
    """
    stop = stop if stop is not None else threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        with open_router(port=port, host=host):
            print(f"zenoh router listening on {endpoint(host, port)}", flush=True)
            while not stop.wait(0.5):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of `fleetmpc zenoh-router`."""
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to listen on")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port to listen on")


def run(args: argparse.Namespace) -> int:
    """Run a router on --host/--port until SIGINT or SIGTERM."""
    serve(args.port, host=args.host)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Command line: run a router on --host/--port until interrupted."""
    parser = argparse.ArgumentParser(prog="zenoh-router", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
