"""MAVSDK (python `mavsdk` 4.x, native binding) discovers and flies the simulated PX4 vehicle."""

import asyncio
import math

import pytest
from mavsdk.asyncio.plugins.telemetry import FlightMode
from mavsdk_flow import FORWARD_M_S, HOME, YAWSPEED_DEG_S, Observer, mavsdk_flight, position_ned
from sim_client import M, SimClient, free_port


def test_mavsdk_discovers_arms_and_flies_offboard(start_sitl):
    port = free_port()
    observer_client = SimClient.listen_udp(target_system=2)
    try:
        sitl, _ = start_sitl(
            "--vehicle", "2", "--offboard-port", str(port), "--offboard-local-port", "0",
            "--gcs-port", str(observer_client.port), "--gcs-local-port", "0",
        )  # fmt: skip
        observer_client.wait_type("HEARTBEAT")
        # The ground-station link streams positions at 1 Hz by default: ask for 10 Hz there.
        interval = observer_client.command(
            M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100_000
        )
        assert interval == M.MAV_RESULT_ACCEPTED
        with Observer(observer_client) as observer:
            result = asyncio.run(mavsdk_flight(port, observer))
    finally:
        observer_client.close()
    print({k: v for k, v in result.items() if k not in ("home", "position", "ned")})

    assert result["system_id"] == 2 and result["autopilot"] == "PX4"
    north, east = position_ned(result["position"])
    assert (north, east) == (pytest.approx(0.0, abs=0.02), pytest.approx(10.0, abs=0.02))
    # Its local frame starts where it booted, 10 m East of the scenario's origin (as a real
    # autopilot's estimator does); the global position says where that is.
    assert result["ned"].position.east_m == pytest.approx(0.0, abs=1e-6)
    assert result["home"].latitude_deg == pytest.approx(HOME["home_lat_deg"], abs=1e-7)
    assert result["home"].longitude_deg == pytest.approx(HOME["home_lon_deg"], abs=1e-7)
    assert result["armed"] is True
    assert result["start"] == "accepted"  # MAVSDK's flow: one setpoint, then start at once
    assert result["mode_in_flight"] == FlightMode.OFFBOARD
    assert result["speed_m_s"] == pytest.approx(FORWARD_M_S, rel=0.10)
    assert result["yaw_rate_rad_s"] == pytest.approx(math.radians(YAWSPEED_DEG_S), rel=0.10)
    observed_speed, observed_yaw_rate = result["observed"]
    assert observed_speed == pytest.approx(FORWARD_M_S, rel=0.10)
    assert observed_yaw_rate == pytest.approx(math.radians(YAWSPEED_DEG_S), rel=0.10)
    assert result["mode_after_stop"] == FlightMode.HOLD
    assert sitl.stop() == 0
    assert sitl.summary()["errors"] == 0
