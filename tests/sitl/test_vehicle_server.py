"""The vehicle server in-process, on real loopback sockets but a manual clock: exact rates."""

import math
import socket
from pathlib import Path

import numpy as np
import pytest

from fleetmpc.clock import ManualClock
from fleetmpc.protocol.local_frame import ned_from_geodetic
from fleetmpc.protocol.mavlink_map import (
    PX4_CUSTOM_MODE_OF,
    FlightMode,
    MavResult,
    MavState,
    ModeFlag,
    px4_split_custom_mode,
)
from fleetmpc.protocol.mavlink_setpoint import (
    SetpointFields,
    encode_position_setpoint,
    encode_setpoint,
    setpoint_message_args,
)
from fleetmpc.scenario import load_scenario
from fleetmpc.sitl.autopilot import AutopilotConfig, Profile
from fleetmpc.sitl.mavlink_io import DecodeStats, FrameDecoder, MavlinkEncoder, mavlink
from fleetmpc.sitl.telemetry import PX4_ONBOARD_RATES_HZ
from fleetmpc.sitl.vehicle_group import serve_vehicles
from fleetmpc.sitl.vehicle_server import ServerConfig, UdpEndpoint, VehicleServer

M = mavlink
DATA = Path(__file__).parent / "data"
PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper.toml"
S = 1_000_000_000
OFFBOARD = PX4_CUSTOM_MODE_OF[FlightMode.OFFBOARD]
ONBOARD = ((M.MAVLINK_MSG_ID_HEARTBEAT, 1.0), *PX4_ONBOARD_RATES_HZ.items())


class Client:
    """A raw UDP (or TCP) MAVLink client of an in-process server."""

    def __init__(self, sock: socket.socket, address, *, stream: bool = False) -> None:
        self.sock = sock
        self.address = address
        self.stream = stream
        self.enc = MavlinkEncoder(system_id=255, component_id=190)
        self.decoder = FrameDecoder(DecodeStats())

    def send(self, build) -> None:
        frame = self.enc.pack(build(self.enc.mav))
        if self.stream:
            self.sock.sendall(frame)
        else:
            self.sock.sendto(frame, self.address)

    def receive(self) -> list:
        out = []
        while True:
            try:
                data = self.sock.recv(65535)
            except BlockingIOError:
                return out
            out.extend(self.decoder.stream(data) if self.stream else self.decoder.datagram(data))


class Rig:
    """A server on a manual clock and one client that it streams to."""

    def __init__(
        self,
        *,
        scenario: Path = DATA / "ideal.toml",
        vehicle: int = 1,
        clock: ManualClock | None = None,
        **server,
    ) -> None:
        scen = load_scenario(scenario)
        spec = scen.vehicle(vehicle)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        profile = server.pop("profile", Profile.PX4)
        udp = server.pop("udp", (UdpEndpoint("offboard", 0, self.sock.getsockname()[1], ONBOARD),))
        config = ServerConfig(
            vehicle=spec,
            site=scen.site,
            tick_ns=scen.tick_ns,
            autopilot=AutopilotConfig(
                profile=profile,
                speed_limit_m_s=spec.truth.speed_limit_m_s,
                yaw_rate_limit_rad_s=spec.truth.yaw_rate_limit_rad_s,
                takeoff_altitude_m=scen.site.altitude_m,
                position_ready_ns=0,
            ),
            seed=scen.seed,
            udp=udp,
            **server,
        )
        self.tick_ns = scen.tick_ns
        self.clock = clock or ManualClock()
        self.server = VehicleServer(config, clock=self.clock)
        address = self.server.local_address("offboard") if udp else None
        self.client = Client(self.sock, address)

    def close(self) -> None:
        self.server.close()
        self.sock.close()

    def run(self, duration_ns: int, client: Client | None = None) -> list:
        """Advance tick by tick, serving the server; return what `client` received."""
        client = client or self.client
        out = []
        for _ in range(duration_ns // self.tick_ns):
            self.clock.advance(self.tick_ns)
            self.server.step()
            out.extend(client.receive())
        return out

    def command(self, command: int, *params: float, target: int = 1) -> list:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.client.send(lambda mav: mav.command_long_encode(target, 1, command, 0, *p))
        self.server.step()
        return self.client.receive()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def of_type(messages, kind: str) -> list:
    return [m for m in messages if m.get_type() == kind]


def test_heartbeat_every_second_with_px4_identity(rig):
    msgs = rig.run(10 * S)
    beats = of_type(msgs, "HEARTBEAT")
    assert 10 <= len(beats) <= 12
    hb = beats[-1]
    assert (hb.type, hb.autopilot) == (M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_PX4)
    assert hb.custom_mode == PX4_CUSTOM_MODE_OF[FlightMode.HOLD] == (4 << 16) | (3 << 24)
    assert hb.base_mode & ModeFlag.CUSTOM_MODE_ENABLED and not hb.base_mode & ModeFlag.SAFETY_ARMED
    assert hb.system_status == MavState.STANDBY
    assert {m.get_srcSystem() for m in msgs} == {1} and {m.get_srcComponent() for m in msgs} == {1}


def test_default_rates_and_set_message_interval(rig):
    msgs = rig.run(10 * S)
    assert len(of_type(msgs, "ATTITUDE")) == pytest.approx(500, abs=1)
    assert len(of_type(msgs, "LOCAL_POSITION_NED")) == pytest.approx(300, abs=1)
    assert len(of_type(msgs, "HOME_POSITION")) == pytest.approx(5, abs=1)

    (ack,) = of_type(
        rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 100_000),
        "COMMAND_ACK",
    )
    assert (ack.command, ack.result) == (M.MAV_CMD_SET_MESSAGE_INTERVAL, MavResult.ACCEPTED)
    assert (ack.target_system, ack.target_component) == (255, 190)
    stamps = [m.time_boot_ms for m in of_type(rig.run(5 * S), "ATTITUDE")]
    assert len(stamps) == pytest.approx(50, abs=1)
    assert set(np.diff(stamps)) == {100}

    rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, -1)
    assert of_type(rig.run(2 * S), "ATTITUDE") == []
    rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 0)
    assert len(of_type(rig.run(2 * S), "ATTITUDE")) == pytest.approx(100, abs=1)
    (ack,) = of_type(rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100_000), "COMMAND_ACK")
    assert ack.result == MavResult.DENIED
    (ack,) = of_type(rig.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 30, math.nan), "COMMAND_ACK")
    assert ack.result == MavResult.DENIED


def test_every_command_gets_exactly_one_ack(rig):
    commands = [
        (M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
        (M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_HOME_POSITION),
        (M.MAV_CMD_REQUEST_MESSAGE, 9999),
        (M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1),
        (M.MAV_CMD_COMPONENT_ARM_DISARM, 1),
        (M.MAV_CMD_COMPONENT_ARM_DISARM, 0),
        (M.MAV_CMD_COMPONENT_ARM_DISARM, 7),
        (M.MAV_CMD_DO_SET_MODE, 1, 3, 0),
        (M.MAV_CMD_DO_SET_MODE, 1, 6, 0),
        (M.MAV_CMD_DO_SET_MODE, 0, 6, 0),
        (M.MAV_CMD_NAV_TAKEOFF,),
        (M.MAV_CMD_NAV_LAND,),
        (M.MAV_CMD_DO_REPOSITION,),
        (12345,),
    ]
    expected = [
        MavResult.ACCEPTED, MavResult.ACCEPTED, MavResult.DENIED, MavResult.ACCEPTED,
        MavResult.ACCEPTED, MavResult.ACCEPTED, MavResult.DENIED, MavResult.ACCEPTED,
        MavResult.DENIED, MavResult.DENIED, MavResult.DENIED, MavResult.ACCEPTED,
        MavResult.UNSUPPORTED, MavResult.UNSUPPORTED,
    ]  # fmt: skip
    replies = []
    for cmd, *params in commands:
        replies.extend(rig.command(cmd, *params))
    acks = of_type(replies, "COMMAND_ACK")
    assert [(a.command, a.result) for a in acks] == [
        (c[0], r) for c, r in zip(commands, expected, strict=True)
    ]
    assert len(of_type(replies, "AUTOPILOT_VERSION")) == 2
    assert len(of_type(replies, "HOME_POSITION")) == 1
    assert rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=7) == []  # not for us


def test_set_mode_message_is_acked_and_shown_in_the_next_heartbeat(rig):
    """As PX4 and ArduPilot do: the ACK at once, the new mode in the next 1 Hz HEARTBEAT."""
    rig.run(S)
    custom = PX4_CUSTOM_MODE_OF[FlightMode.POSITION]
    rig.client.send(lambda mav: mav.set_mode_encode(1, ModeFlag.CUSTOM_MODE_ENABLED, custom))
    rig.server.step()
    replies = rig.client.receive()
    assert [m.get_type() for m in replies] == ["COMMAND_ACK"]
    assert (replies[0].command, replies[0].result) == (
        M.MAVLINK_MSG_ID_SET_MODE,
        MavResult.ACCEPTED,
    )
    heartbeats = of_type(rig.run(S), "HEARTBEAT")
    assert len(heartbeats) == 1 and heartbeats[0].custom_mode == custom


def test_ping_timesync_and_parameters(rig):
    rig.run(5 * S)
    rig.client.send(lambda mav: mav.ping_encode(123456, 7, 0, 0))
    rig.client.send(lambda mav: mav.timesync_encode(0, 42))
    rig.client.send(lambda mav: mav.param_request_list_encode(1, 1))
    rig.server.step()
    replies = rig.client.receive()
    (pong,) = of_type(replies, "PING")
    assert (pong.time_usec, pong.seq, pong.target_system, pong.target_component) == (
        123456,
        7,
        255,
        190,
    )
    (sync,) = of_type(replies, "TIMESYNC")
    assert (sync.tc1, sync.ts1) == (5 * S, 42)
    params = {p.param_id: p.param_value for p in of_type(replies, "PARAM_VALUE")}
    assert params["COM_OF_LOSS_T"] == pytest.approx(1.0)
    assert params["MIS_TAKEOFF_ALT"] == pytest.approx(5.0)


def test_position_velocity_and_home_of_a_vehicle_off_the_origin():
    rig = Rig(vehicle=2)
    try:
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        msgs = rig.run(S)
        gp = of_type(msgs, "GLOBAL_POSITION_INT")[-1]
        north, east = ned_from_geodetic(
            gp.lat * 1e-7, gp.lon * 1e-7, home_lat_deg=47.397742, home_lon_deg=8.545594
        )
        assert (north, east) == (pytest.approx(0.0, abs=0.02), pytest.approx(10.0, abs=0.02))
        assert gp.alt == 488_000 and gp.relative_alt == 0
        lp = of_type(msgs, "LOCAL_POSITION_NED")[-1]
        assert (lp.x, lp.y, lp.z) == (0.0, 10.0, 0.0)
        home = of_type(msgs, "HOME_POSITION")[-1]
        assert (home.latitude, home.longitude, home.altitude) == (473977420, 85455940, 488000)
    finally:
        rig.close()


def test_measurement_noise_and_a_parked_vehicle_that_does_not_drift():
    rig = Rig(scenario=PAPER)  # noise 0.05 m and 0.01 rad, wind (0.3, -0.2) m/s
    try:
        msgs = rig.run(20 * S)
        lp = of_type(msgs, "LOCAL_POSITION_NED")
        x = np.array([m.x for m in lp])
        yaw = np.array([m.yaw for m in of_type(msgs, "ATTITUDE")])
        assert len(x) == 600
        assert x.std() == pytest.approx(0.05, rel=0.15)
        assert abs(x.mean()) < 0.01, "a disarmed vehicle on the ground does not drift"
        assert np.abs(x).max() <= 3 * 0.05 + 1e-6  # truncated at 3 sigma
        assert yaw.std() == pytest.approx(0.01, rel=0.15)
        assert {(m.vx, m.vy) for m in lp} == {(0.0, 0.0)}
    finally:
        rig.close()


def test_ground_truth_on_request_timed_and_without_the_measurement_noise():
    """HIL_STATE_QUATERNION, asked for, carries where the vehicle is (not its noisy estimate)
    and its time since boot: what a ground station judges a flight by."""
    rig = Rig(scenario=PAPER, vehicle=2)  # noise 0.05 m and 0.01 rad; parked at (0, 12), yaw 0
    try:
        (ack,) = of_type(
            rig.command(
                M.MAV_CMD_SET_MESSAGE_INTERVAL,
                M.MAVLINK_MSG_ID_HIL_STATE_QUATERNION,
                200_000,
                target=2,
            ),
            "COMMAND_ACK",
        )
        assert ack.result == MavResult.ACCEPTED
        msgs = rig.run(4 * S)
        truth = of_type(msgs, "HIL_STATE_QUATERNION")
        assert len(truth) == 20
        steps = np.diff([m.time_usec for m in truth])
        assert set(steps.tolist()) == {200_000}
        assert all(m.time_usec * 1000 % rig.tick_ns == 0 for m in truth)
        for m in truth:
            north, east = ned_from_geodetic(
                m.lat * 1e-7, m.lon * 1e-7, home_lat_deg=47.397742, home_lon_deg=8.545594
            )
            assert (north, east) == (pytest.approx(0.0, abs=0.006), pytest.approx(12.0, abs=0.006))
            assert list(m.attitude_quaternion) == [1.0, 0.0, 0.0, 0.0]
        measured = [m.y for m in of_type(msgs, "LOCAL_POSITION_NED")]
        assert np.std(measured) == pytest.approx(0.05, rel=0.2)  # (the estimate stays noisy)
    finally:
        rig.close()


def _fly(rig: Rig, sp: SetpointFields, duration_ns: int) -> list:
    """Send `sp` every 0.1 s of simulated time for `duration_ns`; what the client received."""
    out = []
    for _ in range(duration_ns // (S // 10)):
        args = setpoint_message_args(sp, time_boot_ms=0, target_system=1)
        rig.client.send(lambda mav, args=args: mav.set_position_target_local_ned_encode(*args))
        out.extend(rig.run(S // 10))
    return out


def test_the_autopilot_holds_position_against_the_wind_unless_flying_a_velocity():
    """Armed in HOLD, then on a position setpoint the wind moves nothing; on a zero velocity
    setpoint (the unicycle's own command) it drifts with the wind, as the truth model says."""
    rig = Rig(scenario=PAPER)  # wind (0.3, -0.2) m/s, speed limit 2 m/s
    plant = rig.server.plant
    try:
        rig.run(S)
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)  # PX4 armed on the ground flies
        start = plant.position_m
        rig.run(3 * S)
        assert plant.position_m == pytest.approx(start, abs=1e-12), "HOLD holds the point"
        # A position setpoint: flown to at most 2 m/s, then held; heading and altitude kept.
        heading = plant.pose[2]
        _fly(rig, encode_position_setpoint(3.0, 4.0, 0.0), 2 * S)  # 1.1 s warm-up + 0.9 s
        rig.command(M.MAV_CMD_DO_SET_MODE, 1, *px4_split_custom_mode(OFFBOARD))
        assert rig.server.autopilot.mode == FlightMode.OFFBOARD
        assert plant.position_m == pytest.approx(start, abs=1e-12)
        msgs = _fly(rig, encode_position_setpoint(3.0, 4.0, 0.0), 12 * S)
        lp = of_type(msgs, "LOCAL_POSITION_NED")
        noise = 3 * load_scenario(PAPER).vehicles[0].truth.velocity_noise_m_s  # (3 sigma at most)
        assert max(math.hypot(m.vx, m.vy) for m in lp) <= 2.0 + math.sqrt(2) * noise + 1e-6
        assert plant.position_m == pytest.approx((3.0, 4.0), abs=0.01)
        assert plant.ground_velocity_m_s == (pytest.approx(0.0, abs=0.01),) * 2
        assert (lp[-1].vx, lp[-1].vy) == (pytest.approx(0.0, abs=noise + 1e-6),) * 2
        assert plant.pose[2] == heading and rig.server.autopilot.altitude_m == 0.0
        # A zero velocity setpoint is a unicycle command: the wind moves the vehicle.
        moving = of_type(_fly(rig, encode_setpoint(0.0, 0.0), 2 * S), "LOCAL_POSITION_NED")[-1]
        assert (moving.vx, moving.vy) == (
            pytest.approx(0.3, abs=noise + 1e-6),
            pytest.approx(-0.2, abs=noise + 1e-6),
        )
        assert plant.ground_velocity_m_s == (pytest.approx(0.3), pytest.approx(-0.2))
    finally:
        rig.close()


def test_a_late_loop_flies_the_setpoints_that_came_while_it_did_not_run():
    """The host keeps the SITL from running for 1.5 s of simulated time (0.4 s of wall time at
    x4) while its agent streams a setpoint every 0.1 s: the late loop reads them before it
    catches up, so the vehicle flies them and stays in OFFBOARD. A stream that really stops for
    as long still ends in HOLD (PX4's 1 s offboard-loss timeout)."""
    rig = Rig(scenario=PAPER)
    plant, autopilot = rig.server.plant, rig.server.autopilot
    forward = encode_setpoint(1.0, 0.0)
    try:
        rig.run(S)
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        _fly(rig, forward, 2 * S)
        rig.command(M.MAV_CMD_DO_SET_MODE, 1, *px4_split_custom_mode(OFFBOARD))
        _fly(rig, forward, S)
        assert autopilot.mode == FlightMode.OFFBOARD
        start = plant.position_m
        args = setpoint_message_args(forward, time_boot_ms=0, target_system=1)
        for _ in range(15):  # the agent streams on; the server does not run
            rig.client.send(lambda mav: mav.set_position_target_local_ned_encode(*args))
            rig.clock.advance(S // 10)
        rig.server.step()
        assert autopilot.mode == FlightMode.OFFBOARD
        flown = math.dist(plant.position_m, start)
        assert 1.0 < flown < 2.0, flown  # 1.5 s at about 1 m/s (effectiveness, wind)
        rig.clock.advance(15 * S // 10)  # nothing sent this time
        rig.server.step()
        assert autopilot.mode == FlightMode.HOLD
    finally:
        rig.close()


def test_peers_that_talk_receive_telemetry_until_they_fall_silent(rig):
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    other.setblocking(False)
    peer = Client(other, rig.client.address)
    try:
        peer.send(lambda mav: mav.heartbeat_encode(6, 8, 0, 0, 4))
        assert of_type(rig.run(S, peer), "ATTITUDE")
        rig.run(11 * S, peer)
        peer.receive()
        assert rig.run(S, peer) == [], "a peer silent for 10 s is dropped"
        assert of_type(rig.run(S), "ATTITUDE"), "the configured remote keeps its stream"
    finally:
        other.close()


def test_ardupilot_over_tcp_streams_only_what_is_asked():
    rig = Rig(profile=Profile.ARDUPILOT, udp=(), tcp_port=0)
    conn = socket.create_connection(rig.server.local_address("ardupilot"))
    conn.setblocking(False)
    client = Client(conn, None, stream=True)
    try:
        rig.server.step()  # accept
        first = rig.run(3 * S, client)
        assert {m.get_type() for m in first} == {"HEARTBEAT"}
        assert first[-1].autopilot == M.MAV_AUTOPILOT_ARDUPILOTMEGA and first[-1].custom_mode == 0
        client.send(
            lambda mav: mav.request_data_stream_encode(1, 1, M.MAV_DATA_STREAM_POSITION, 5, 1)
        )
        msgs = rig.run(2 * S, client)
        assert len(of_type(msgs, "GLOBAL_POSITION_INT")) == pytest.approx(10, abs=1)
        assert len(of_type(msgs, "LOCAL_POSITION_NED")) == pytest.approx(10, abs=1)
        assert of_type(msgs, "ATTITUDE") == []
        client.send(lambda mav: mav.request_data_stream_encode(1, 1, M.MAV_DATA_STREAM_ALL, 0, 0))
        rig.server.step()
        client.receive()
        assert {m.get_type() for m in rig.run(2 * S, client)} == {"HEARTBEAT"}
    finally:
        conn.close()
        rig.close()


def test_one_loop_serves_two_vehicles_each_on_its_own_endpoint():
    clock = ManualClock()
    one, two = Rig(vehicle=1, clock=clock), Rig(vehicle=2, clock=clock)
    ticks = iter(range(5 * S // one.tick_ns))
    got: dict[int, list] = {1: [], 2: []}

    def should_stop() -> bool:  # (the loop's clock moves one tick per iteration)
        got[1] += one.client.receive()
        got[2] += two.client.receive()
        if next(ticks, None) is None:
            return True
        clock.advance(one.tick_ns)
        return False

    try:
        arm = (M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        two.client.send(lambda mav: mav.command_long_encode(2, 1, *arm))
        one.client.send(lambda mav: mav.command_long_encode(2, 1, *arm))  # not vehicle 1's id
        serve_vehicles([one.server, two.server], clock, should_stop)
        for vid, messages in got.items():
            assert {m.get_srcSystem() for m in messages} == {vid}
            assert 5 <= len(of_type(messages, "HEARTBEAT")) <= 7
        assert [a.result for a in of_type(got[2], "COMMAND_ACK")] == [MavResult.ACCEPTED]
        assert of_type(got[1], "COMMAND_ACK") == []
        assert two.server.autopilot.armed and not one.server.autopilot.armed
        assert one.server.plant.time_ns == two.server.plant.time_ns == 5 * S
    finally:
        one.close()
        two.close()
