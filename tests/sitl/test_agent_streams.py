"""What the agent's autopilot link asks the simulated vehicle to stream, and what then comes:
on PX4 the pose and heading in ODOMETRY alone, on ArduPilot in LOCAL_POSITION_NED and ATTITUDE
(an interval for ODOMETRY is denied)."""

import math
import re
import time

import pytest
from sim_client import free_port

from fleetmpc.onboard.mavlink_autopilot_link import MavlinkAutopilotLink
from fleetmpc.protocol.mavlink_map import Autopilot


def _kinds_after_connect(link: MavlinkAutopilotLink, wall_s: float) -> list[str]:
    """Connect, then the types of every message the link reads for `wall_s`."""
    kinds: list[str] = []
    handle = link._handle
    link._handle = lambda msg: (kinds.append(msg.get_type()), handle(msg))
    link.connect(timeout_s=20.0)
    time.sleep(0.3)  # (the streams stopped last may still be in flight)
    kinds.clear()
    time.sleep(wall_s)
    return kinds


def test_a_px4_link_reads_its_pose_from_odometry_alone(start_sitl):
    port = free_port()
    start_sitl(
        "--vehicle", "1", "--speed", "2", "--offboard-port", str(port),
        "--offboard-local-port", "0", "--gcs-port", "0",
    )  # fmt: skip
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=1)
    try:
        kinds = _kinds_after_connect(link, wall_s=1.0)
        state = link.state()
    finally:
        link.close()
    assert state.autopilot == Autopilot.PX4 and state.has_pose
    assert kinds.count("ODOMETRY") >= 40  # (30 Hz of simulated time, x2, for a second)
    assert "LOCAL_POSITION_NED" not in kinds and "ATTITUDE" not in kinds
    assert state.rejected == 0
    assert math.isclose(state.north_m, 0.0, abs_tol=0.5)  # (the ideal scenario's start)


def test_an_ardupilot_link_reads_its_pose_from_two_messages(start_sitl):
    _, ready = start_sitl(
        "--vehicle", "1", "--autopilot", "ardupilot", "--speed", "2", "--tcp-port", "0",
    )  # fmt: skip
    port = int(re.search(r"ardupilot tcp 127\.0\.0\.1:(\d+)", ready["endpoints"])[1])
    link = MavlinkAutopilotLink(f"tcp:127.0.0.1:{port}", system_id=1)
    try:
        kinds = _kinds_after_connect(link, wall_s=1.0)
        state = link.state()
    finally:
        link.close()
    assert state.autopilot == Autopilot.ARDUPILOTMEGA and state.has_pose
    assert "ODOMETRY" not in kinds
    assert kinds.count("LOCAL_POSITION_NED") >= 40 and kinds.count("ATTITUDE") >= 40


@pytest.mark.parametrize(
    ("child_frame", "velocity", "expected"),
    [(1, (1.0, 0.5), (1.0, 0.5)), (12, (1.0, 0.0), (0.0, 1.0))],
    ids=["local-ned", "body-frd"],
)
def test_odometry_gives_the_heading_and_the_velocity_in_ned(child_frame, velocity, expected):
    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.onboard.telemetry_streams import odometry_pose

    yaw = math.pi / 2  # (facing East: a body-forward velocity is an eastward one)
    q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]

    def odometry(frame: int = 1, quaternion: list[float] = q):
        return mavlink.MAVLink_odometry_message(
            2_000_000, frame, child_frame, 3.0, -4.0, -10.0, quaternion, *velocity, 0.0,
            0.0, 0.0, 0.1, [math.nan] * 21, [math.nan] * 21, 0, 1, 0,
        )  # fmt: skip

    t_ns, x, y, z, vn, ve, heading = odometry_pose(odometry())
    assert (t_ns, x, y, z) == (2_000_000_000, 3.0, -4.0, -10.0)
    assert heading == pytest.approx(yaw)
    assert (vn, ve) == pytest.approx(expected, abs=1e-12)
    assert odometry_pose(odometry(frame=20)) is None  # LOCAL_FRD: not north-aligned
    assert odometry_pose(odometry(quaternion=[0.5, 0.0, 0.0, 0.5])) is None  # not a rotation


def test_each_reader_takes_a_valid_message_and_refuses_a_bad_one():
    """The link's readers of LOCAL_POSITION_NED, ATTITUDE, GLOBAL_POSITION_INT and
    EXTENDED_SYS_STATE: the values of a valid message, None for one out of its bounds."""
    from types import SimpleNamespace as Msg

    from fleetmpc.onboard.telemetry_streams import (
        attitude_yaw,
        global_fix,
        landed_state,
        local_position,
    )
    from fleetmpc.protocol.mavlink_map import LandedState

    position = {"x": 1.0, "y": -2.0, "z": -10.0, "vx": 0.5, "vy": 0.0, "time_boot_ms": 1500}
    assert local_position(Msg(**position)) == (1_500_000_000, 1.0, -2.0, -10.0, 0.5, 0.0)
    assert local_position(Msg(**{**position, "vy": math.nan})) is None
    assert local_position(Msg(**{**position, "time_boot_ms": -1})) is None
    assert attitude_yaw(Msg(yaw=-3.0, time_boot_ms=20)) == (20_000_000, -3.0)
    assert attitude_yaw(Msg(yaw=7.0, time_boot_ms=20)) is None  # (beyond a turn)
    home = (47.0, 8.0)
    t_ns, north, east = global_fix(Msg(lat=470_000_900, lon=80_000_000, time_boot_ms=3), home)
    assert t_ns == 3_000_000 and math.isclose(north, 10.0, rel_tol=0.01) and abs(east) < 1e-6
    assert global_fix(Msg(lat=0, lon=80_000_000, time_boot_ms=3), home) is None  # (no fix yet)
    assert global_fix(Msg(lat=950_000_000, lon=0, time_boot_ms=3), home) is None
    assert landed_state(Msg(landed_state=2)) == LandedState.IN_AIR
    assert landed_state(Msg(landed_state=9)) is None
