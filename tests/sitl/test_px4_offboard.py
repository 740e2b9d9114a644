"""PX4 offboard semantics of the `fleetmpc sitl` process, seen by a pymavlink client on loopback.

All times are the vehicle's simulated time (time_boot_ms), so the checks hold at any --speed.
The agent's link is flown against it too: addressed to a system id other than 1, and engaging
through the refusals and failed takeoffs of a real PX4 SITL.
"""

import math
import re
import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as M
from sim_client import (
    SimClient,
    fly_offboard,
    free_port,
    horizontal_speed,
    px4_args,
    wait_hold_after_stop,
    wait_offboard_lost,
)

from fleetmpc.onboard.mavlink_autopilot_link import MavlinkAutopilotLink
from fleetmpc.onboard.setpoints import SetpointStreamer
from fleetmpc.protocol.mavlink_map import FlightMode, MavResult
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
        assert 1000 <= wait_offboard_lost(client) - t_last_valid <= 1100
        client.wait_type("HEARTBEAT")
        assert client.mode() == FlightMode.HOLD
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


def _px4_vehicle(start_sitl, *args: str, vehicle: int = 2, speed: float = 4.0):
    """A PX4-profile vehicle (system id `vehicle`) streaming its offboard link to a free port;
    (the SITL child, that port, the port its offboard link binds)."""
    port = free_port()
    sitl, ready = start_sitl(
        "--vehicle", str(vehicle), "--speed", f"{speed:g}", "--offboard-port", str(port),
        "--offboard-local-port", "0", "--gcs-port", "0", *args,
    )  # fmt: skip
    bound = int(re.search(r"offboard udp 127\.0\.0\.1:(\d+)", ready["endpoints"])[1])
    return sitl, port, bound


def _engage(link: MavlinkAutopilotLink, *, timeout_s: float) -> bool:
    """Connect, stream a position hold where the vehicle is (what PX4 needs for OFFBOARD),
    engage."""
    state = link.connect(timeout_s=10.0)
    streamer = SetpointStreamer(link, period_s=0.02)
    streamer.hold_position(north_m=state.north_m, east_m=state.east_m)
    streamer.start()
    try:
        return link.engage(timeout_s=timeout_s)
    finally:
        streamer.stop()


def test_a_vehicle_of_system_2_is_addressed_as_system_2_and_ignores_commands_to_system_1(
    start_sitl,
):
    """Everything the agent's link sends goes to the system id of the autopilot's HEARTBEAT:
    its stream requests are taken (the pose comes in ODOMETRY alone) and it engages. A command
    to another system gets no ACK, and the PX4 profile logs it as PX4 does."""
    sitl, port, bound = _px4_vehicle(start_sitl, vehicle=2)
    logs: list[str] = []
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", log=logs.append)
    kinds: list[str] = []
    handle = link._handle
    link._handle = lambda msg: (kinds.append(msg.get_type()), handle(msg))
    try:
        assert _engage(link, timeout_s=20.0), logs
        state = link.state()
        time.sleep(0.3)  # (the streams stopped last may still be in flight)
        kinds.clear()
        time.sleep(0.5)
    finally:
        link.close()
    assert state.system_id == 2 and state.engaged and state.armed
    assert state.mode == FlightMode.OFFBOARD and state.mode_name == "OFFBOARD"
    assert kinds.count("ODOMETRY") >= 20 and "LOCAL_POSITION_NED" not in kinds

    other = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{bound}", source_system=255, source_component=190
    )
    try:
        acks = []
        for target in (1, 2):  # (to system 2 as well: the way there works)
            other.mav.command_long_send(target, 1, 511, 0, 33, 200_000, 0, 0, 0, 0, 0)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                m = other.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.1)
                if m is not None and m.command == 511:
                    acks.append((target, m.result))
                    break
    finally:
        other.close()
    assert acks == [(2, MavResult.ACCEPTED)]
    assert sitl.stop() == 0
    assert "vehicle 2: Ignore command 511 from 255/190 to 1/1" in sitl.stderr
    assert "(1 to other systems ignored)" in sitl.stderr


def test_an_arming_refused_and_a_takeoff_that_ends_on_the_ground_are_tried_again(start_sitl):
    """A real PX4 SITL refuses arming while its heading estimate settles, and its first
    takeoff once ended on the ground, disarmed by COM_DISARM_PRFLT: the link asks again, starts
    the sequence over, logs the autopilot's reasons, and engages."""
    sitl, port, _ = _px4_vehicle(
        start_sitl, "--heading-ready", "3", "--takeoff-stall", "5", "--com-disarm-prflt", "2"
    )
    logs: list[str] = []
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", log=logs.append)
    try:
        t0 = time.monotonic()
        assert _engage(link, timeout_s=30.0), logs
        print(f"engaged in {time.monotonic() - t0:.1f} s of wall time at x4")
        state = link.state()
    finally:
        link.close()
    assert state.engaged and state.armed and state.mode == FlightMode.OFFBOARD
    engage = [text for text in logs if text.startswith("engage: ")]
    assert engage == [
        "engage: arm: TEMPORARILY_REJECTED (Preflight Fail: heading estimate not stable);"
        " trying again",
        "engage: the takeoff ended before the vehicle was airborne, disarmed (Disarmed by auto"
        " preflight disarming); trying again",
        "engage: done",
    ]
    assert sitl.stop() == 0


def test_engage_gives_up_at_its_timeout_naming_the_last_reason(start_sitl):
    sitl, port, _ = _px4_vehicle(start_sitl, "--heading-ready", "600")
    logs: list[str] = []
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", log=logs.append)
    try:
        t0 = time.monotonic()
        assert not _engage(link, timeout_s=2.0)
        took_s = time.monotonic() - t0
        state = link.state()
    finally:
        link.close()
    assert not state.engaged and not state.armed
    assert 2.0 <= took_s <= 3.5
    assert logs[-1] == (
        "engage: gave up after 2 s; last reason: arm: TEMPORARILY_REJECTED (Preflight Fail:"
        " heading estimate not stable)"
    )
    # Each reason is logged once, not at every refusal.
    assert sum("trying again" in text for text in logs) == 1
    assert sitl.stop() == 0


def test_a_px4_takeoff_given_a_position_stalls_and_one_without_climbs(start_sitl):
    """PX4 takes a finite latitude and longitude of MAV_CMD_NAV_TAKEOFF as the takeoff's
    position (a real PX4 SITL given 0, 0 never climbed and disarmed itself): the SITL's PX4
    stalls on one, and a takeoff with NaN there (what the agent sends) climbs."""
    client = SimClient.listen_udp(target_system=1)
    try:
        start_sitl(*px4_args(client, speed=4.0))
        client.wait_type("HEARTBEAT")
        assert client.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
        takeoff = M.MAV_CMD_NAV_TAKEOFF
        assert client.command(takeoff, 0, 0, 0, math.nan, 0, 0, math.nan) == MavResult.ACCEPTED
        client.sleep_sim(3.0)
        assert client.wait_type("LOCAL_POSITION_NED").z == 0.0
        nan = math.nan
        assert client.command(takeoff, 0, 0, 0, nan, nan, nan, nan) == MavResult.ACCEPTED
        client.sleep_sim(3.0)
        assert client.wait_type("LOCAL_POSITION_NED").z < -1.0
    finally:
        client.close()
