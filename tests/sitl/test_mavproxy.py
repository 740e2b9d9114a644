"""MAVProxy, run headless, routes clients to the simulated vehicle; the flows still work."""

import asyncio
import math
import os
import re
import socket
import sys
from pathlib import Path

import pytest
from mavsdk.asyncio.plugins.telemetry import FlightMode
from mavsdk_flow import FORWARD_M_S, YAWSPEED_DEG_S, mavsdk_flight
from sim_client import SimClient, fly_offboard, free_port, horizontal_speed, wait_hold_after_stop

from fleetmpc.protocol.mavlink_setpoint import Frame, encode_setpoint
from fleetmpc.security.mavlink_signing import write_key_file
from fleetmpc.sitl.mavlink_io import MavlinkEncoder

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"


def _mavproxy(master_port: int, *outs: int, state_dir: Path, modules: str = "") -> list[str]:
    return [
        sys.executable,
        str(MAVPROXY),
        f"--master=udpin:127.0.0.1:{master_port}",
        *(f"--out=udpout:127.0.0.1:{port}" for port in outs),
        "--daemon",
        "--non-interactive",
        f"--default-modules={modules}",
        f"--state-basedir={state_dir}",
    ]


def test_mavproxy_routes_pymavlink_and_mavsdk_clients(start_sitl, spawn, tmp_path):
    master_port, mavsdk_port = free_port(), free_port()
    client = SimClient.listen_udp(target_system=1)
    try:
        sitl, _ = start_sitl(
            "--vehicle", "1", "--offboard-port", str(master_port), "--offboard-local-port", "0",
            "--gcs-port", "0",
        )  # fmt: skip
        spawn(_mavproxy(master_port, client.port, mavsdk_port, state_dir=tmp_path), cwd=tmp_path)
        # The OFFBOARD rules through the router: denied, accepted after 1 s, HOLD on loss.
        fly_offboard(client, encode_setpoint(1.0, 0.1, frame=Frame.BODY_NED))
        client.sleep_sim(1.0)
        assert horizontal_speed(client.wait_type("LOCAL_POSITION_NED")) == pytest.approx(1.0)
        hold_after_s = wait_hold_after_stop(client)
        print(f"through MAVProxy: HOLD {hold_after_s:.3f} s (simulated) after the last setpoint")
        assert 1.0 <= hold_after_s <= 1.1

        # MAVSDK through the same router.
        result = asyncio.run(mavsdk_flight(mavsdk_port))
    finally:
        client.close()
    print({k: v for k, v in result.items() if k not in ("home", "position", "ned")})
    assert result["system_id"] == 1 and result["autopilot"] == "PX4"
    assert result["start"] == "accepted"
    assert result["mode_in_flight"] == FlightMode.OFFBOARD
    assert result["speed_m_s"] == pytest.approx(FORWARD_M_S, rel=0.10)
    assert result["yaw_rate_rad_s"] == pytest.approx(math.radians(YAWSPEED_DEG_S), rel=0.10)
    assert result["mode_after_stop"] == FlightMode.HOLD
    assert sitl.stop() == 0
    assert sitl.summary()["errors"] == 0


def test_mavproxy_holding_the_key_flies_a_signed_vehicle_for_an_unsigned_client(
    start_sitl, spawn, tmp_path
):
    """The vehicle signs; MAVProxy finds the passphrase of its master link in
    ~/.mavproxy/signing.keys and signs what it forwards, so a client without the key flies the
    vehicle through it; an unsigned frame sent around MAVProxy is refused."""
    passphrase = "a-passphrase-for-vehicle-1"
    key_file = write_key_file(tmp_path / "mavlink-1.key", passphrase)
    master_port = free_port()
    client = SimClient.listen_udp(target_system=1)
    rogue = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sitl, ready = start_sitl(
            "--vehicle", "1", "--offboard-port", str(master_port), "--offboard-local-port", "0",
            "--gcs-port", "0", "--mavlink-key", str(key_file),
        )  # fmt: skip
        vehicle_port = int(re.search(r"offboard udp 127.0.0.1:(\d+)", ready["endpoints"])[1])
        home = tmp_path / "home"
        (home / ".mavproxy").mkdir(parents=True)
        keys = home / ".mavproxy" / "signing.keys"
        keys.write_text(f"udpin:127.0.0.1:{master_port} {passphrase}\n")
        keys.chmod(0o600)
        spawn(
            _mavproxy(master_port, client.port, state_dir=tmp_path, modules="signing"),
            cwd=tmp_path,
            env={**os.environ, "HOME": str(home)},
        )
        fly_offboard(client, encode_setpoint(1.0, 0.1, frame=Frame.BODY_NED))
        client.sleep_sim(1.0)
        assert horizontal_speed(client.wait_type("LOCAL_POSITION_NED")) == pytest.approx(1.0)
        enc = MavlinkEncoder(system_id=255, component_id=190)
        disarm = enc.mav.command_long_encode(1, 1, 400, 0, 0, 21196, 0, 0, 0, 0, 0)
        rogue.sendto(enc.pack(disarm), ("127.0.0.1", vehicle_port))
        client.sleep_sim(1.0)
        assert client.armed and horizontal_speed(
            client.wait_type("LOCAL_POSITION_NED")
        ) == pytest.approx(1.0)
    finally:
        rogue.close()
        client.close()
    assert sitl.stop() == 0
    summary = re.search(r"signing: accepted (\d+), rejected (.*?) \(", sitl.stderr)
    assert summary is not None, sitl.stderr
    assert int(summary[1]) > 20 and summary[2] == "unsigned 1"
