"""`fleetmpc sitl` as a process: clean shutdown, default ports, errors naming the field."""

import argparse
import signal
import socket
import sys

import pytest
from sim_client import IDEAL_SCENARIO, M, SimClient, free_port

from fleetmpc.errors import ConfigError
from fleetmpc.sitl.cli import add_arguments, build_configs


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


def test_default_ports_stream_to_px4_s_and_bind_clear_of_real_sitls(start_sitl):
    """Vehicle i streams to PX4's offboard port 14540 + i - 1 and the ground station's 14550,
    and binds PX4's ports + 10000 (a real PX4 SITL instance 1 binds 14581 and 18571); an
    ArduPilot-profile vehicle serves ArduPilot SITL's TCP port + 10000."""
    offset = free_offset([24581, 28571, 28572, 15780])
    px4, ready = start_sitl("--vehicle", "2", "--port-offset", str(offset))
    assert ready["endpoints"] == (
        f"offboard udp 127.0.0.1:{24581 + offset} -> 127.0.0.1:{14541 + offset}, "
        f"gcs udp 127.0.0.1:{28571 + offset} -> 127.0.0.1:{14550 + offset}"
    )
    apm, ready = start_sitl(
        "--vehicle", "3", "--autopilot", "ardupilot", "--port-offset", str(offset),
        scenario=IDEAL_SCENARIO.parent / "three.toml",
    )  # fmt: skip
    assert ready["endpoints"] == (
        f"gcs udp 127.0.0.1:{28572 + offset} -> 127.0.0.1:{14550 + offset}, "
        f"ardupilot tcp 127.0.0.1:{15780 + offset}"
    )
    assert px4.stop() == 0 and apm.stop() == 0


def test_ardupilot_streams_to_the_ground_station_only_what_it_is_asked_for(start_sitl):
    """As a real ArduPilot with SRn_ rates of 0 on its ground-station port: HEARTBEATs only,
    until a ground station sets message intervals."""
    gcs = SimClient.listen_udp(target_system=3)
    try:
        sitl, ready = start_sitl(
            "--vehicle", "3", "--autopilot", "ardupilot", "--speed", "4", "--tcp-port", "0",
            "--gcs-port", str(gcs.port), "--gcs-local-port", "0",
            scenario=IDEAL_SCENARIO.parent / "three.toml",
        )  # fmt: skip
        assert f"-> 127.0.0.1:{gcs.port}" in ready["endpoints"]
        kinds = set()
        for _ in range(5):  # five HEARTBEATs (1 Hz of vehicle time): nothing else comes
            heartbeat = gcs.wait(
                lambda m: (
                    kinds.add(m.get_type())
                    or (m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1)
                ),
                what="a HEARTBEAT",
            )
        assert heartbeat.autopilot == M.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert not kinds & {"GLOBAL_POSITION_INT", "ATTITUDE"}, kinds
        assert gcs.command(511, 33, 200_000) == M.MAV_RESULT_ACCEPTED
        gcs.conn.mav.request_data_stream_send(3, 1, M.MAV_DATA_STREAM_EXTRA1, 5, 1)
        seen = set()
        gcs.wait(
            lambda m: seen.add(m.get_type()) or {"GLOBAL_POSITION_INT", "ATTITUDE"} <= seen,
            what="GLOBAL_POSITION_INT and ATTITUDE",
        )
    finally:
        gcs.close()
    assert sitl.stop() == 0


def parse(*argv: str, scenario=IDEAL_SCENARIO) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(["--scenario", str(scenario), *argv])


def test_bound_ports_move_with_the_scenario_network(tmp_path):
    """Two fleets whose [network] tables differ share no port, bound ones included."""
    moved = tmp_path / "moved.toml"
    moved.write_text(
        IDEAL_SCENARIO.read_text()
        + "\n[network]\noffboard_base_port = 24540\ngcs_port = 34550\n"
        + "ardupilot_tcp_base_port = 25760\n"
    )
    px4 = build_configs(parse("--vehicle", "2", scenario=moved))[0]
    assert [(ep.name, ep.local_port, ep.remote_port) for ep in px4.udp] == [
        ("offboard", 34581, 24541),
        ("gcs", 48571, 34550),
    ]
    apm = build_configs(parse("--vehicle", "2", "--autopilot", "ardupilot", scenario=moved))[0]
    assert apm.tcp_port == 25770
    assert [(ep.name, ep.local_port, ep.remote_port) for ep in apm.udp] == [("gcs", 48571, 34550)]
    # The default network: PX4's ports streamed to, PX4's + 10000 bound.
    default = build_configs(parse("--vehicle", "2"))[0]
    assert [(ep.local_port, ep.remote_port) for ep in default.udp] == [
        (24581, 14541),
        (28571, 14550),
    ]


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
        (["--vehicle", "1", "--heading-ready", "nan"], "--heading-ready"),
        (["--vehicle", "1", "--com-disarm-prflt", "-1"], "--com-disarm-prflt"),
        (["--vehicle", "1", "--takeoff-stall", "601"], "--takeoff-stall"),
        (["--vehicle", "1", "--vehicle", "1"], "--vehicle"),
        (["--vehicle", "1", "--vehicle", "2", "--offboard-port", "15000"], "--offboard-port"),
        (["--vehicle", "1", "--vehicle", "2", "--boot-origin", "0,0"], "--boot-origin"),
        (["--vehicle", "1", "--vehicle", "2", "--mavlink-key", "k"], "--mavlink-key"),
    ],
)
def test_bad_options_are_refused_naming_the_option(argv, field):
    with pytest.raises(ConfigError) as error:
        build_configs(parse(*argv))
    assert error.value.field == field


def test_several_vehicles_get_each_their_own_ports_and_identity():
    configs = build_configs(parse("--vehicle", "1", "--vehicle", "2", "--gcs-port", "0"))
    assert [c.vehicle.id for c in configs] == [1, 2]
    assert [[(ep.local_port, ep.remote_port) for ep in c.udp] for c in configs] == [
        [(24580, 14540)],
        [(24581, 14541)],
    ]


def test_config_carries_the_scenario_limits_and_options():
    config = build_configs(parse("--vehicle", "2", "--com-of-loss-t", "0.5", "--gcs-port", "0"))[0]
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
        child = spawn([sys.executable, "-m", "fleetmpc.cli", "sitl",
                       "--scenario", str(IDEAL_SCENARIO),
                       "--gcs-port", "0", "--offboard-port", str(free_port()), *argv])  # fmt: skip
        assert child.proc.wait(timeout=20) == 2
    child.stop()
    assert message in child.stderr
