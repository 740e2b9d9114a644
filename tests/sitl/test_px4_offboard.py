"""PX4 offboard semantics of the `fleetmpc sitl` process, seen by a pymavlink client on loopback.

All times are the vehicle's simulated time (time_boot_ms), so the checks hold at any --speed.
"""

import math

import pytest
from sim_client import SimClient, fly_offboard, horizontal_speed, px4_args, wait_hold_after_stop

from fleetmpc.protocol.mavlink_map import FlightMode
from fleetmpc.protocol.mavlink_setpoint import Frame, SetpointFields, TypeMask, encode_setpoint


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_offboard_needs_a_setpoint_stream_and_falls_back_to_hold(start_sitl, speed):
    client = SimClient.listen_udp(target_system=1)
    try:
        sitl, _ = start_sitl(*px4_args(client, speed=speed))
        fly_offboard(client, encode_setpoint(1.0, 0.2, frame=Frame.BODY_NED))
        client.sleep_sim(1.0)
        lp = client.wait_type("LOCAL_POSITION_NED")
        att = client.wait_type("ATTITUDE")
        assert horizontal_speed(lp) == pytest.approx(1.0, rel=1e-3)
        assert att.yawspeed == pytest.approx(0.2, rel=1e-3)

        hold_after_s = wait_hold_after_stop(client)
        print(f"speed {speed}: HOLD {hold_after_s:.3f} s (simulated) after the last setpoint")
        assert 1.0 <= hold_after_s <= 1.1
        assert any("Offboard lost" in text for _, text in client.texts)
        client.sleep_sim(0.1)
        assert horizontal_speed(client.wait_type("LOCAL_POSITION_NED")) == 0.0
        assert client.armed, "the failsafe holds position, it does not disarm"
    finally:
        client.close()
    assert sitl.stop() == 0
    assert sitl.summary()["errors"] == 0


def test_invalid_setpoints_leave_the_motion_unchanged(start_sitl):
    client = SimClient.listen_udp(target_system=1)
    try:
        sitl, _ = start_sitl(*px4_args(client, speed=2.0))
        fly_offboard(client, encode_setpoint(1.2, -0.3, frame=Frame.BODY_NED))
        client.sleep_sim(0.5)
        client.stream(None)
        t_last_valid = client.last_setpoint_t_ms
        base = dict(frame=int(Frame.BODY_NED), type_mask=int(TypeMask.VELOCITY_YAW_RATE))
        bad = [
            SetpointFields(**base, vx_m_s=math.nan),
            SetpointFields(**base, vx_m_s=1.0, yaw_rate_rad_s=math.inf),
            SetpointFields(**base, vx_m_s=1e30),
            SetpointFields(**base, vx_m_s=-math.inf, vy_m_s=math.nan, vz_m_s=math.nan),
            SetpointFields(frame=7, type_mask=int(TypeMask.VELOCITY_YAW_RATE), vx_m_s=0.5),
            SetpointFields(frame=int(Frame.LOCAL_NED), type_mask=0, vx_m_s=0.5),
        ]
        speeds, yaw_rates, sent, next_ms = [], [], 0, client.t_ms
        while client.t_ms < t_last_valid + 900:  # under COM_OF_LOSS_T: only bad ones arrive
            m = client.pump()
            if m is None:
                continue
            if client.t_ms >= next_ms:
                client.send_setpoint(bad[sent % len(bad)])
                sent, next_ms = sent + 1, next_ms + 40
            if m.get_type() == "LOCAL_POSITION_NED":
                speeds.append(horizontal_speed(m))
            elif m.get_type() == "ATTITUDE":
                yaw_rates.append(m.yawspeed)
        assert sent >= 20
        assert client.mode() == FlightMode.OFFBOARD
        assert min(speeds) == pytest.approx(1.2, rel=1e-6)
        assert max(speeds) == pytest.approx(1.2, rel=1e-6)
        assert all(w == pytest.approx(-0.3, rel=1e-6) for w in yaw_rates)
        # Invalid setpoints do not keep offboard alive: HOLD 1 s after the last *valid* one.
        client.wait(
            lambda m: m.get_type() == "HEARTBEAT" and client.mode() == FlightMode.HOLD,
            what="HOLD heartbeat",
        )
        after = client.wait(lambda m: hasattr(m, "time_boot_ms"), what="timestamped message")
        assert 1000 <= after.time_boot_ms - t_last_valid <= 1100
        ignored = [text for _, text in client.texts if text.startswith("Setpoint ignored")]
        assert sorted(ignored) == sorted(
            {
                "Setpoint ignored: NaN or Inf field",
                "Setpoint ignored: implausibly large value",
                "Setpoint ignored: unsupported frame",
                "Setpoint ignored: unsupported type_mask",
            }
        ), "each kind of bad setpoint is reported once"
    finally:
        client.close()
    assert sitl.stop() == 0
