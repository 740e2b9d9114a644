"""The in-process Zenoh router: two clients talk through it; the command line stops on SIGTERM."""

import json
import signal
import socket

import numpy as np
import pytest
from helpers import free_port, router_process, wait_until

from fleetmpc.bus.open_bus import open_plan_bus
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.plan import Plan
from fleetmpc.protocol.zenoh_router import open_router, router_config

PERIOD_NS = 200_000_000


def make_plan(vehicle_id: int, stamp_ns: int) -> Plan:
    return Plan(
        vehicle_id=vehicle_id,
        stamp_ns=stamp_ns,
        period_ns=PERIOD_NS,
        states=np.full((4, 3), float(vehicle_id)),
        inputs=np.full((3, 2), 0.5),
    )


def test_router_config_listens_only_where_told_and_never_scouts() -> None:
    conf = router_config(port=7447)
    assert json.loads(conf.get_json("mode")) == "router"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("connect/endpoints")) == []
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    with pytest.raises(ConfigError) as info:
        router_config(port=0)
    assert info.value.field == "port"


def test_two_clients_exchange_plans_and_targets_through_the_router() -> None:
    port = free_port(socket.SOCK_STREAM)
    url = f"zenoh://127.0.0.1:{port}?mode=client"
    with (
        open_router(port=port),
        open_plan_bus(url, fleet="routed", vehicle_id=1) as a,
        open_plan_bus(url, fleet="routed", vehicle_id=2) as b,
    ):
        step = [0]

        def publish() -> None:
            step[0] += 1
            now = step[0] * PERIOD_NS
            a.publish_plan(make_plan(1, now))
            b.publish_plan(make_plan(2, now))
            a.publish_target(stamp_ns=now, north_m=1.0, east_m=2.0, velocity_m_s=(0.5, 0.5))

        def exchanged() -> bool:
            now = step[0] * PERIOD_NS
            return (
                1 in b.latest_plans(now, 10**9)
                and 2 in a.latest_plans(now, 10**9)
                and b.latest_target(now, 10**9) is not None
            )

        assert wait_until(exchanged, tick=publish)
        now = step[0] * PERIOD_NS
        assert b.latest_plans(now, 10**9)[1].states.tobytes() == make_plan(1, 0).states.tobytes()
        assert b.latest_target(now, 10**9).velocity_m_s == (0.5, 0.5)
        assert a.counters().rejected_total == 0 and b.counters().rejected_total == 0


def test_router_command_line_serves_until_sigterm() -> None:
    port = free_port(socket.SOCK_STREAM)
    with router_process("--port", str(port)) as proc:
        assert proc.stdout.readline().strip() == f"zenoh router listening on tcp/127.0.0.1:{port}"
        url = f"zenoh://127.0.0.1:{port}?mode=client"
        with (
            open_plan_bus(url, fleet="cli", vehicle_id=1),
            open_plan_bus(url, fleet="cli", vehicle_id=2),
        ):
            pass  # a client session opens only if the router is up
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
