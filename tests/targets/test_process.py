"""`fleetmpc target` waiting for the fleet epoch: adopted, refused at another speed, timed out."""

import socket
import threading

import pytest
from helpers import free_port_block

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.memory_planbus import InMemoryPlanBus, MemoryHubs
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
