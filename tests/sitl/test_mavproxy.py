"""MAVProxy, run headless, routes clients to the simulated vehicle; the flows still work."""

import asyncio
import math
import sys
from pathlib import Path

import pytest
from mavsdk.asyncio.plugins.telemetry import FlightMode
from mavsdk_flow import FORWARD_M_S, YAWSPEED_DEG_S, mavsdk_flight
from sim_client import SimClient, fly_offboard, free_port, horizontal_speed, wait_hold_after_stop

from fleetmpc.protocol.mavlink_setpoint import Frame, encode_setpoint

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"


def test_mavproxy_routes_pymavlink_and_mavsdk_clients(start_sitl, spawn, tmp_path):
    master_port, mavsdk_port = free_port(), free_port()
    client = SimClient.listen_udp(target_system=1)
    try:
        sitl, _ = start_sitl(
            "--vehicle", "1", "--offboard-port", str(master_port), "--offboard-local-port", "0",
            "--gcs-port", "0",
        )  # fmt: skip
        spawn(
            [
                sys.executable,
                str(MAVPROXY),
                f"--master=udpin:127.0.0.1:{master_port}",
                f"--out=udpout:127.0.0.1:{client.port}",
                f"--out=udpout:127.0.0.1:{mavsdk_port}",
                "--daemon",
                "--non-interactive",
                "--default-modules=",
                f"--state-basedir={tmp_path}",
            ],
            cwd=tmp_path,
        )
        # The OFFBOARD rules through the router: denied, accepted after 1 s, HOLD on loss.
        fly_offboard(client, encode_setpoint(1.0, 0.1, frame=Frame.BODY_NED))
        client.sleep_sim(1.0)
        assert horizontal_speed(client.wait_type("LOCAL_POSITION_NED")) == pytest.approx(1.0)
        hold_after_s = wait_hold_after_stop(client)
        print(f"through MAVProxy: HOLD {hold_after_s:.3f} s (simulated) after the last setpoint")
        assert 1.0 <= hold_after_s <= 1.1

        # MAVSDK through the same router.
        result = asyncio.run(mavsdk_flight(mavsdk_port))
    finally:
        client.close()
    print({k: v for k, v in result.items() if k not in ("home", "position", "ned")})
    assert result["system_id"] == 1 and result["autopilot"] == "PX4"
    assert result["start"] == "accepted"
    assert result["mode_in_flight"] == FlightMode.OFFBOARD
    assert result["speed_m_s"] == pytest.approx(FORWARD_M_S, rel=0.10)
    assert result["yaw_rate_rad_s"] == pytest.approx(math.radians(YAWSPEED_DEG_S), rel=0.10)
    assert result["mode_after_stop"] == FlightMode.HOLD
    assert sitl.stop() == 0
    assert sitl.summary()["errors"] == 0
