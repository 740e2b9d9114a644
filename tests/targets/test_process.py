"""`fleetmpc target` waiting for the fleet epoch: adopted, refused at another speed, timed out."""

import socket
import threading
import time

import pytest
from helpers import free_port_block

from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHubs
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.messages import GROUND_STATION_ID, TARGET_ID
from fleetmpc.protocol.zenoh_router import open_router
from fleetmpc.targets.process import wait_for_epoch

EPOCH_NS = 1_700_000_000_000_000_000


def _buses(fleet: str = "t"):
    hub = MemoryHubs().hub(fleet)
    target = InMemoryPlanBus(hub, fleet=fleet, vehicle_id=TARGET_ID)
    gcs = InMemoryPlanBus(hub, fleet=fleet, vehicle_id=GROUND_STATION_ID)
    return target, gcs


def test_the_announced_epoch_is_taken() -> None:
    target, gcs = _buses()
    gcs.publish_epoch(epoch_ns=EPOCH_NS, speed=4.0)
    stop = threading.Event()
    assert wait_for_epoch(target, speed=4.0, timeout_s=1.0, stop=stop) == EPOCH_NS


def test_a_stop_request_ends_the_wait() -> None:
    target, _ = _buses()
    stop = threading.Event()
    stop.set()
    assert wait_for_epoch(target, speed=4.0, timeout_s=1.0, stop=stop) is None


def test_an_epoch_at_another_speed_is_a_config_error() -> None:
    target, gcs = _buses()
    gcs.publish_epoch(epoch_ns=EPOCH_NS, speed=2.0)
    with pytest.raises(ConfigError) as info:
        wait_for_epoch(target, speed=4.0, timeout_s=1.0, stop=threading.Event())
    assert info.value.field == "--speed" and "x2" in str(info.value) and "x4" in str(info.value)


def test_no_epoch_in_time_is_a_config_error_naming_the_key() -> None:
    target, _ = _buses("lonely")
    with pytest.raises(ConfigError) as info:
        wait_for_epoch(target, speed=1.0, timeout_s=0.1, stop=threading.Event())
    assert info.value.field == "--epoch-timeout"
    assert "fleetmpc/lonely/epoch" in str(info.value)


def test_the_process_gives_up_with_exit_code_2(processes) -> None:
    port = free_port_block([0], kinds=(socket.SOCK_STREAM,))
    with open_router(port=port):
        target = processes.fleetmpc(
            "target", "target", "--scenario", "scenarios/paper.toml", "--zenoh-connect",
            f"127.0.0.1:{port}", "--fleet", "lonely", "--wait-epoch", "--epoch-timeout", "0.5",
        )  # fmt: skip
        assert target.proc.wait(timeout=30.0) == 2
    err = target.err()
    assert "waiting for the fleet epoch on fleetmpc/lonely/epoch" in err, err
    assert "error: --epoch-timeout: no fleet epoch for fleet 'lonely'" in err, err
    assert "on fleetmpc/lonely/epoch within 0.5 s" in err, err
    assert "Traceback" not in err


def _send_bad_and_good_fixes(port: int) -> None:
    """System 4's GLOBAL_POSITION_INT at 5 Hz, a fix of each fault among them, and system 7's."""
    import math as m

    from pymavlink import mavutil

    from fleetmpc.protocol.local_frame import geodetic_from_ned

    home = (47.397742, 8.545594)
    links = {
        s: mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=s) for s in (4, 7)
    }

    def position(sysid: int, t_ms: int, north: float, east: float = 0.0) -> None:
        lat, lon = geodetic_from_ned(north, east, home_lat_deg=home[0], home_lon_deg=home[1])
        links[sysid].mav.global_position_int_send(
            t_ms, round(lat * 1e7), round(lon * 1e7), 0, 0, 100, 0, 0, 0
        )

    try:
        for k in range(30):
            t_ms = 5000 + 200 * k
            if k == 12:
                position(4, t_ms - 1000, 0.2 * k)  # (backwards)
            elif k == 14:
                position(4, t_ms + 60_000, 0.2 * k)  # (60 s ahead)
            elif k == 16:
                position(4, t_ms, 100_000.0)  # (100 km away)
            elif k == 18:
                lat, lon = geodetic_from_ned(0.2 * k, 0, home_lat_deg=home[0], home_lon_deg=home[1])
                links[4].mav.follow_target_send(
                    t_ms, 0, round(lat * 1e7), round(lon * 1e7), 0.0, [m.nan, 0.0, 0.0],
                    [0.0] * 3, [1.0, 0.0, 0.0, 0.0], [0.0] * 3, [0.0] * 3, 0,
                )  # fmt: skip
            else:
                position(4, t_ms, 0.2 * k)
            position(7, t_ms, 50.0)  # (another system, not followed)
            time.sleep(0.1)
    finally:
        for link in links.values():
            link.close()


def test_a_bad_mavlink_source_is_screened_and_logged(processes) -> None:
    zenoh_port = free_port_block([0], kinds=(socket.SOCK_STREAM,))
    mav_port = free_port_block([0], avoid=[zenoh_port])
    with open_router(port=zenoh_port):
        target = processes.fleetmpc(
            "target", "target", "--scenario", "scenarios/paper.toml", "--zenoh-connect",
            f"127.0.0.1:{zenoh_port}", "--fleet", "bad", "--duration", "8",
            "--source", f"mavlink:udpin:127.0.0.1:{mav_port}", "--sysid", "4",
        )  # fmt: skip
        target.wait_for(r"following mavlink:udpin", stream="err")
        _send_bad_and_good_fixes(mav_port)
        assert target.proc.wait(timeout=30.0) == 0, target.tail()
    err = target.err()
    assert "Traceback" not in err
    for line in (
        "rejected (backwards): system 4 GLOBAL_POSITION_INT",
        "rejected (future): system 4 GLOBAL_POSITION_INT",
        "rejected (too far): system 4 GLOBAL_POSITION_INT",
        "100.0 km from home",
        "rejected (not a number): system 4 FOLLOW_TARGET",
        "rejected (wrong system): system 7 GLOBAL_POSITION_INT",
    ):
        assert line in err, err
    # 30 fixes of system 4, 4 of them bad; all 30 of system 7's rejected (some of the first may
    # be lost before the listener heard its first datagram).
    summary = [ln for ln in err.splitlines() if "accepted," in ln][-1]
    accepted = int(summary.split("target: ")[1].split()[0])
    assert 20 <= accepted <= 26, summary
    for fault in ("backwards 1", "future 1", "too far 1", "not a number 1"):
        assert fault in summary, summary
    assert f"stopped after {accepted} observations" in err
