"""The ArduPilot (Copter) profile, driven by a pymavlink client over TCP like ArduPilot SITL.

Times are the vehicle's simulated time (time_boot_ms).
"""

import re

import pytest
from sim_client import M, SimClient, horizontal_speed

from fleetmpc.protocol.mavlink_map import CopterMode, FlightMode, LandedState, MavResult
from fleetmpc.protocol.mavlink_setpoint import Frame, encode_setpoint

POSITION_READY_S = 8.0
ARDUPILOT = M.MAV_AUTOPILOT_ARDUPILOTMEGA


def set_copter_mode(client: SimClient, mode: CopterMode) -> int:
    return client.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(mode))


def test_guided_takeoff_velocity_and_three_second_stop(start_sitl):
    sitl, ready = start_sitl(
        "--vehicle", "1", "--autopilot", "ardupilot", "--speed", "3", "--tcp-port", "0",
        "--position-ready", str(POSITION_READY_S),
    )  # fmt: skip
    port = int(re.search(r"ardupilot tcp 127\.0\.0\.1:(\d+)", ready["endpoints"])[1])
    client = SimClient.connect_tcp(port, target_system=1)
    try:
        hb = client.wait_type("HEARTBEAT")
        assert (hb.autopilot, hb.type) == (ARDUPILOT, M.MAV_TYPE_QUADROTOR)
        assert hb.custom_mode == CopterMode.STABILIZE
        # Nothing is streamed until a client asks: only heartbeats, whatever is waited for.
        kinds: list[str] = []
        client.wait(
            lambda m: kinds.append(m.get_type()) or kinds.count("HEARTBEAT") >= 3,
            what="three heartbeats",
        )
        assert set(kinds) == {"HEARTBEAT"}
        client.conn.mav.request_data_stream_send(1, 1, M.MAV_DATA_STREAM_ALL, 10, 1)
        client.wait_type("ATTITUDE")
        assert (
            client.command(
                M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 20_000
            )
            == MavResult.ACCEPTED
        )

        # Before the position estimate is ready GUIDED and arming are refused; clients retry.
        assert client.t_ms < POSITION_READY_S * 1000, "the test connected too late to see refusals"
        assert set_copter_mode(client, CopterMode.GUIDED) == MavResult.FAILED
        attempts = []
        while True:
            result = client.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            attempts.append((client.t_ms, result))
            if result == MavResult.ACCEPTED:
                break
            assert result in (MavResult.FAILED, MavResult.TEMPORARILY_REJECTED)
            assert len(attempts) < 100
            client.sleep_sim(0.5)
        print(f"arming attempts (time_boot_ms, result): {attempts}")
        assert len(attempts) >= 2
        assert all(t < POSITION_READY_S * 1000 for t, r in attempts[:-1])
        assert attempts[-1][0] >= POSITION_READY_S * 1000 - 20
        assert any(text.startswith("PreArm: ") for _, text in client.texts)
        assert set_copter_mode(client, CopterMode.GUIDED) == MavResult.ACCEPTED
        assert client.mode(ARDUPILOT) == FlightMode.OFFBOARD and client.armed

        # Take off to the scenario altitude (5 m).
        assert client.command(M.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5.0) == MavResult.ACCEPTED
        client.wait(
            lambda m: m.get_type() == "GLOBAL_POSITION_INT" and m.relative_alt >= 4990,
            what="5 m altitude",
        )
        state = client.wait_type("EXTENDED_SYS_STATE")
        assert state.landed_state == LandedState.IN_AIR

        # Velocity + yaw rate in BODY_OFFSET_NED (9), type mask 1479.
        client.stream(encode_setpoint(1.0, 0.2, frame=Frame.BODY_OFFSET_NED), rate_hz=5.0)
        client.sleep_sim(2.0)
        assert horizontal_speed(client.wait_type("LOCAL_POSITION_NED")) == pytest.approx(1.0)
        assert client.wait_type("ATTITUDE").yawspeed == pytest.approx(0.2)
        assert client.mode(ARDUPILOT) == FlightMode.OFFBOARD

        # No new setpoint: the velocity target stops after 3 s, the mode stays GUIDED.
        client.stream(None)
        t_last = client.last_setpoint_t_ms
        samples = []
        stopped = client.wait(
            lambda m: (
                m.get_type() == "LOCAL_POSITION_NED"
                and (samples.append((m.time_boot_ms, horizontal_speed(m))) or samples[-1][1] < 1e-9)
            ),
            what="the velocity target to stop",
        )
        stop_after_s = (stopped.time_boot_ms - t_last) / 1000
        print(f"GUIDED velocity stopped {stop_after_s:.3f} s (simulated) after the last setpoint")
        assert 3.0 <= stop_after_s <= 3.1
        assert all(s == pytest.approx(1.0) for t, s in samples if t - t_last < 3000)
        client.sleep_sim(0.5)
        assert client.mode(ARDUPILOT) == FlightMode.OFFBOARD and client.armed
        assert client.wait_type("ATTITUDE").yawspeed == 0.0
        lp = client.wait_type("LOCAL_POSITION_NED")
        assert horizontal_speed(lp) == 0.0 and lp.z == pytest.approx(-5.0)
    finally:
        client.close()
    assert sitl.stop() == 0
    assert sitl.summary()["errors"] == 0
