"""`fleetmpc sitl` as a process: clean shutdown, default ports, errors naming the field."""

import argparse
import signal
import socket
import sys

import pytest
from sim_client import IDEAL_SCENARIO, SimClient, free_port

from onboard.core.errors import ConfigError
from sitl.cli import add_arguments, build_config


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signals_stop_the_vehicle_cleanly(start_sitl, sig):
    client = SimClient.listen_udp(target_system=1)
    local = free_port()
    try:
        sitl, _ = start_sitl(
            "--vehicle", "1", "--speed", "2", "--offboard-port", str(client.port),
            "--offboard-local-port", str(local), "--gcs-port", "0",
        )  # fmt: skip
        client.wait_type("HEARTBEAT")
    finally:
        client.close()
    assert sitl.stop(sig, timeout_s=5) == 0
    assert "fleetmpc sitl: stopped vehicle 1" in sitl.stderr
    assert "Traceback" not in sitl.stderr
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", local))  # the socket was closed


def free_offset(ports: list[int]) -> int:
    """A port offset at which all `ports` are free."""
    for offset in range(20_000, 40_000, 137):
        try:
            for port in ports:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
                    s.bind(("127.0.0.1", port + offset))
                with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                    s.bind(("127.0.0.1", port + offset))
        except OSError:
            continue
        return offset
    raise AssertionError("no free port offset")


def test_default_ports_follow_px4_and_ardupilot_sitl(start_sitl):
    offset = free_offset([14581, 18571, 18572, 5780])
    px4, ready = start_sitl("--vehicle", "2", "--port-offset", str(offset))
    assert ready["endpoints"] == (
        f"offboard udp 127.0.0.1:{14581 + offset} -> 127.0.0.1:{14541 + offset}, "
        f"gcs udp 127.0.0.1:{18571 + offset} -> 127.0.0.1:{14550 + offset}"
    )
    apm, ready = start_sitl(
        "--vehicle", "3", "--autopilot", "ardupilot", "--port-offset", str(offset),
        scenario=IDEAL_SCENARIO.parent / "three.toml",
    )  # fmt: skip
    assert ready["endpoints"] == (
        f"gcs udp 127.0.0.1:{18572 + offset} -> 127.0.0.1:{14550 + offset}, "
        f"ardupilot tcp 127.0.0.1:{5780 + offset}"
    )
    assert px4.stop() == 0 and apm.stop() == 0


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(["--scenario", str(IDEAL_SCENARIO), *argv])


@pytest.mark.parametrize(
    ("argv", "field"),
    [
        (["--vehicle", "9"], "vehicle"),
        (["--vehicle", "1", "--com-of-loss-t", "0"], "--com-of-loss-t"),
        (["--vehicle", "1", "--com-of-loss-t", "nan"], "--com-of-loss-t"),
        (["--vehicle", "1", "--offboard-port", "0"], "--offboard-port"),
        (["--vehicle", "1", "--gcs-local-port", "70000"], "--gcs-local-port"),
        (["--vehicle", "1", "--autopilot", "ardupilot", "--tcp-port", "-1"], "--tcp-port"),
        (["--vehicle", "1", "--position-ready", "-1"], "--position-ready"),
    ],
)
def test_bad_options_are_refused_naming_the_option(argv, field):
    with pytest.raises(ConfigError) as error:
        build_config(parse(*argv))
    assert error.value.field == field


def test_config_carries_the_scenario_limits_and_options():
    config = build_config(parse("--vehicle", "2", "--com-of-loss-t", "0.5", "--gcs-port", "0"))
    assert config.vehicle.id == 2 and config.tick_ns == 20_000_000
    assert config.autopilot.offboard_loss_timeout_ns == 500_000_000
    assert config.autopilot.takeoff_altitude_m == 5.0
    assert config.autopilot.speed_limit_m_s == 2.0
    assert [ep.name for ep in config.udp] == ["offboard"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--vehicle", "7"], "vehicle: no vehicle with id 7"),
        (["--vehicle", "1", "--speed", "0"], "speed: must be"),
        (["--vehicle", "1", "--offboard-local-port", "{busy}"], "offboard-local-port: cannot bind"),
    ],
)
def test_errors_exit_with_code_2_and_a_message(spawn, argv, message):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        argv = [a.replace("{busy}", str(busy.getsockname()[1])) for a in argv]
        child = spawn([sys.executable, "-m", "gcs.cli", "sitl", "--scenario", str(IDEAL_SCENARIO),
                       "--gcs-port", "0", "--offboard-port", str(free_port()), *argv])  # fmt: skip
        assert child.proc.wait(timeout=20) == 2
    child.stop()
    assert message in child.stderr
