"""10^5 hostile datagrams (10^6 with -m slow) at the vehicle: it stays up, serves, never speeds.

The mix: random bytes, CRC-valid frames of every message in the dialect with random payloads
(targets patched to this vehicle so the handlers act on them), valid setpoints whose floats are
random bit patterns (NaN, Inf, huge), bad CRCs, truncated frames, unknown message ids and several
frames per datagram. A PING round trip every window paces the flood so the kernel does not drop
it: what is sent is what the vehicle has to chew through.

What is asserted is behaviour, not throughput (a faster machine floods faster): at checkpoints
spread through the flood the test client's REQUEST_MESSAGE, sent between hostile frames, is ACKed
and followed by position telemetry within a wall-clock bound; after the flood the vehicle still
streams, answers, obeys a mode change, and never reported a speed above its limit.
"""

import math
import os
import random
import socket
import struct
import time

import pytest
from sim_client import M, SimClient, fly_offboard, horizontal_speed, px4_args

from fleetmpc.protocol.mavlink_map import FlightMode, MavResult
from fleetmpc.protocol.mavlink_setpoint import Frame, encode_setpoint

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

WINDOW = 250
CHECKPOINTS = 20
"""Points spread through the flood where a valid request must be answered."""
ANSWER_TIMEOUT_S = 5.0
"""Wall-clock bound on each answer at a checkpoint (the ACK, the telemetry after it) [s]."""
VEHICLE = 1
TARGET_FIELDS = ("target_system", "target_component")


class FrameFactory:
    """Makes hostile frames from a seeded generator."""

    def __init__(self, seed: int) -> None:
        self.rng = random.Random(seed)
        self.mav = mavlink.MAVLink(None, srcSystem=200, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.msg_ids = sorted(mavlink.mavlink_map)
        self.counts = {"valid_crc": 0, "random": 0, "bad_crc": 0, "truncated": 0, "unknown": 0}

    def _raw_v2(self, msg_id: int, payload: bytes, crc_extra: int) -> bytes:
        header = struct.pack("<BBBBBB", len(payload), 0, 0, 0, 200, 1) + msg_id.to_bytes(
            3, "little"
        )
        crc = mavlink.x25crc(header + payload + bytes([crc_extra])).crc
        return b"\xfd" + header + payload + struct.pack("<H", crc)

    def valid_crc(self) -> bytes:
        """Any dialect message, random payload, targets patched to the vehicle, correct CRC."""
        self.counts["valid_crc"] += 1
        msg_id = self.rng.choice(self.msg_ids)
        cls = mavlink.mavlink_map[msg_id]
        payload = self.rng.randbytes(self.rng.randint(1, cls.unpacker.size))
        frame = self._raw_v2(msg_id, payload, cls.crc_extra)
        if self.rng.random() < 0.8:
            try:
                m = self.parser.decode(bytearray(frame))
                for name in TARGET_FIELDS:
                    if name in m.get_fieldnames():
                        setattr(m, name, VEHICLE if name == "target_system" else 1)
                frame = bytes(m.pack(self.mav))
            except Exception:
                pass  # keep the unpatched frame: still CRC-valid
        return frame

    def _float(self) -> float:
        return struct.unpack("<f", self.rng.randbytes(4))[0]

    def setpoint(self) -> bytes:
        """A well-formed velocity setpoint whose values are random float bit patterns."""
        self.counts["valid_crc"] += 1
        frame = self.rng.choice([1, 8, 9, 7])
        mask = self.rng.choice([1479, 2503, 0, 4095])
        scale = self.rng.choice([1.0, 5.0, 1e6])
        values = [
            self._float() if self.rng.random() < 0.5 else scale * self.rng.gauss(0.0, 1.0)
            for _ in range(5)
        ]
        m = self.mav.set_position_target_local_ned_encode(
            0, VEHICLE, 1, frame, mask, 0, 0, 0, *values[:3], 0, 0, 0, values[3], values[4]
        )
        return bytes(m.pack(self.mav))

    def command(self) -> bytes:
        """COMMAND_LONG of a command the vehicle implements, with random float params."""
        self.counts["valid_crc"] += 1
        command = self.rng.choice([400, 176, 22, 21, 511, 512, 520, 11, 0, 65535])
        params = [
            self._float() if self.rng.random() < 0.3 else float(self.rng.randint(-2, 300))
            for _ in range(7)
        ]
        return bytes(self.mav.command_long_encode(VEHICLE, 1, command, 0, *params).pack(self.mav))

    def garbage(self) -> bytes:
        kind = self.rng.randrange(4)
        if kind == 0:
            self.counts["random"] += 1
            data = self.rng.randbytes(self.rng.randint(1, 300))
            return (b"\xfd" if self.rng.random() < 0.5 else b"\xfe") + data
        good = self.valid_crc()
        self.counts["valid_crc"] -= 1
        if kind == 1:
            self.counts["bad_crc"] += 1
            return good[:-1] + bytes([good[-1] ^ 0x5A])
        if kind == 2:
            self.counts["truncated"] += 1
            return good[: self.rng.randrange(1, len(good))]
        self.counts["unknown"] += 1
        return self._raw_v2(60_000 + self.rng.randrange(1000), self.rng.randbytes(20), 0)

    def datagram(self) -> bytes:
        r = self.rng.random()
        if r < 0.35:
            return self.valid_crc()
        if r < 0.55:
            return self.setpoint()
        if r < 0.65:
            return self.command()
        if r < 0.95:
            return self.garbage()
        return b"".join(self.valid_crc() for _ in range(self.rng.randint(2, 4)))


def ping(sock: socket.socket, seq: int, mav) -> bytes:
    return bytes(mav.ping_encode(seq, seq, 0, 0).pack(mav))


def wait_pong(sock: socket.socket, seq: int, parser, *, timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        sock.settimeout(max(deadline - time.monotonic(), 0.001))
        try:
            data = sock.recv(65535)
        except TimeoutError:
            return False
        parser.buf, parser.buf_index = bytearray(), 0
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == "PING" and m.seq == seq and m.target_system == 200:
                return True
    return False


def record_speeds(speeds: list[float], predicate):
    """`predicate`, which also keeps the ground speed of every LOCAL_POSITION_NED it sees."""

    def seen(m) -> bool:
        if m.get_type() == "LOCAL_POSITION_NED":
            speeds.append(horizontal_speed(m))
        return predicate(m)

    return seen


def drain_client(client: SimClient, speeds: list[float]) -> None:
    seen = record_speeds(speeds, lambda m: False)
    while (m := client.pump(timeout_s=0.0)) is not None:
        seen(m)


def request_position(client: SimClient) -> None:
    """Ask the vehicle for one LOCAL_POSITION_NED (REQUEST_MESSAGE) without waiting."""
    request = (M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, *[0] * 6)
    client.conn.mav.command_long_send(VEHICLE, 1, *request)


def check_answers(client: SimClient, speeds: list[float], *, checkpoint: int) -> None:
    """The request sent at `checkpoint` is ACKed, then fresh position telemetry arrives."""
    ack = client.wait(
        record_speeds(
            speeds,
            lambda m: m.get_type() == "COMMAND_ACK" and m.command == M.MAV_CMD_REQUEST_MESSAGE,
        ),
        what=f"COMMAND_ACK of the request at checkpoint {checkpoint}",
        wall_s=ANSWER_TIMEOUT_S,
    )
    assert ack.result == MavResult.ACCEPTED, f"checkpoint {checkpoint}: result {ack.result}"
    # Sent after the ACK (the requested message, or the stream): made after the request.
    lp = client.wait(
        record_speeds(speeds, lambda m: m.get_type() == "LOCAL_POSITION_NED"),
        what=f"LOCAL_POSITION_NED after the ACK at checkpoint {checkpoint}",
        wall_s=ANSWER_TIMEOUT_S,
    )
    assert all(math.isfinite(v) for v in (lp.x, lp.y, lp.z, lp.vx, lp.vy, lp.vz)), lp


@pytest.mark.parametrize("n_frames", [100_000, pytest.param(1_000_000, marks=pytest.mark.slow)])
def test_hostile_frames_do_not_break_the_vehicle(start_sitl, n_frames):
    client = SimClient.listen_udp(target_system=VEHICLE)
    fuzz = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fuzz.bind(("127.0.0.1", 0))
    try:
        sitl, match = start_sitl(*px4_args(client, speed=1.0))
        address = match["endpoints"].split("udp ")[1].split(" ->")[0].rsplit(":", 1)
        target = (address[0], int(address[1]))
        # Fly first, so hostile setpoints and commands meet a vehicle in offboard flight.
        fly_offboard(client, encode_setpoint(1.0, 0.1, frame=Frame.BODY_NED))
        factory = FrameFactory(seed=20240607)
        pinger = mavlink.MAVLink(None, srcSystem=200, srcComponent=1)
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        speeds: list[float] = []
        n_windows = n_frames // WINDOW
        checkpoint_every = n_windows // CHECKPOINTS
        lost_pongs, answered, t0 = 0, 0, time.monotonic()
        for window in range(1, n_windows + 1):
            checkpoint = window % checkpoint_every == checkpoint_every // 2
            for i in range(WINDOW):
                if checkpoint and i == WINDOW // 2:
                    # A valid request in the middle of the hostile frames, as a GCS would send.
                    request_position(client)
                fuzz.sendto(factory.datagram(), target)
            fuzz.sendto(ping(fuzz, window, pinger), target)
            lost_pongs += not wait_pong(fuzz, window, parser)
            if checkpoint:
                check_answers(client, speeds, checkpoint=window // checkpoint_every + 1)
                answered += 1
            drain_client(client, speeds)
            assert sitl.proc.poll() is None, "the vehicle process died"
        flood_s = time.monotonic() - t0
        print(
            f"{n_windows * WINDOW} frames in {flood_s:.1f} s, {answered} checkpoints answered, "
            f"{lost_pongs} pongs lost, mix {factory.counts}"
        )
        assert answered == CHECKPOINTS
        assert lost_pongs <= max(4, n_frames // 25_000)

        # Still serving: fresh heartbeats and telemetry, and commands are answered and obeyed.
        result = client.command(
            M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0
        )
        assert result == MavResult.ACCEPTED
        t_after = client.t_ms
        client.wait(
            record_speeds(speeds, lambda m: m.get_type() == "HEARTBEAT"),
            what="heartbeat after the flood",
        )
        lp = client.wait(
            record_speeds(
                speeds,
                lambda m: m.get_type() == "LOCAL_POSITION_NED" and m.time_boot_ms > t_after,
            ),
            what="fresh LOCAL_POSITION_NED",
        )
        assert all(math.isfinite(v) for v in (lp.x, lp.y, lp.z, lp.vx, lp.vy, lp.vz)), lp
        result = client.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert result == MavResult.ACCEPTED
        client.wait_type("AUTOPILOT_VERSION", wall_s=5)
        client.stream(None)
        assert client.set_px4_mode(FlightMode.HOLD) == MavResult.ACCEPTED
        assert client.mode() == FlightMode.HOLD  # announced before the ACK
        assert max(speeds) <= 2.0 + 1e-6, "commanded speed exceeded the vehicle's limit"
        assert all(math.isfinite(s) for s in speeds)
    finally:
        client.close()
        fuzz.close()
    assert sitl.stop() == 0
    summary = sitl.summary()
    print(f"vehicle counters: {summary}")
    assert summary["errors"] == 0, sitl.stderr
    assert summary["bad"] > 0.05 * n_frames
    assert summary["unknown"] > 0
    assert summary["messages"] > 0.5 * n_frames  # decoded, i.e. not lost before the parser


@pytest.mark.parametrize("seed", [1, 2])
def test_frame_factory_makes_crc_valid_frames(seed):
    """The generator's 'valid' frames really pass pymavlink's CRC check (so the test means it)."""
    factory = FrameFactory(seed)
    parser = mavlink.MAVLink(None)
    for _ in range(500):
        frame = factory.valid_crc()
        assert not isinstance(parser.decode(bytearray(frame)), mavlink.MAVLink_bad_data)
