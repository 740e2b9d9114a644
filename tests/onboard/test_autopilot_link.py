"""AutopilotLink: the pymavlink link against a scripted autopilot on loopback UDP, and the fake."""

import math
import os
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from fleetmpc.errors import ConfigError  # noqa: E402
from fleetmpc.onboard.autopilot_link import AutopilotLinkError, open_autopilot_link  # noqa: E402
from fleetmpc.onboard.fake_autopilot_link import FakeAutopilotLink  # noqa: E402
from fleetmpc.onboard.mavlink_autopilot_link import MavlinkAutopilotLink  # noqa: E402
from fleetmpc.protocol.mavlink_map import (  # noqa: E402
    Autopilot,
    FlightMode,
    LandedState,
    base_mode,
    custom_mode_of,
)


def _free_udp_port() -> int:
    with closing(socket.socket(socket.AF_INET, socket.SOCK_DGRAM)) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Sink:
    def __init__(self) -> None:
        self.frame = b""

    def write(self, data: bytes) -> None:
        self.frame = bytes(data)


class ScriptedAutopilot:
    """A minimal MAVLink autopilot on loopback: streams pose, records and ACKs what it gets."""

    def __init__(
        self,
        port: int,
        *,
        autopilot: Autopilot,
        deny_arms: int = 0,
        on_ground: bool = False,
        prompt_heartbeat: bool = True,
    ) -> None:
        self.autopilot = autopilot
        self.prompt_heartbeat = prompt_heartbeat
        """Send a HEARTBEAT right after each command (a real ArduPilot waits for its 1 Hz one)."""
        self.setpoints_in_takeoff = 0
        self.landed_state = 1 if on_ground else None
        """EXTENDED_SYS_STATE's landed state to stream (None: not streamed)."""
        self.climb_left = 0
        """Loop turns (20 ms) until a takeoff's climb is over."""
        self.port = port
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.sink = _Sink()
        self.mav = mavlink.MAVLink(self.sink, srcSystem=1, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.mode = FlightMode.HOLD if autopilot == Autopilot.PX4 else FlightMode.STABILIZE
        self.armed = False
        self.deny_arms = deny_arms
        self.received: list = []
        self.pose = (1.5, -2.5, 0.25)
        self.bad_position = False
        self.boot_ms = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _send(self, msg) -> None:
        self.mav.send(msg)
        self.sock.sendto(self.sink.frame, ("127.0.0.1", self.port))

    def _heartbeat(self) -> None:
        self._send(
            self.mav.heartbeat_encode(
                mavlink.MAV_TYPE_QUADROTOR,
                int(self.autopilot),
                base_mode(armed=self.armed, mode=self.mode),
                custom_mode_of(self.mode, self.autopilot),
                4,
            )
        )

    def _loop(self) -> None:
        k = 0
        while not self._stop.is_set():
            self.boot_ms += 20
            if k % 10 == 0:
                self._heartbeat()
            x, y, yaw = self.pose
            if self.bad_position:
                x = math.nan
            self._send(self.mav.local_position_ned_encode(self.boot_ms, x, y, -10.0, 0, 0, 0))
            self._send(self.mav.attitude_encode(self.boot_ms, 0, 0, yaw, 0, 0, 0))
            if self.climb_left > 0:
                self.climb_left -= 1
                if self.climb_left == 0:  # (the takeoff is over: PX4 loiters)
                    self.landed_state = 2
                    if self.autopilot == Autopilot.PX4:
                        self.mode = FlightMode.HOLD
                        self._heartbeat()
            if self.landed_state is not None and k % 5 == 0:
                self._send(self.mav.extended_sys_state_encode(0, self.landed_state))
            k += 1
            deadline = time.monotonic() + 0.02
            while time.monotonic() < deadline:
                try:
                    data, _ = self.sock.recvfrom(4096)
                except TimeoutError:
                    continue
                for msg in self.parser.parse_buffer(data) or []:
                    self._handle(msg)

    def _handle(self, msg) -> None:
        self.received.append(msg)
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and self.landed_state == 3:
            self.setpoints_in_takeoff += 1
        if msg.get_type() != "COMMAND_LONG":
            return
        result = 0
        if msg.command == 400:
            if self.deny_arms > 0:
                self.deny_arms -= 1
                result = 4
            else:
                self.armed = True
        elif msg.command == 22 and self.landed_state is not None:
            self.landed_state, self.climb_left = 3, 15
            if self.autopilot == Autopilot.PX4:
                self.mode = FlightMode.TAKEOFF
        elif msg.command == 176:
            number = int(msg.param2)
            if self.autopilot == Autopilot.PX4:
                if number == 6 and self.landed_state in (1, 3):
                    result = 4  # (this script accepts OFFBOARD only in the air)
                else:
                    self.mode = {6: FlightMode.OFFBOARD, 4: FlightMode.HOLD}.get(number, self.mode)
            else:
                self.mode = {4: FlightMode.OFFBOARD, 5: FlightMode.HOLD}.get(number, self.mode)
        self._send(self.mav.command_ack_encode(msg.command, result, 0, 0, 255, 190))
        if self.prompt_heartbeat:
            self._heartbeat()

    def of_type(self, kind: str) -> list:
        return [m for m in list(self.received) if m.get_type() == kind]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.sock.close()


@pytest.fixture(params=[Autopilot.PX4, Autopilot.ARDUPILOTMEGA], ids=["px4", "ardupilot"])
def pair(request) -> Iterator[tuple[MavlinkAutopilotLink, ScriptedAutopilot]]:
    port = _free_udp_port()
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=1)
    ap = ScriptedAutopilot(port, autopilot=request.param, deny_arms=2)
    try:
        yield link, ap
    finally:
        link.close()
        ap.close()


def test_connect_detects_the_autopilot_and_reads_the_pose(pair) -> None:
    link, ap = pair
    state = link.connect(timeout_s=5.0)
    assert state.autopilot == ap.autopilot
    assert state.system_id == 1
    assert (state.north_m, state.east_m) == pytest.approx(ap.pose[:2])
    assert state.yaw_rad == pytest.approx(ap.pose[2])
    assert state.time_boot_ns > 0 and state.time_boot_ns % 1_000_000 == 0


def test_setpoints_use_the_autopilots_frame_and_mask(pair) -> None:
    link, ap = pair
    link.connect(timeout_s=5.0)
    link.send_setpoint(speed_m_s=1.25, yaw_rate_rad_s=-0.3)
    deadline = time.monotonic() + 2.0
    while not ap.of_type("SET_POSITION_TARGET_LOCAL_NED") and time.monotonic() < deadline:
        time.sleep(0.01)
    sp = ap.of_type("SET_POSITION_TARGET_LOCAL_NED")[-1]
    assert sp.type_mask == 1479
    assert sp.coordinate_frame == (8 if ap.autopilot == Autopilot.PX4 else 9)
    assert (sp.vx, sp.vy, sp.vz) == pytest.approx((1.25, 0.0, 0.0))
    assert sp.yaw_rate == pytest.approx(-0.3)
    assert sp.target_system == 1 and sp.target_component == 1


def test_engage_follows_the_autopilots_semantics(pair) -> None:
    link, ap = pair
    link.connect(timeout_s=5.0)
    assert link.engage(timeout_s=5.0)
    commands = [(int(m.command), m.param1, m.param2) for m in ap.of_type("COMMAND_LONG")]
    arms = [c for c in commands if c[0] == 400]
    assert len(arms) == 3  # two refusals, then accepted: retried until accepted
    modes = [c for c in commands if c[0] == 176]
    if ap.autopilot == Autopilot.PX4:
        assert modes[-1][1:] == (1.0, 6.0)  # CUSTOM_MODE_ENABLED, OFFBOARD
        assert commands.index(arms[-1]) < commands.index(modes[-1])
    else:
        intervals = {int(c[1]) for c in commands if c[0] == 511}
        assert {32, 30} <= intervals  # streams requested
        assert modes[0][1:] == (1.0, 4.0)  # GUIDED
        assert commands[-1][0] == 22  # takeoff after arming
    state = link.wait_state(newer_than_ns=link.state().time_boot_ns, timeout_s=1.0)
    assert state.engaged and state.mode == FlightMode.OFFBOARD and state.armed


def test_a_px4_on_the_ground_takes_off_before_offboard() -> None:
    port = _free_udp_port()
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=1)
    ap = ScriptedAutopilot(port, autopilot=Autopilot.PX4, on_ground=True)
    try:
        link.connect(timeout_s=5.0)
        deadline = time.monotonic() + 2.0
        while link.state().landed_state is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert link.engage(timeout_s=5.0)
        commands = [int(m.command) for m in ap.of_type("COMMAND_LONG") if m.command != 511]
        assert commands[:2] == [400, 22]  # arm, then take off,
        assert commands[-1] == 176 and commands.count(176) == 1  # then OFFBOARD, once airborne
        takeoff = next(m for m in ap.of_type("COMMAND_LONG") if m.command == 22)
        assert math.isnan(takeoff.param7)  # PX4's own takeoff altitude (MIS_TAKEOFF_ALT)
        state = link.wait_state(newer_than_ns=link.state().time_boot_ns, timeout_s=1.0)
        assert state.engaged and state.mode == FlightMode.OFFBOARD
        assert state.landed_state == LandedState.IN_AIR
    finally:
        link.close()
        ap.close()


def test_an_ardupilot_takeoff_gets_no_setpoints_and_outlasts_a_late_heartbeat() -> None:
    """A real ArduCopter: HEARTBEAT once a second, not after each command (so the arming shows
    late), and a GUIDED target during its takeoff would replace the takeoff."""
    port = _free_udp_port()
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=1)
    ap = ScriptedAutopilot(
        port, autopilot=Autopilot.ARDUPILOTMEGA, on_ground=True, prompt_heartbeat=False
    )
    stop = threading.Event()

    def stream() -> None:  # (as the agent's setpoint streamer does, all along)
        while not stop.wait(0.02):
            link.send_position_setpoint(north_m=1.5, east_m=-2.5, down_m=0.0)

    streamer = threading.Thread(target=stream, daemon=True)
    try:
        link.connect(timeout_s=5.0)
        deadline = time.monotonic() + 2.0
        while link.state().landed_state is None and time.monotonic() < deadline:
            time.sleep(0.02)
        streamer.start()
        assert link.engage(timeout_s=5.0)
        assert link.state().landed_state == LandedState.IN_AIR
        assert ap.setpoints_in_takeoff == 0
        time.sleep(0.2)
        assert ap.of_type("SET_POSITION_TARGET_LOCAL_NED")  # (flowing again once airborne)
    finally:
        stop.set()
        if streamer.is_alive():
            streamer.join(timeout=1.0)
        link.close()
        ap.close()


def test_mode_loss_is_detected_not_fought(pair) -> None:
    link, ap = pair
    link.connect(timeout_s=5.0)
    assert link.engage(timeout_s=5.0)
    sent = len(ap.of_type("COMMAND_LONG"))
    ap.mode = FlightMode.HOLD  # the autopilot fails safe
    deadline = time.monotonic() + 2.0
    while not link.state().mode_lost and time.monotonic() < deadline:
        time.sleep(0.02)
    assert link.state().mode_lost
    assert link.state().mode == FlightMode.HOLD
    time.sleep(0.3)
    assert len(ap.of_type("COMMAND_LONG")) == sent  # no attempt to re-engage


def test_invalid_telemetry_is_rejected_and_counted(pair) -> None:
    link, ap = pair
    link.connect(timeout_s=5.0)
    ap.bad_position = True
    time.sleep(0.3)
    state = link.state()
    assert state.rejected > 0
    assert state.north_m == pytest.approx(ap.pose[0])


def test_connect_times_out_without_an_autopilot() -> None:
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{_free_udp_port()}")
    try:
        with pytest.raises(AutopilotLinkError, match="no HEARTBEAT"):
            link.connect(timeout_s=0.5)
    finally:
        link.close()


def test_urls_pick_the_implementation() -> None:
    assert isinstance(open_autopilot_link("fake://"), FakeAutopilotLink)
    fake = open_autopilot_link("fake://ardupilot", system_id=3)
    assert fake.connect(timeout_s=0.1).autopilot == Autopilot.ARDUPILOTMEGA
    with pytest.raises(ConfigError, match="mavlink_url"):
        open_autopilot_link("fake://betaflight")
    with pytest.raises(ConfigError, match="mavlink_url"):
        open_autopilot_link("")


def test_fake_flies_the_setpoint_and_fails_safe_to_hold() -> None:
    fake = FakeAutopilotLink(yaw_rad=0.0, loss_timeout_ns=500_000_000)
    fake.connect(timeout_s=0.1)
    fake.engage(timeout_s=0.1)
    fake.send_setpoint(speed_m_s=2.0, yaw_rate_rad_s=0.0)
    fake.advance(400_000_000)
    assert fake.state().north_m == pytest.approx(0.8)
    assert not fake.state().mode_lost
    fake.advance(400_000_000)
    state = fake.state()
    assert state.mode == FlightMode.HOLD and state.mode_lost
    assert state.north_m == pytest.approx(1.0, abs=0.05)  # 0.5 s flown, 40 ms substeps


def test_the_first_autopilot_heard_is_flown_whatever_its_system_id() -> None:
    """An ArduCopter answers as system 1 by default (MAV_SYSID): a link that insists on no id
    flies it; one that insists on another id says which autopilots it heard instead."""
    port = _free_udp_port()
    ap = ScriptedAutopilot(port, autopilot=Autopilot.ARDUPILOTMEGA)
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}")
    try:
        assert link.connect(timeout_s=5.0).system_id == 1
    finally:
        link.close()
        ap.close()
    port = _free_udp_port()
    ap = ScriptedAutopilot(port, autopilot=Autopilot.ARDUPILOTMEGA)
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=2)
    try:
        with pytest.raises(AutopilotLinkError, match="no HEARTBEAT from system 2.*heard.*system 1"):
            link.connect(timeout_s=1.0)
    finally:
        link.close()
        ap.close()


def test_a_disarm_by_the_autopilot_is_reported_by_name_within_a_second(pair) -> None:
    link, ap = pair
    said: list[str] = []
    link._log = said.append  # (the fixture's link logs nowhere)
    link.connect(timeout_s=5.0)
    assert link.engage(timeout_s=5.0)
    deadline = time.monotonic() + 2.0
    while not link.state().armed and time.monotonic() < deadline:
        time.sleep(0.02)
    ap.armed = False  # ArduCopter's auto-disarm on the ground; the mode stays GUIDED
    t0 = time.monotonic()
    while "mode lost: the autopilot disarmed" not in said and time.monotonic() - t0 < 2.0:
        time.sleep(0.02)
    assert "mode lost: the autopilot disarmed" in said and time.monotonic() - t0 < 1.0
    assert link.state().mode_lost


def test_the_local_origin_is_placed_from_global_fixes() -> None:
    """An autopilot whose local frame starts where it booted, 12 m East of the scenario's
    origin: its global fixes, placed against the scenario's home, put it where it is."""
    from fleetmpc.onboard.local_origin import OriginShift

    origin = OriginShift()
    origin.global_fix(0, 0.0, 12.0)  # no local position yet: not compared
    assert origin.value is None
    for k in range(30):
        t = k * 200_000_000
        local_x, local_y = 0.5 * k * 0.2, 0.0  # flying North at 0.5 m/s
        origin.local(t, local_x, local_y, 0.5, 0.0)
        noise = 0.01 * (-1) ** k  # a fix is quantized to about a centimetre
        origin.global_fix(t + 40_000_000, local_x + 0.5 * 0.04 + noise, 12.0 + local_y - noise)
    assert origin.value == (pytest.approx(0.0, abs=0.005), pytest.approx(12.0, abs=0.005))
    origin.global_fix(30 * 200_000_000 + 10**9, 99.0, 99.0)  # a fix a second off: not compared
    assert origin.value == (pytest.approx(0.0, abs=0.005), pytest.approx(12.0, abs=0.005))


def test_a_signed_link_flies_a_signed_vehicle_and_ignores_forged_telemetry() -> None:
    """Agent and SITL share a key: the agent engages the vehicle; forged frames (no key, a
    wrong key with a far-future timestamp) claiming the vehicle left offboard change nothing,
    and the real stream is still heard after them."""
    from fleetmpc.clock import RealTimeClock
    from fleetmpc.scenario import load_scenario
    from fleetmpc.security.mavlink_signing import (
        Rejection,
        key_from_passphrase,
        sign_outgoing,
        signing_timestamp,
    )
    from fleetmpc.sitl.autopilot import AutopilotConfig, Profile
    from fleetmpc.sitl.mavlink_io import MavlinkEncoder
    from fleetmpc.sitl.vehicle_group import serve_vehicles
    from fleetmpc.sitl.vehicle_server import ServerConfig, UdpEndpoint, VehicleServer

    key = key_from_passphrase("vehicle 1")
    scenario = load_scenario(Path(__file__).parents[1] / "sitl" / "data" / "ideal.toml")
    spec = scenario.vehicle(1)
    port = _free_udp_port()
    link = MavlinkAutopilotLink(f"udpin:127.0.0.1:{port}", system_id=1, signing_key=key)
    config = ServerConfig(
        vehicle=spec,
        site=scenario.site,
        tick_ns=scenario.tick_ns,
        autopilot=AutopilotConfig(
            profile=Profile.PX4,
            speed_limit_m_s=2.0,
            yaw_rate_limit_rad_s=1.0,
            takeoff_altitude_m=2.0,
            position_ready_ns=0,
        ),
        udp=(UdpEndpoint("offboard", 0, port, ((0, 2.0), (32, 20.0), (30, 20.0))),),
        signing_key=key,
    )
    clock = RealTimeClock(speed=1.0)
    server = VehicleServer(config, clock=clock)
    stop = threading.Event()
    thread = threading.Thread(
        target=serve_vehicles, args=([server], clock, stop.is_set), daemon=True
    )
    thread.start()
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def stream() -> None:  # PX4 enters offboard only on a live setpoint stream
        while not stop.wait(0.1):
            link.send_setpoint(speed_m_s=0.5, yaw_rate_rad_s=0.0)

    streamer = threading.Thread(target=stream, daemon=True)
    try:
        link.connect(timeout_s=5.0)
        streamer.start()
        assert link.engage(timeout_s=10.0)
        hold = custom_mode_of(FlightMode.HOLD, Autopilot.PX4)
        for enc_key, stamp in ((None, None), (key_from_passphrase("guess"), 10**12)):
            enc = MavlinkEncoder(system_id=1, component_id=1)
            if enc_key is not None:
                sign_outgoing(enc.mav, enc_key)
                enc.mav.signing.timestamp = signing_timestamp(time.time_ns()) + stamp
            hb = enc.mav.heartbeat_encode(
                2, 12, base_mode(armed=False, mode=FlightMode.HOLD), hold, 3
            )
            for _ in range(5):
                forger.sendto(enc.pack(hb), ("127.0.0.1", port))
        heard = link.state().heartbeats
        deadline = time.monotonic() + 3.0
        while link.state().heartbeats < heard + 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        state = link.state()
        assert state.heartbeats >= heard + 2, "the real stream is still heard"
        assert state.mode == FlightMode.OFFBOARD and state.armed and not state.mode_lost
        assert link.signing.rejected[Rejection.UNSIGNED] == 5
        assert link.signing.rejected[Rejection.BAD_SIGNATURE] == 5
        assert server.signing.rejected == {}, "everything the agent sent was signed"
    finally:
        forger.close()
        stop.set()
        thread.join(timeout=2.0)
        if streamer.is_alive():
            streamer.join(timeout=2.0)
        link.close()
        server.close()


def test_a_waiter_sleeps_through_telemetry_before_its_time_and_wakes_on_an_event() -> None:
    """The runner sleeps from one step to the next: telemetry short of the boot time it waits
    for wakes nobody (no notify at all), telemetry past it does, and so does a change of mode."""
    link = FakeAutopilotLink()
    notified = []
    real_notify = link._cond.notify_all
    link._cond.notify_all = lambda: (notified.append(link.state().time_boot_ns), real_notify())
    link._update(time_boot_ns=0)
    notified.clear()

    def wait(newer_than_ns: int) -> tuple[list, threading.Thread]:
        seen: list = []
        t = threading.Thread(
            target=lambda: seen.append(link.wait_state(newer_than_ns=newer_than_ns, timeout_s=5.0))
        )
        t.start()
        deadline = time.monotonic() + 2.0
        while not link._waits and time.monotonic() < deadline:
            time.sleep(0.001)
        return seen, t

    seen, t = wait(1_000)
    for boot_ns in (200, 400, 600, 800, 1_000):
        link._update(time_boot_ns=boot_ns, north_m=1.0, yaw_rad=0.5)
    assert notified == [] and seen == []  # (five messages, none past 1000: no wake-up)
    link._update(time_boot_ns=1_200)
    t.join(timeout=2.0)
    assert notified == [1_200] and seen[0].time_boot_ns == 1_200

    seen, t = wait(10_000)
    link._update(time_boot_ns=1_400, mode=FlightMode.HOLD)  # an event: the mode changed
    t.join(timeout=2.0)
    assert seen and seen[0].mode == FlightMode.HOLD and seen[0].time_boot_ns == 1_400
    assert link._waits == []
