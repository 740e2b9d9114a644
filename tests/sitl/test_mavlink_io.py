"""MAVLink bytes in and out: a setpoint survives the wire, and the decoder shrugs off garbage."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetmpc.protocol.mavlink_setpoint import (
    Frame,
    UnicycleDemand,
    decode_setpoint,
    encode_setpoint,
    setpoint_message_args,
)
from fleetmpc.sitl.handlers import setpoint_fields
from fleetmpc.sitl.mavlink_io import DecodeStats, FrameDecoder, MavlinkEncoder, mavlink


def client_frame(message_of) -> bytes:
    enc = MavlinkEncoder(system_id=255, component_id=190)
    return enc.pack(message_of(enc.mav))


def setpoint_frame(sp) -> bytes:
    return client_frame(
        lambda mav: mav.set_position_target_local_ned_encode(
            *setpoint_message_args(sp, time_boot_ms=0, target_system=1)
        )
    )


HEARTBEAT = client_frame(lambda mav: mav.heartbeat_encode(6, 8, 0, 0, 4))


@settings(max_examples=200)
@given(
    speed=st.floats(-20, 20),
    yaw_rate=st.floats(-5, 5),
    heading=st.floats(-math.pi, math.pi),
    frame=st.sampled_from(list(Frame)),
)
def test_a_unicycle_setpoint_survives_the_wire(speed, yaw_rate, heading, frame):
    sent = encode_setpoint(speed, yaw_rate, frame=frame, heading_rad=heading)
    stats = DecodeStats()
    (message,) = FrameDecoder(stats).datagram(setpoint_frame(sent))
    assert message.get_header().msgId == mavlink.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED
    demand = decode_setpoint(setpoint_fields(message), heading_rad=heading, yaw_gain_1_s=1.0)
    assert isinstance(demand, UnicycleDemand)
    # float32 on the wire: a few ulps of the largest component
    assert demand.speed_m_s == pytest.approx(speed, abs=1e-5)
    assert demand.yaw_rate_rad_s == pytest.approx(yaw_rate, abs=1e-6)
    assert stats.messages == 1 and stats.bad_frames == 0


def test_bad_crc_truncation_and_unknown_ids_are_dropped_and_counted():
    stats = DecodeStats()
    decoder = FrameDecoder(stats)
    bad_crc = HEARTBEAT[:-1] + bytes([HEARTBEAT[-1] ^ 0xFF])
    unknown = bytearray(HEARTBEAT)
    unknown[7:10] = (60_123).to_bytes(3, "little")
    assert decoder.datagram(bad_crc) == []
    assert decoder.datagram(HEARTBEAT[:7]) == []  # truncated: must not poison the next datagram
    assert [m.get_type() for m in decoder.datagram(HEARTBEAT)] == ["HEARTBEAT"]
    assert decoder.datagram(bytes(unknown)) == []
    assert decoder.datagram(b"") == []
    assert (stats.messages, stats.bad_frames, stats.unknown) == (1, 1, 1)


@settings(max_examples=200)
@given(
    noise=st.lists(st.binary(max_size=40), min_size=3, max_size=3),
    cuts=st.lists(st.integers(0, 400), max_size=6),
)
def test_a_tcp_stream_resynchronises_after_garbage(noise, cuts):
    """Frames between arbitrary garbage, delivered in arbitrary chunks, all come out.

    Garbage is kept free of frame markers, so it cannot swallow the frame after it.
    """
    clean = [n.replace(b"\xfd", b"").replace(b"\xfe", b"") for n in noise]
    stream = clean[0] + HEARTBEAT + clean[1] + HEARTBEAT + clean[2] + HEARTBEAT
    decoder = FrameDecoder(DecodeStats())
    bounds = sorted({0, len(stream), *(c for c in cuts if c < len(stream))})
    out = []
    for a, b in zip(bounds, bounds[1:], strict=False):
        out.extend(decoder.stream(stream[a:b]))
    assert [m.get_type() for m in out] == ["HEARTBEAT"] * 3


@given(data=st.binary(max_size=600))
def test_random_bytes_never_raise(data):
    decoder = FrameDecoder(DecodeStats())
    for m in decoder.datagram(data) + decoder.stream(data):
        assert not isinstance(m, mavlink.MAVLink_bad_data | mavlink.MAVLink_unknown)


def test_mavlink1_frames_are_understood():
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = bytes(mav.heartbeat_encode(6, 8, 0, 0, 4).pack(mav, force_mavlink1=True))
    assert frame[0] == 0xFE
    (m,) = FrameDecoder(DecodeStats()).datagram(frame)
    assert m.get_type() == "HEARTBEAT"
