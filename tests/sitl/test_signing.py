"""MAVLink 2 signing: a signed vehicle acts only on frames signed with its key, counts every
other frame by reason, and its real stream keeps flying through every attack."""

import socket
import time
from pathlib import Path

import pytest
from pymavlink.generator.mavcrc import x25crc
from test_vehicle_server import OFFBOARD, Client, Rig, S, _fly, of_type

from fleetmpc.protocol.mavlink_map import FlightMode, px4_split_custom_mode
from fleetmpc.protocol.mavlink_setpoint import encode_setpoint, setpoint_message_args
from fleetmpc.security.mavlink_signing import (
    Rejection,
    SigningGuard,
    key_from_passphrase,
    sign_outgoing,
    signing_timestamp,
)
from fleetmpc.sitl.mavlink_io import DecodeStats, FrameDecoder, MavlinkEncoder, mavlink

M = mavlink
KEY = key_from_passphrase("the fleet's key")
WRONG = key_from_passphrase("a guess")
FUTURE = signing_timestamp(time.time_ns()) + 10**12  # about 116 days ahead


def _signed_encoder(key: bytes, *, timestamp: int | None = None) -> MavlinkEncoder:
    enc = MavlinkEncoder(system_id=255, component_id=190)
    sign_outgoing(enc.mav, key)
    if timestamp is not None:
        enc.mav.signing.timestamp = timestamp
    return enc


def _setpoint(speed: float) -> callable:
    args = setpoint_message_args(encode_setpoint(speed, 0.0), time_boot_ms=0, target_system=1)
    return lambda mav: mav.set_position_target_local_ned_encode(*args)


def _disarm(mav):
    return mav.command_long_encode(1, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)


def _tampered(frame: bytes) -> bytes:
    """A signed setpoint frame with its first payload byte changed and its CRC made right
    again (the CRC is no secret): only the signature can tell."""
    out = bytearray(frame)
    out[10] ^= 0xFF
    end = len(out) - 13 - 2  # the CRC, before the signature block
    crc = x25crc(out[1:end])
    crc.accumulate([M.MAVLink_set_position_target_local_ned_message.crc_extra])
    out[end : end + 2] = crc.crc.to_bytes(2, "little")
    return bytes(out)


def _signed_rig() -> Rig:
    rig = Rig(signing_key=KEY)
    sign_outgoing(rig.client.enc.mav, KEY)  # the vehicle's own agent has the key
    return rig


def test_a_signed_vehicle_flies_its_signed_stream_through_every_attack():
    rig = _signed_rig()
    server, ap = rig.server, rig.server.autopilot
    attacker_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker_sock.bind(("127.0.0.1", 0))
    attacker_sock.setblocking(False)
    try:
        rig.run(S)
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        _fly(rig, encode_setpoint(1.5, 0.0), 2 * S)
        rig.command(M.MAV_CMD_DO_SET_MODE, 1, *px4_split_custom_mode(OFFBOARD))
        assert ap.armed and ap.mode == FlightMode.OFFBOARD
        _fly(rig, encode_setpoint(1.5, 0.0), 2 * S)
        speed = server.plant.achieved_input[0]
        assert speed == pytest.approx(1.5, abs=0.05)
        commands = server.handler.commands
        # One frame of each attack, each a stop or a disarm, between the real setpoints.
        tampered = _tampered(rig.client.enc.pack(_setpoint(1.5)(rig.client.enc.mav)))
        v1 = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        attacks = {
            Rejection.UNSIGNED: MavlinkEncoder(system_id=255, component_id=190).pack(
                _disarm(mavlink.MAVLink(None, srcSystem=255, srcComponent=190))
            ),
            Rejection.MAVLINK1: _disarm(v1).pack(v1, force_mavlink1=True),
            Rejection.BAD_SIGNATURE: _signed_encoder(WRONG).pack(
                _disarm(_signed_encoder(WRONG).mav)
            ),
        }
        future = _signed_encoder(WRONG, timestamp=FUTURE)
        attacks["forged future"] = future.pack(_disarm(future.mav))
        attacks["tampered"] = bytes(tampered)
        address = rig.client.address
        for name, frame in attacks.items():
            attacker_sock.sendto(frame, address)
            _fly(rig, encode_setpoint(1.5, 0.0), S // 2)
            assert ap.armed and ap.mode == FlightMode.OFFBOARD, name
        # A replay: a frame of the real stream, sent again later by someone who recorded it.
        recorded = rig.client.enc.pack(_setpoint(1.5)(rig.client.enc.mav))
        rig.client.sock.sendto(recorded, address)
        _fly(rig, encode_setpoint(1.5, 0.0), S // 2)
        accepted = server.signing.accepted
        attacker_sock.sendto(recorded, address)
        rig.run(S // 10)
        assert server.signing.accepted == accepted
        _fly(rig, encode_setpoint(1.5, 0.0), S)
        assert ap.armed and ap.mode == FlightMode.OFFBOARD
        assert server.plant.achieved_input[0] == pytest.approx(speed, abs=0.05)
        assert server.handler.commands == commands, "no attacker's command was acted on"
        rejected = server.signing.rejected
        assert rejected[Rejection.UNSIGNED] == 1
        assert rejected[Rejection.MAVLINK1] == 1
        assert rejected[Rejection.BAD_SIGNATURE] == 3  # wrong key, forged future, tampered
        assert rejected[Rejection.REPLAY] == 1
        assert server.signing.accepted > 50
    finally:
        attacker_sock.close()
        rig.close()


def test_the_vehicle_announces_each_rejection_once_and_signs_what_it_sends():
    rig = _signed_rig()
    try:
        rig.run(S)
        unsigned = Client(rig.sock, rig.client.address)  # no key
        for _ in range(3):
            unsigned.send(_disarm)
        msgs = rig.run(S)
        texts = [m.text for m in of_type(msgs, "STATUSTEXT")]
        assert texts == ["signing: unsigned, refused (255/190)"]
        guard = SigningGuard(KEY)
        raw = [bytes(m.get_msgbuf()) for m in msgs]
        assert raw and all(guard.verdict(frame) is None for frame in raw), "all signed, fresh"
        assert rig.server.signing.rejected[Rejection.UNSIGNED] == 3
    finally:
        rig.close()


def test_another_vehicles_signed_commands_are_ignored_not_refused():
    """A ground station's UDP server link sends each vehicle's commands (signed with that
    vehicle's key) to every vehicle it hears: a vehicle ignores those for another system
    without a word, and still refuses a frame for itself signed with another key."""
    rig = _signed_rig()
    try:
        rig.run(S)
        other = Client(rig.sock, rig.client.address)
        sign_outgoing(other.enc.mav, WRONG)  # vehicle 2's key, as the ground station signs
        for _ in range(3):
            other.send(
                lambda mav: mav.command_long_encode(
                    2, 1, M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 33, 200_000, 0, 0, 0, 0, 0
                )
            )
        msgs = rig.run(S)
        assert [m.text for m in of_type(msgs, "STATUSTEXT")] == []
        assert rig.server.signing_rejected == 0
        other.send(_disarm)  # for vehicle 1, with the wrong key
        texts = [m.text for m in of_type(rig.run(S), "STATUSTEXT")]
        assert texts == ["signing: bad signature, refused (255/190)"]
        assert rig.server.signing_rejected == 1
    finally:
        rig.close()


def test_setup_signing_changes_the_key_only_on_a_trusted_link_and_only_while_disarmed():
    rig = Rig()  # no key: signing off, and no link is trusted to set one
    try:
        rig.run(S)
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, list(KEY), 1))
        msgs = rig.run(S // 10)
        assert rig.server.signing is None, "a hostile frame cannot lock the owner out"
        assert any("no trusted link" in m.text for m in of_type(msgs, "STATUSTEXT"))
    finally:
        rig.close()
    rig = _signed_rig()
    new_key = key_from_passphrase("the next key")
    try:
        rig.run(S)
        forger = _signed_encoder(WRONG)
        rig.client.sock.sendto(
            forger.pack(forger.mav.setup_signing_encode(1, 1, [0] * 32, 0)), rig.client.address
        )
        rig.run(S // 10)
        assert (
            rig.server.signing is not None
            and rig.server.signing.rejected[Rejection.BAD_SIGNATURE] == 1
        )
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert rig.server.autopilot.armed
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, list(new_key), 1))
        msgs = rig.run(S // 10)
        assert "ERROR: Won't setup signing when armed" in [
            m.text for m in of_type(msgs, "STATUSTEXT")
        ]
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        assert not rig.server.autopilot.armed
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, list(new_key), 1))
        rig.run(S // 10)
        sign_outgoing(rig.client.enc.mav, new_key)  # the owner changed the key
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert rig.server.autopilot.armed, "the new key flies"
        rig.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, [0] * 32, 0))
        rig.run(S // 10)
        assert rig.server.signing is None, "an all-zero key turns signing off"
    finally:
        rig.close()


def _frames(enc: MavlinkEncoder, count: int) -> list[bytes]:
    return [enc.pack(enc.mav.heartbeat_encode(6, 8, 0, 0, 4)) for _ in range(count)]


def test_a_forged_future_frame_locks_stock_pymavlink_out_but_not_our_guard():
    """pymavlink 2.4.50 stores a stream's timestamp before it compares the signature: one
    forged frame with a far-future timestamp makes every real frame after it a 'replay'."""
    real = _signed_encoder(KEY)
    real_frames = _frames(real, 5)
    forger = _signed_encoder(WRONG, timestamp=FUTURE)
    forged = _frames(forger, 1)[0]

    stock = mavlink.MAVLink(None)
    stock.robust_parsing = True
    stock.signing.secret_key = KEY  # pymavlink's own check, as shipped
    heard = [m for m in stock.parse_buffer(real_frames[0]) or [] if m.get_type() == "HEARTBEAT"]
    assert len(heard) == 1
    stock.parse_buffer(forged)
    after = [
        m
        for frame in real_frames[1:]
        for m in stock.parse_buffer(frame) or []
        if m.get_type() == "HEARTBEAT"
    ]
    assert after == [], "stock pymavlink: the real stream is locked out"

    guard = SigningGuard(KEY)
    decoder = FrameDecoder(DecodeStats())
    verdicts = [
        guard.admit(m) for frame in (real_frames[0], forged, *real_frames[1:])
        for m in decoder.datagram(frame)
    ]  # fmt: skip
    assert verdicts == [True, False, True, True, True, True]
    assert guard.rejected == {Rejection.BAD_SIGNATURE: 1}


def test_key_files_are_private_one_word_and_errors_name_the_option(tmp_path):
    from fleetmpc.errors import ConfigError
    from fleetmpc.security.mavlink_signing import read_key_file, write_key_file

    path = write_key_file(tmp_path / "k.key")
    assert path.stat().st_mode & 0o777 == 0o600
    assert len(read_key_file(path)) == 32
    with pytest.raises(ConfigError, match="exists"):
        write_key_file(path)
    path.chmod(0o644)
    with pytest.raises(ConfigError, match=r"--mavlink-key: .*readable by others"):
        read_key_file(path)
    with pytest.raises(ConfigError, match="no spaces"):
        write_key_file(tmp_path / "spaced.key", "two words")
    with pytest.raises(ConfigError, match=r"--mavlink-key: cannot read"):
        read_key_file(tmp_path / "missing.key")


def test_fleetmpc_keys_makes_every_secret_of_a_fleet_privately(tmp_path):
    from fleetmpc.cli import main

    out, paper = tmp_path / "secrets", str(Path(__file__).parents[2] / "scenarios" / "paper.toml")
    assert main(["keys", paper, "-o", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert [n for n in names if n.startswith("mavlink-")] == [
        "mavlink-1.key", "mavlink-2.key", "mavlink-3.key",
    ]  # fmt: skip
    assert {"zenoh-agent-1.json5", "zenoh-gcs.json5", "zenoh-users.txt"} <= set(names)
    assert out.stat().st_mode & 0o777 == 0o700
    assert all(p.stat().st_mode & 0o777 == 0o600 for p in out.iterdir())
    assert main(["keys", paper, "-o", str(out)]) == 2, "not over a set"


def test_an_unsigned_sender_gets_no_telemetry_from_a_signed_vehicle():
    rig = _signed_rig()
    other = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    other.bind(("127.0.0.1", 0))
    other.setblocking(False)
    try:
        stranger = Client(other, rig.client.address)  # no key
        stranger.send(lambda mav: mav.heartbeat_encode(6, 8, 0, 0, 4))
        assert rig.run(S, stranger) == [], "a signed vehicle streams only to signed peers"
        sign_outgoing(stranger.enc.mav, KEY)
        stranger.send(lambda mav: mav.heartbeat_encode(6, 8, 0, 0, 4))
        assert of_type(rig.run(S, stranger), "ATTITUDE"), "a peer that signs is streamed to"
    finally:
        other.close()
        rig.close()


def test_setup_signing_with_the_same_key_keeps_the_replay_table_and_bounds_the_timestamp():
    rig = _signed_rig()
    try:
        rig.run(S)
        recorded = rig.client.enc.pack(_disarm(rig.client.enc.mav))
        rig.client.sock.sendto(recorded, rig.client.address)
        rig.run(S // 10)
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, list(KEY), 1))
        rig.run(S // 10)
        rig.client.sock.sendto(recorded, rig.client.address)  # replayed after the "new" key
        rig.run(S // 10)
        assert rig.server.signing.rejected[Rejection.REPLAY] == 1
        rig.client.send(lambda mav: mav.setup_signing_encode(1, 1, list(WRONG), 1 << 48))
        msgs = rig.run(S // 10)
        assert rig.server.signing.has_key(KEY), "a timestamp beyond 48 bits is refused"
        assert any("over 48 bits" in m.text for m in of_type(msgs, "STATUSTEXT"))
    finally:
        rig.close()
