"""`fleetmpc agent` as a process: an epoch announced at another speed is exit code 2."""

import json
import socket
import time

from helpers import free_port_block

from fleetmpc.bus.open_bus import open_plan_bus
from fleetmpc.protocol.messages import GROUND_STATION_ID
from fleetmpc.protocol.zenoh_router import open_router

IDEAL = "tests/sitl/data/ideal.toml"


def test_an_epoch_at_another_speed_ends_the_agent_with_code_2(processes) -> None:
    offboard = free_port_block([0], kinds=(socket.SOCK_DGRAM,))
    router = free_port_block([0], kinds=(socket.SOCK_STREAM,))
    processes.fleetmpc(
        "sitl", "sitl", "--scenario", IDEAL, "--vehicle", "1", "--speed", "4",
        "--offboard-port", str(offboard), "--offboard-local-port", "0", "--gcs-port", "0",
    ).wait_for("ready")  # fmt: skip
    with (
        open_router(port=router),
        open_plan_bus(
            f"zenoh://127.0.0.1:{router}?mode=client", fleet="speeds", vehicle_id=GROUND_STATION_ID
        ) as gcs,
    ):
        agent = processes.fleetmpc(
            "agent", "agent", "--scenario", IDEAL, "--vehicle", "1",
            "--mavlink", f"udpin:127.0.0.1:{offboard}", "--zenoh-connect", f"127.0.0.1:{router}",
            "--fleet", "speeds", "--wait-epoch", "--speed", "4",
        )  # fmt: skip
        deadline = time.monotonic() + 60.0
        while agent.proc.poll() is None and time.monotonic() < deadline:
            gcs.publish_epoch(epoch_ns=time.time_ns() + 1_000_000_000, speed=2.0)
            time.sleep(0.2)
    assert agent.proc.wait(timeout=10.0) == 2, agent.tail()
    err = agent.err()
    assert "error: speed: the fleet epoch is announced at x2, this process runs at x4" in err, err
    assert "Traceback" not in err
    summary = json.loads(agent.out().strip().splitlines()[-1])
    assert summary["failure"].startswith("speed: ") and summary["steps"] == 0, summary
    assert summary["epoch_ns"] is None
