"""A pymavlink test client that follows the vehicle's simulated clock.

It remembers the latest `time_boot_ms` it has seen, so waits and setpoint streams can be
expressed in simulated time whatever `--speed` the vehicle runs at: a setpoint stream sends the
next setpoint when a message stamped at or after the next due time arrives.
"""

import math
import os
import socket
import time
from pathlib import Path

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil  # noqa: E402

from fleetmpc.protocol.mavlink_map import (  # noqa: E402
    PX4_CUSTOM_MODE_OF,
    FlightMode,
    MavResult,
    mode_from_custom,
    px4_split_custom_mode,
)
from fleetmpc.protocol.mavlink_setpoint import SetpointFields, setpoint_message_args  # noqa: E402

M = mavutil.mavlink
IDEAL_SCENARIO = Path(__file__).parent / "data" / "ideal.toml"
"""Two vehicles with ideal truth: what is commanded is what flies."""


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port that was free on 127.0.0.1 a moment ago."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SimClient:
    def __init__(self, conn, *, target_system: int) -> None:
        self.conn = conn
        self.target = target_system
        self.t_ms = -1
        self.heartbeat = None
        self._heartbeat_stale = False
        """A COMMAND_ACK came after the newest HEARTBEAT."""
        self.texts: list[tuple[int, str]] = []
        self.acks: list = []
        self._stream: SetpointFields | None = None
        self._period_ms = 100
        self._next_ms = 0
        self.last_setpoint_t_ms = -1
        self.setpoints_sent = 0

    @classmethod
    def listen_udp(cls, *, target_system: int, port: int = 0) -> "SimClient":
        """Listen on 127.0.0.1:`port` (0: any free port) and answer whoever streams to it."""
        conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=255, source_component=190
        )
        return cls(conn, target_system=target_system)

    @classmethod
    def connect_tcp(cls, port: int, *, target_system: int) -> "SimClient":
        conn = mavutil.mavlink_connection(
            f"tcp:127.0.0.1:{port}", source_system=255, source_component=190, retries=20
        )
        return cls(conn, target_system=target_system)

    @property
    def port(self) -> int:
        return self.conn.port.getsockname()[1]

    def close(self) -> None:
        self.conn.close()

    # ----------------------------------------------------------------------------- receiving
    def pump(self, timeout_s: float = 0.05):
        """Read one message (waiting up to `timeout_s`; 0: only if one is already there)."""
        if timeout_s > 0:
            m = self.conn.recv_match(blocking=True, timeout=timeout_s)
        else:
            m = self.conn.recv_match(blocking=False)
        if m is None or m.get_srcSystem() != self.target or m.get_type() == "BAD_DATA":
            return None
        t = getattr(m, "time_boot_ms", None)
        if t is not None:
            self.t_ms = max(self.t_ms, t)
            self._maybe_send_setpoint()
        kind = m.get_type()
        if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
            self.heartbeat = m
            self._heartbeat_stale = False
        elif kind == "STATUSTEXT":
            self.texts.append((m.severity, m.text))
        elif kind == "COMMAND_ACK":
            self.acks.append(m)
            self._heartbeat_stale = True
        return m

    def wait(self, predicate, *, what: str, wall_s: float = 30.0):
        """Pump until a message satisfies `predicate`; return it."""
        deadline = time.monotonic() + wall_s
        while time.monotonic() < deadline:
            m = self.pump()
            if m is not None and predicate(m):
                return m
        raise AssertionError(f"timed out waiting for {what} (vehicle time {self.t_ms} ms)")

    def wait_type(self, kind: str, *, wall_s: float = 30.0):
        return self.wait(lambda m: m.get_type() == kind, what=kind, wall_s=wall_s)

    def wait_until_ms(self, t_ms: int, *, wall_s: float = 60.0) -> None:
        """Pump until the vehicle's clock reaches `t_ms` (needs a timestamped stream)."""
        self.wait(lambda m: self.t_ms >= t_ms, what=f"vehicle time {t_ms} ms", wall_s=wall_s)

    def sleep_sim(self, duration_s: float) -> None:
        if self.t_ms < 0:
            self.wait(lambda m: self.t_ms >= 0, what="a timestamped message")
        self.wait_until_ms(self.t_ms + round(duration_s * 1000))

    # ----------------------------------------------------------------------------- state
    def _current_heartbeat(self):
        """The newest HEARTBEAT, waiting for the next one when a COMMAND_ACK came after it: the
        vehicle sends HEARTBEAT at 1 Hz, so the state a command set shows only in the next."""
        if self._heartbeat_stale or self.heartbeat is None:
            self.wait_type("HEARTBEAT")
        return self.heartbeat

    def mode(self, autopilot: int = M.MAV_AUTOPILOT_PX4) -> FlightMode | None:
        return mode_from_custom(self._current_heartbeat().custom_mode, autopilot)

    @property
    def armed(self) -> bool:
        return bool(self._current_heartbeat().base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)

    # ----------------------------------------------------------------------------- sending
    def command(self, command: int, *params: float, wall_s: float = 10.0) -> int:
        """COMMAND_LONG to the vehicle; returns the COMMAND_ACK result."""
        p = [*params, *([0.0] * (7 - len(params)))]
        self.conn.mav.command_long_send(self.target, 1, command, 0, *p)
        ack = self.wait(
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == command,
            what=f"COMMAND_ACK of {command}",
            wall_s=wall_s,
        )
        return ack.result

    def set_px4_mode(self, mode: FlightMode) -> int:
        main, sub = px4_split_custom_mode(PX4_CUSTOM_MODE_OF[mode])
        return self.command(M.MAV_CMD_DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)

    def send_setpoint(self, sp: SetpointFields) -> None:
        self.conn.mav.set_position_target_local_ned_send(
            *setpoint_message_args(sp, time_boot_ms=max(self.t_ms, 0), target_system=self.target)
        )

    def stream(self, sp: SetpointFields | None, *, rate_hz: float = 10.0) -> None:
        """Send `sp` every 1/rate_hz simulated seconds from now on (None stops the stream)."""
        first = self._stream is None
        self._stream = sp
        self._period_ms = round(1000.0 / rate_hz)
        if sp is not None and first:
            self._next_ms = max(self.t_ms, 0)
            self._maybe_send_setpoint()

    def _maybe_send_setpoint(self) -> None:
        if self._stream is None or self.t_ms < self._next_ms:
            return
        self.send_setpoint(self._stream)
        self.setpoints_sent += 1
        self.last_setpoint_t_ms = self.t_ms
        self._next_ms += self._period_ms
        if self._next_ms <= self.t_ms:
            self._next_ms = self.t_ms + self._period_ms


def horizontal_speed(m) -> float:
    """Ground speed of a LOCAL_POSITION_NED message [m/s]."""
    return math.hypot(m.vx, m.vy)


def px4_args(client: SimClient, *, speed: float, vehicle: int = 1) -> list[str]:
    return [
        "--vehicle",
        str(vehicle),
        "--speed",
        str(speed),
        "--offboard-port",
        str(client.port),
        "--offboard-local-port",
        "0",
        "--gcs-port",
        "0",
    ]


def fly_offboard(client: SimClient, sp: SetpointFields) -> None:
    """Stream `sp` at 10 Hz: OFFBOARD denied before any setpoint, accepted once one is recent
    (as PX4's commander decides it); then arm."""
    client.wait_type("HEARTBEAT")
    client.sleep_sim(0.2)
    assert client.set_px4_mode(FlightMode.OFFBOARD) == MavResult.DENIED
    assert any("Offboard denied" in text for _, text in client.texts)
    client.stream(sp, rate_hz=10.0)
    client.wait_until_ms(client.t_ms + 150)  # a setpoint or two
    assert client.set_px4_mode(FlightMode.OFFBOARD) == MavResult.ACCEPTED
    assert client.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
    assert client.mode() == FlightMode.OFFBOARD and client.armed


def wait_hold_after_stop(client: SimClient) -> float:
    """Stop the stream; return the simulated seconds until the vehicle says it lost offboard
    (its STATUSTEXT comes at once: an upper bound), after checking its next HEARTBEAT shows
    HOLD (HEARTBEAT comes at 1 Hz)."""
    client.stream(None)
    t_stop = client.last_setpoint_t_ms  # the vehicle received the last setpoint after this
    after = wait_offboard_lost(client)
    client.wait_type("HEARTBEAT")
    assert client.mode() == FlightMode.HOLD
    return (after - t_stop) / 1000.0


def wait_offboard_lost(client: SimClient) -> int:
    """The vehicle time [ms] of the first timestamped message after its "Offboard lost"."""
    client.wait(
        lambda m: m.get_type() == "STATUSTEXT" and "Offboard lost" in m.text,
        what="Offboard lost",
    )
    after = client.wait(lambda m: hasattr(m, "time_boot_ms"), what="a timestamped message")
    return after.time_boot_ms
