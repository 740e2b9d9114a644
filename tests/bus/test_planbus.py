"""PlanBus: receive rules on the in-memory fake, and the same bus for real over loopback Zenoh."""

import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, closing

import helpers
import numpy as np
import pytest
import zenoh
from helpers import wait_until

from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHub, MemoryHubs
from fleetmpc.bus.open_bus import open_plan_bus
from fleetmpc.bus.planbus import PlanBus, PlanBusClosedError, PlanBusError
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.codec import decode, encode
from fleetmpc.protocol.key_expressions import plan_key, target_observation_key
from fleetmpc.protocol.messages import (
    GROUND_STATION_ID,
    LearnedParams,
    MessageKind,
    PlanMessage,
    PlanStatus,
    RejectReason,
    StatusMessage,
    VehicleMode,
    VehicleStatus,
)
from fleetmpc.protocol.plan import Plan
from fleetmpc.protocol.zenoh_config import ZenohOptions

FLEET = "test"
PERIOD_NS = 200_000_000
S = 1_000_000_000


def make_plan(vehicle_id: int, stamp_ns: int, *, m: int = 5, offset: float = 0.0) -> Plan:
    j = np.arange(m + 1.0)
    states = np.column_stack([j + offset + vehicle_id, -j * 0.5, np.full(m + 1, 0.1 * vehicle_id)])
    return Plan(
        vehicle_id=vehicle_id,
        stamp_ns=stamp_ns,
        period_ns=PERIOD_NS,
        states=states,
        inputs=np.tile([1.0, 0.05 * vehicle_id], (m, 1)),
    )


def same_plan(a: Plan, b: Plan) -> bool:
    return (
        (a.vehicle_id, a.stamp_ns, a.period_ns) == (b.vehicle_id, b.stamp_ns, b.period_ns)
        and a.states.tobytes() == b.states.tobytes()
        and a.inputs.tobytes() == b.inputs.tobytes()
    )


def raw_plan(vehicle_id: int, seq: int, stamp_ns: int) -> bytes:
    return encode(PlanMessage(seq=seq, plan=make_plan(vehicle_id, stamp_ns)))


def check_balance(bus: PlanBus) -> None:
    c = bus.counters()
    parts = (
        c.accepted + c.duplicates + c.out_of_order + c.own_ignored + c.filtered + c.rejected_total
    )
    assert c.received == parts, c


@pytest.fixture
def hub_buses() -> Iterator[tuple[MemoryHub, list[PlanBus]]]:
    hubs = MemoryHubs()
    buses = [open_plan_bus("mem://sim", fleet=FLEET, vehicle_id=i, hubs=hubs) for i in (1, 2, 3)]
    yield hubs.hub("sim"), buses
    for bus in buses:
        bus.close()


# In-memory fake ---------------------------------------------------------------------------


def test_three_buses_on_one_hub_exchange_plans(hub_buses) -> None:
    _, buses = hub_buses
    sent = {b.vehicle_id: make_plan(b.vehicle_id, 2 * S) for b in buses}
    for bus in buses:
        bus.publish_plan(sent[bus.vehicle_id], PlanStatus(first_c_norm=0.5))
    for bus in buses:
        got = bus.latest_plans(2 * S, 0)
        assert sorted(got) == sorted({1, 2, 3} - {bus.vehicle_id})
        assert all(same_plan(got[i], sent[i]) for i in got)
        c = bus.counters()
        assert (c.published, c.received, c.accepted, c.own_ignored) == (1, 2, 2, 0)
        assert bus.latest_plan_messages(2 * S, 0)[next(iter(got))].status.first_c_norm == 0.5
        check_balance(bus)


def test_a_bus_listening_near_drops_far_plans_unread_and_forgets_their_senders(hub_buses) -> None:
    hub, (bus, *_) = hub_buses
    bus.listen_near((0.0, 0.0), 20.0, always=frozenset({9}))
    near, far, linked = (
        make_plan(7, 2 * S, offset=0.0),  # starts at (7, 0): near
        make_plan(8, 2 * S, offset=50.0),  # starts at (58, 0): far
        make_plan(9, 2 * S, offset=50.0),  # far, but always heard (a formation neighbour)
    )
    for seq, plan in enumerate((near, far, linked), start=1):
        hub.put(plan_key(FLEET, plan.vehicle_id), encode(PlanMessage(seq=seq, plan=plan)))
    assert sorted(bus.latest_plans(2 * S, S)) == [7, 9]
    assert bus.counters().filtered == 1
    # Vehicle 7 flies away: its next plan is dropped and its last one forgotten.
    gone = make_plan(7, 3 * S, offset=100.0)
    hub.put(plan_key(FLEET, 7), encode(PlanMessage(seq=10, plan=gone)))
    assert sorted(bus.latest_plans(3 * S, 2 * S)) == [9]
    # Garbage on a plan key is still rejected, not filtered.
    hub.put(plan_key(FLEET, 7), b"FM\x02\x01\x07" + bytes(60))
    c = bus.counters()
    assert (c.filtered, c.rejected_total) == (2, 1)
    check_balance(bus)


def test_far_plans_of_vehicles_not_held_are_dropped_without_a_decode() -> None:
    decoded = []

    def counting(payload: bytes, kind: MessageKind):
        decoded.append(kind)
        return decode(payload, expect=kind)

    hub = MemoryHub("sim")
    hub.decode = counting  # (the decoder its buses are built with)
    with InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1) as bus:
        bus.listen_near((0.0, 0.0), 20.0)
        for seq, offset in enumerate((0.0, 50.0, 60.0), start=1):  # near, then far twice
            hub.put(
                plan_key(FLEET, 7),
                encode(PlanMessage(seq=seq, plan=make_plan(7, S, offset=offset))),
            )
        for seq in (1, 2):  # never near: never decoded
            hub.put(
                plan_key(FLEET, 8), encode(PlanMessage(seq=seq, plan=make_plan(8, S, offset=50.0)))
            )
        # The first far plan of vehicle 7, which was held, is decoded (it makes the bus forget).
        assert len(decoded) == 2
        assert bus.latest_plans(S, S) == {}
        c = bus.counters()
        assert (c.received, c.accepted, c.filtered) == (5, 1, 4)
        check_balance(bus)


def test_statuses_reach_the_ground_station_and_not_the_agents() -> None:
    hubs = MemoryHubs()
    agent = open_plan_bus("mem://s", fleet=FLEET, vehicle_id=1, hubs=hubs)
    ground = open_plan_bus("mem://s", fleet=FLEET, vehicle_id=GROUND_STATION_ID, hubs=hubs)
    other = open_plan_bus("mem://s", fleet=FLEET, vehicle_id=2, hubs=hubs)
    try:
        other.publish_status(VehicleStatus(mode=VehicleMode.OFFBOARD, armed=True), stamp_ns=2 * S)
        assert 2 in ground.latest_statuses(2 * S, S)
        assert agent.latest_statuses(2 * S, S) == {} and agent.counters().received == 0
    finally:
        for bus in (agent, ground, other):
            bus.close()


def test_duplicates_and_out_of_order_are_dropped_and_counted(hub_buses) -> None:
    hub, (bus, *_) = hub_buses
    key = plan_key(FLEET, 7)
    for seq, stamp in [(5, 10 * S), (5, 10 * S), (6, 11 * S), (3, 8 * S), (6, 11 * S), (7, 12 * S)]:
        hub.put(key, raw_plan(7, seq, stamp))
    c = bus.counters()
    assert (c.accepted, c.duplicates, c.out_of_order, c.sender_restarts) == (3, 2, 1, 0)
    assert bus.latest_plans(12 * S, S)[7].stamp_ns == 12 * S
    hub.put(key, raw_plan(7, 4, 11 * S))  # older seq and older stamp: out of order
    assert bus.counters().out_of_order == 2
    assert bus.latest_plans(12 * S, S)[7].stamp_ns == 12 * S
    check_balance(bus)


def test_a_restarted_sender_is_accepted_again(hub_buses) -> None:
    hub, (bus, *_) = hub_buses
    hub.put(plan_key(FLEET, 7), raw_plan(7, 900, 30 * S))
    hub.put(plan_key(FLEET, 7), raw_plan(7, 0, 31 * S))  # seq reset, time moved on
    c = bus.counters()
    assert (c.accepted, c.sender_restarts, c.out_of_order) == (2, 1, 0)
    assert bus.latest_plans(31 * S, 0)[7].stamp_ns == 31 * S


def test_max_age_filter_uses_simulated_time(hub_buses) -> None:
    _, (a, b, c) = hub_buses
    a.publish_plan(make_plan(1, 10 * S))
    c.publish_plan(make_plan(3, 9 * S))
    assert sorted(b.latest_plans(10 * S, S)) == [1, 3]
    assert sorted(b.latest_plans(10 * S + S // 2, S)) == [1]
    assert sorted(b.latest_plans(11 * S, S)) == [1]  # age == max_age is fresh
    assert b.latest_plans(11 * S + 1, S) == {}
    assert b.latest_plans(8 * S, S // 2) == {}  # stamped more than max_age in the future
    assert sorted(b.latest_plans(30 * S, 30 * S)) == [1, 3]
    with pytest.raises(ConfigError) as info:
        b.latest_plans(10 * S, -1)
    assert info.value.field == "max_age_ns"


def test_own_id_from_elsewhere_is_ignored(hub_buses) -> None:
    hub, (bus, other, _) = hub_buses
    hub.put(plan_key(FLEET, 1), raw_plan(1, 0, S))  # someone else claims vehicle 1
    assert bus.latest_plans(S, S) == {}
    assert bus.counters().own_ignored == 1
    assert sorted(other.latest_plans(S, S)) == [1]


def test_malformed_payloads_are_counted_by_reason_and_plans_keep_flowing(hub_buses) -> None:
    hub, (bus, two, _) = hub_buses
    good = raw_plan(2, 0, S)
    hub.put(plan_key(FLEET, 2), b"garbage")  # too short for a header
    hub.put(plan_key(FLEET, 2), b"XX" + good[2:])
    hub.put(plan_key(FLEET, 3), good)  # vehicle 2's plan on vehicle 3's key
    hub.put(plan_key(FLEET, 2), encode(StatusMessage(2, 0, S, VehicleStatus())))
    hub.put(f"fleetmpc/{FLEET}/uav/02/plan", good)
    two.publish_plan(make_plan(2, 2 * S))
    c = bus.counters()
    assert dict(c.rejected) == {
        RejectReason.SIZE: 1,
        RejectReason.MAGIC: 1,
        RejectReason.KEY_MISMATCH: 1,
        RejectReason.KIND: 1,
        RejectReason.KEY: 1,
    }
    assert c.accepted == 1 and bus.latest_plans(2 * S, 0)[2].stamp_ns == 2 * S
    check_balance(bus)


def test_deferred_delivery_until_flush() -> None:
    hubs = MemoryHubs(deliver_immediately=False)
    a = open_plan_bus("mem://lockstep", fleet=FLEET, vehicle_id=1, hubs=hubs)
    b = open_plan_bus("mem://lockstep", fleet=FLEET, vehicle_id=2, hubs=hubs)
    a.publish_plan(make_plan(1, S))
    b.publish_plan(make_plan(2, S))
    assert a.latest_plans(S, 0) == {} and b.latest_plans(S, 0) == {}
    assert hubs.hub("lockstep").flush() == 2
    assert sorted(a.latest_plans(S, 0)) == [2] and sorted(b.latest_plans(S, 0)) == [1]
    assert hubs.hub("lockstep").pending == 0


def test_status_and_target_and_a_listen_only_observer(hub_buses) -> None:
    hub, (a, b, c) = hub_buses
    gcs = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=None)
    status = VehicleStatus(mode=VehicleMode.OFFBOARD, armed=True, beta=LearnedParams(0.9))
    a.publish_status(status, stamp_ns=5 * S)
    a.publish_plan(make_plan(1, 5 * S))
    b.publish_target(stamp_ns=5 * S, north_m=10.0, east_m=10.0, noise_std_m=0.5)
    c.publish_target(stamp_ns=6 * S, north_m=11.0, east_m=11.0, velocity_m_s=(1.0, 1.0))
    assert gcs.latest_statuses(5 * S, 0)[1].status == status
    assert sorted(gcs.latest_plans(5 * S, 0)) == [1]
    newest = a.latest_target(6 * S, 2 * S)
    assert (newest.sender_id, newest.north_m, newest.velocity_m_s) == (3, 11.0, (1.0, 1.0))
    assert a.latest_target(20 * S, S) is None
    assert c.latest_target(6 * S, 2 * S).sender_id == 2  # its own observation is not returned
    with pytest.raises(ConfigError) as info:
        gcs.publish_plan(make_plan(1, 0))
    assert info.value.field == "vehicle_id"
    gcs.close()


def test_publishing_invalid_data_names_the_field(hub_buses) -> None:
    _, (a, b, _) = hub_buses
    with pytest.raises(ConfigError) as info:
        a.publish_plan(make_plan(2, S))
    assert info.value.field == "plan.vehicle_id"
    bad = make_plan(1, S)
    bad.states[1, 0] = np.nan
    with pytest.raises(ConfigError) as info:
        a.publish_plan(bad)
    assert info.value.field == "plan.states"
    assert b.counters().received == 0 and a.counters().published == 0


def test_close_is_idempotent_and_a_context_manager() -> None:
    hub = MemoryHub("h")
    with InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1) as a:
        b = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=2)
        b.publish_plan(make_plan(2, S))
    assert a.closed
    a.close()
    b.publish_plan(make_plan(2, 2 * S))  # a has detached: it keeps what it had
    assert a.latest_plans(S, 0)[2].stamp_ns == S and a.counters().received == 1
    with pytest.raises(PlanBusClosedError):
        a.publish_plan(make_plan(1, S))
    b.close()


def test_other_fleets_on_the_same_hub_are_not_seen() -> None:
    hub = MemoryHub("h")
    a = InMemoryPlanBus(hub, fleet="alpha", vehicle_id=1)
    b = InMemoryPlanBus(hub, fleet="bravo", vehicle_id=2)
    b.publish_plan(make_plan(2, S))
    assert a.counters().received == 0


@pytest.mark.parametrize(
    ("url", "kwargs", "field"),
    [
        ("mem://sim", {}, "hubs"),
        ("mem://bad/name", {"hubs": MemoryHubs()}, "plan_bus_url"),
        ("udp://127.0.0.1:1", {}, "plan_bus_url"),
        ("zenohx", {}, "plan_bus_url"),
        ("mem://sim", {"hubs": MemoryHubs(), "fleet": "a/b"}, "fleet"),
        ("mem://sim", {"hubs": MemoryHubs(), "vehicle_id": 0}, "vehicle_id"),
        ("zenoh://127.0.0.1:7447?bogus=1", {}, "zenoh_url.bogus"),
    ],
)
def test_open_plan_bus_refuses_bad_urls(url: str, kwargs: dict, field: str) -> None:
    args = {"fleet": FLEET, "vehicle_id": 1, **kwargs}
    with pytest.raises(ConfigError) as info:
        open_plan_bus(url, **args)
    assert info.value.field == field


def test_concurrent_deliveries_are_all_counted(hub_buses) -> None:
    """Transport callbacks run on other threads: the receive state stays consistent."""
    hub, (bus, *_) = hub_buses
    payloads = [raw_plan(7, seq, seq * PERIOD_NS) for seq in range(300)]

    def deliver(offset: int) -> None:
        for payload in payloads[offset::4]:
            hub.put(plan_key(FLEET, 7), payload)
            hub.put(plan_key(FLEET, 7), b"junk")
            bus.latest_plans(0, 10**12)

    threads = [threading.Thread(target=deliver, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    c = bus.counters()
    assert c.received == 600 and c.rejected[RejectReason.SIZE] == 300
    assert c.accepted + c.out_of_order == 300 and c.duplicates == 0
    check_balance(bus)


class RefusingBus(InMemoryPlanBus):
    def _send(self, key: str, payload: bytes) -> bool:
        return False


def test_a_refused_send_is_counted_not_raised() -> None:
    bus = RefusingBus(MemoryHub("h"), fleet=FLEET, vehicle_id=1)
    bus.publish_plan(make_plan(1, S))
    c = bus.counters()
    assert (c.published, c.publish_errors) == (0, 1)


# Real Zenoh on loopback ----------------------------------------------------------------------


def free_port_block(n: int) -> int:
    """First of `n` consecutive free TCP ports on 127.0.0.1."""
    return helpers.free_port_block(range(n), kinds=(socket.SOCK_STREAM,))


@pytest.fixture
def zenoh_mesh() -> Iterator[tuple[int, list[PlanBus]]]:
    base = free_port_block(3)
    with ExitStack() as stack:
        buses = [
            stack.enter_context(
                open_plan_bus(
                    ZenohOptions.peer_mesh(index=k, size=3, base_port=base),
                    fleet=FLEET,
                    vehicle_id=k + 1,
                )
            )
            for k in range(3)
        ]
        yield base, buses
    assert all(b.closed for b in buses)
    assert_ports_released(base, 3)


def assert_ports_released(base: int, n: int) -> None:
    """A closed session stops listening: its ports can be bound again.

    SO_REUSEADDR tolerates connections left in TIME_WAIT, never a socket still listening.
    """
    for port in range(base, base + n):
        with closing(socket.socket()) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind(("127.0.0.1", port))
            s.listen()


def test_zenoh_peers_exchange_plans_and_target_observations(zenoh_mesh) -> None:
    _, buses = zenoh_mesh
    step = [0]

    def publish_all() -> None:
        step[0] += 1
        for bus in buses:
            bus.publish_plan(make_plan(bus.vehicle_id, step[0] * PERIOD_NS))
        buses[2].publish_target(stamp_ns=step[0] * PERIOD_NS, north_m=5.0, east_m=-5.0)

    def everyone_has_everything() -> bool:
        now = step[0] * PERIOD_NS
        return all(
            len(b.latest_plans(now, 10 * S)) == 2
            and (b is buses[2] or b.latest_target(now, 10 * S) is not None)
            for b in buses
        )

    assert wait_until(everyone_has_everything, tick=publish_all)
    now = step[0] * PERIOD_NS
    for bus in buses:
        got = bus.latest_plans(now, 10 * S)
        assert sorted(got) == sorted({1, 2, 3} - {bus.vehicle_id})
        assert all(same_plan(p, make_plan(i, p.stamp_ns)) for i, p in got.items())
        assert bus.counters().own_ignored == 0 and bus.counters().rejected_total == 0
    target = buses[0].latest_target(now, 10 * S)
    assert (target.sender_id, target.north_m, target.east_m) == (3, 5.0, -5.0)


def test_an_agents_zenoh_bus_leaves_samples_queued_in_zenoh_until_it_reads(zenoh_mesh) -> None:
    _, (one, two, _) = zenoh_mesh
    step = [0]

    def publish() -> None:
        step[0] += 1
        two.publish_plan(make_plan(2, step[0] * PERIOD_NS))

    assert wait_until(lambda: 2 in one.latest_plans(step[0] * PERIOD_NS, 10 * S), tick=publish)
    before = one.counters()
    for _ in range(100):
        publish()
    time.sleep(0.5)
    untouched = one._inbox.snapshot(published=0, publish_errors=0)  # (no read: no pull)
    assert untouched.received == before.received, "no thread handles a sample before a read"
    last = step[0] * PERIOD_NS
    assert wait_until(lambda: one.latest_plans(last, S)[2].stamp_ns == last)
    after = one.counters()  # (plans of the first wait may still have been on their way)
    assert after.received - before.received >= 100, "every queued sample is handled"
    assert after.accepted - before.accepted == after.received - before.received
    assert after.rejected_total == 0


def test_zenoh_garbage_is_counted_while_valid_plans_keep_flowing(zenoh_mesh) -> None:
    base, (one, two, _) = zenoh_mesh
    intruder = zenoh.open(ZenohOptions(connect=(f"tcp/127.0.0.1:{base}",)).to_config())
    try:
        step = [0]

        def publish() -> None:
            step[0] += 1
            intruder.put(plan_key(FLEET, 2), b"\x00garbage-that-is-not-a-plan")
            intruder.put(f"fleetmpc/{FLEET}/uav/x/plan", raw_plan(2, 0, 0))
            intruder.put(target_observation_key(FLEET), raw_plan(2, 0, 0))  # (wrong kind)
            intruder.put(target_observation_key(FLEET), b"FM")
            two.publish_plan(make_plan(2, step[0] * PERIOD_NS))

        def seen() -> bool:
            rejected = one.counters().rejected
            return all(
                rejected.get(r, 0) >= 2
                for r in (
                    RejectReason.MAGIC,
                    RejectReason.KEY,
                    RejectReason.KIND,
                    RejectReason.SIZE,
                )
            ) and 2 in one.latest_plans(step[0] * PERIOD_NS, 0)

        assert wait_until(seen, tick=publish)
        accepted = one.counters().accepted
        assert wait_until(lambda: one.counters().accepted > accepted, tick=publish)
        assert one.latest_plans(step[0] * PERIOD_NS, S)[2].stamp_ns >= (step[0] - 5) * PERIOD_NS
        check_balance(one)
    finally:
        intruder.close()


def test_zenoh_client_without_router_fails_with_plan_bus_error_after_its_wait() -> None:
    port = free_port_block(1)
    t0 = time.monotonic()
    with pytest.raises(PlanBusError, match=f"127.0.0.1:{port}"):
        open_plan_bus(f"zenoh://127.0.0.1:{port}?mode=client&wait=0.5", fleet=FLEET, vehicle_id=1)
    assert time.monotonic() - t0 >= 0.4, "it waited for its router"


EXIT_SCRIPT = """
import sys, time
import numpy as np
from fleetmpc.protocol.plan import Plan
from fleetmpc.bus.open_bus import open_plan_bus
base = int(sys.argv[1])
plan = Plan(vehicle_id=1, stamp_ns=0, period_ns=1, states=np.zeros((2, 3)), inputs=np.zeros((1, 2)))
a = open_plan_bus(f"zenoh://?listen=127.0.0.1:{base}", fleet="x", vehicle_id=1)
with open_plan_bus(f"zenoh://127.0.0.1:{base}", fleet="x", vehicle_id=2) as b:
    deadline = time.monotonic() + 5
    while not b.latest_plans(0, 1) and time.monotonic() < deadline:
        a.publish_plan(plan)
        time.sleep(0.02)
    print("received", sorted(b.latest_plans(0, 1)))
a.close()
"""


def test_a_process_using_zenoh_buses_exits_promptly() -> None:
    base = free_port_block(1)
    script = textwrap.dedent(EXIT_SCRIPT)
    done = subprocess.run(
        [sys.executable, "-c", script, str(base)], capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "received [1]"


def test_epoch_announcement_and_accept_listener() -> None:
    hubs = MemoryHubs()
    seen = []
    gcs = open_plan_bus("mem://t", fleet="f", vehicle_id=249, hubs=hubs)
    agent = open_plan_bus("mem://t", fleet="f", vehicle_id=1, hubs=hubs, on_accept=seen.append)
    assert agent.latest_epoch() is None
    gcs.publish_epoch(epoch_ns=5_000, speed=4.0)
    gcs.publish_epoch(epoch_ns=6_000, speed=4.0)
    gcs.publish_epoch(epoch_ns=6_000, speed=4.0)
    e = agent.latest_epoch()
    assert (e.epoch_ns, e.speed, e.sender_id) == (6_000, 4.0, 249)
    assert [m.epoch_ns for m in seen] == [5_000, 6_000, 6_000]
    with pytest.raises(ConfigError, match="speed"):
        gcs.publish_epoch(epoch_ns=1, speed=0.0)


def test_a_raising_listener_is_counted_not_propagated() -> None:
    hubs = MemoryHubs()

    def boom(_message) -> None:
        raise RuntimeError("listener bug")

    a = open_plan_bus("mem://t", fleet="f", vehicle_id=1, hubs=hubs)
    b = open_plan_bus("mem://t", fleet="f", vehicle_id=2, hubs=hubs, on_accept=boom)
    a.publish_epoch(epoch_ns=1, speed=1.0)
    assert b.counters().listener_errors == 1 and b.latest_epoch() is not None
