"""A local Rerun viewer for a run, started with its usage analytics off.

The Rerun viewer reports usage analytics unless told not to. A viewer fleetmpc starts (``--viewer
spawn``, the ``spawn:`` telemetry sink) runs with a configuration directory of its own in which
``rerun analytics disable`` has been run, so it sends nothing; the user's own Rerun settings are
left as they are. It listens on 127.0.0.1 and, like the SDK's own spawn, outlives the run: it is
the user's window.
"""

import os
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from fleetmpc.errors import FleetMpcError

__all__ = ["DEFAULT_PORT", "rerun_binary", "spawn_viewer"]

DEFAULT_PORT = 9876
"""The viewer's gRPC port (Rerun's default)."""

_START_TIMEOUT_S = 20.0


def rerun_binary() -> Path:
    """The Rerun viewer executable that rerun-sdk ships (not the `rerun` wrapper script)."""
    import rerun_cli

    return Path(rerun_cli.__file__).parent / "rerun"


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def spawn_viewer(*, port: int = DEFAULT_PORT) -> str:
    """Start a viewer on 127.0.0.1:`port` (or use the one already there); its gRPC URL."""
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    if _listening(port):
        return url
    config = Path(tempfile.mkdtemp(prefix="fleetmpc-viewer-"))
    env = {**os.environ, "XDG_CONFIG_HOME": str(config)}
    binary = str(rerun_binary())
    done = subprocess.run(
        [binary, "analytics", "disable"], env=env, capture_output=True, text=True, timeout=30
    )
    if done.returncode != 0:
        raise FleetMpcError(f"rerun analytics disable failed: {done.stderr.strip()}")
    subprocess.Popen(
        [binary, "--port", str(port), "--bind", "127.0.0.1"],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # the user's window: not stopped with the run
    )
    deadline = time.monotonic() + _START_TIMEOUT_S
    while not _listening(port):
        if time.monotonic() > deadline:
            raise FleetMpcError(f"the Rerun viewer did not listen on port {port} in time")
        time.sleep(0.1)
    return url
