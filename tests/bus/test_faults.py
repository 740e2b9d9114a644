"""Injected network faults: the fault file's validation, what each kind does to the payloads
a FaultLayer sees on a clock the test steps by hand, its random streams, and a layer behind a bus.
"""

import math

import numpy as np
import pytest
from test_planbus import make_plan

from fleetmpc.bus.faults import (
    REORDER_HOLD_S,
    Fault,
    FaultLayer,
    FaultSchedule,
    load_faults,
    parse_faults,
)
from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHub
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.key_expressions import (
    epoch_key,
    plan_key,
    status_key,
    target_observation_key,
)

FLEET = "test"
FLEET_IDS = (1, 2, 3, 4, 5)
S = 1_000_000_000
MS = 1_000_000


def schedule(*faults: dict, seed: int | None = None) -> FaultSchedule:
    doc: dict = {"faults": list(faults)}
    if seed is not None:
        doc["seed"] = seed
    return parse_faults(doc, vehicle_ids=FLEET_IDS)


def layer(sched: FaultSchedule, clock: list, *, vehicle_id: int = 1, seed: int = 0) -> FaultLayer:
    """A layer whose clock reads `clock[0]` (the test steps it)."""
    return FaultLayer(sched, vehicle_id=vehicle_id, clock=lambda: clock[0], seed=seed)


def payloads(n: int) -> list[bytes]:
    return [i.to_bytes(4, "big") for i in range(n)]


# Fault files ------------------------------------------------------------------------------


LOSS = {"kind": "loss", "probability": 0.3}


@pytest.mark.parametrize(
    ("doc", "field"),
    [
        (
            {"faults": [{"kind": "blackout"}, {"kind": "loss", "probability": 1.5}]},
            "faults[1].probability",
        ),
        ({"faults": [{"kind": "loss", "probability": -0.1}]}, "faults[0].probability"),
        ({"faults": [{"kind": "duplicate", "probability": "often"}]}, "faults[0].probability"),
        ({"faults": [{"kind": "blackout", "vehicles": [9]}]}, "faults[0].vehicles[0]"),
        ({"faults": [{"kind": "blackout", "vehicles": [1, 0]}]}, "faults[0].vehicles[1]"),
        ({"faults": [{"kind": "blackout", "vehicles": [2.0]}]}, "faults[0].vehicles[0]"),
        ({"faults": [{"kind": "blackout", "vehicles": []}]}, "faults[0].vehicles"),
        ({"faults": [{"kind": "blackout", "vehicles": [2, 2]}]}, "faults[0].vehicles"),
        ({"faults": [{"kind": "blackout", "vehicles": 2}]}, "faults[0].vehicles"),
        ({"faults": [{"kind": "jam"}]}, "faults[0].kind"),
        ({"faults": [{"probability": 0.3}]}, "faults[0].kind"),
        ({"faults": [{**LOSS, "delay_s": 0.1}]}, "faults[0].delay_s"),
        ({"faults": [{"kind": "blackout", "probability": 0.5}]}, "faults[0].probability"),
        (
            {"faults": [{"kind": "partition", "groups": [[1]], "vehicles": [1]}]},
            "faults[0].vehicles",
        ),
        ({"faults": [{"kind": "loss"}]}, "faults[0].probability"),
        ({"faults": [LOSS, {"kind": "duplicate"}]}, "faults[1].probability"),
        ({"faults": [{"kind": "reorder"}]}, "faults[0].probability"),
        ({"faults": [{"kind": "delay", "jitter_s": 0.1}]}, "faults[0].delay_s"),
        ({"faults": [{"kind": "delay", "delay_s": -0.1}]}, "faults[0].delay_s"),
        ({"faults": [{"kind": "delay", "delay_s": 0.1, "jitter_s": -1}]}, "faults[0].jitter_s"),
        ({"faults": [{**LOSS, "start_s": -1.0}]}, "faults[0].start_s"),
        ({"faults": [{**LOSS, "duration_s": 0.0}]}, "faults[0].duration_s"),
        ({"faults": [{**LOSS, "duration_s": math.nan}]}, "faults[0].duration_s"),
        ({"faults": [{"kind": "partition", "groups": [[1, 2], [2, 3]]}]}, "faults[0].groups[1]"),
        ({"faults": [{"kind": "partition", "groups": [[1], [3, 7]]}]}, "faults[0].groups[1][1]"),
        ({"faults": [{"kind": "partition", "groups": [[1], []]}]}, "faults[0].groups[1]"),
        ({"faults": [{"kind": "partition"}]}, "faults[0].groups"),
        ({"faults": [{"kind": "partition", "groups": []}]}, "faults[0].groups"),
        ({"faults": [LOSS], "sede": 7}, "sede"),
        ({"faults": [LOSS], "seed": -1}, "seed"),
        ({"faults": [LOSS], "seed": True}, "seed"),
        ({"faults": [LOSS], "seed": 1.5}, "seed"),
        ({"faults": []}, "faults"),
        ({"seed": 3}, "faults"),
        ({"faults": {"kind": "loss"}}, "faults"),
        ({"faults": ["loss"]}, "faults[0]"),
    ],
)
def test_a_bad_fault_file_names_the_offending_field(doc, field) -> None:
    with pytest.raises(ConfigError) as info:
        parse_faults(doc, vehicle_ids=(1, 2, 3))
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")


def test_a_good_fault_file_parses_with_its_defaults(tmp_path) -> None:
    path = tmp_path / "faults.toml"
    path.write_text(
        """
seed = 7

[[faults]]
kind = "loss"
probability = 0.3

[[faults]]
kind = "delay"
start_s = 2.5
delay_s = 0.3
jitter_s = 0.1

[[faults]]
kind = "duplicate"
duration_s = 4
vehicles = [3, 1]
probability = 1

[[faults]]
kind = "reorder"
probability = 0.2

[[faults]]
kind = "blackout"
vehicles = [2]
start_s = 10.0
duration_s = 5.0

[[faults]]
kind = "partition"
groups = [[1], [2, 3]]
"""
    )
    got = load_faults(path, vehicle_ids=[1, 2, 3, 4])
    assert got == FaultSchedule(
        seed=7,
        faults=(
            Fault("loss", probability=0.3),
            Fault("delay", start_s=2.5, delay_s=0.3, jitter_s=0.1),
            Fault("duplicate", duration_s=4.0, vehicles=(3, 1), probability=1.0),
            Fault("reorder", probability=0.2),
            Fault("blackout", start_s=10.0, duration_s=5.0, vehicles=(2,)),
            Fault("partition", groups=((1,), (2, 3))),
        ),
    )
    loss = got.faults[0]
    assert (loss.start_s, loss.duration_s, loss.vehicles) == (0.0, math.inf, None)
    assert all(
        isinstance(f.start_s, float) and isinstance(f.probability, float) for f in got.faults
    )
    assert got.faults[4].describe() == "blackout for vehicles [2], 10 s to 15 s"
    assert got.faults[0].describe() == "30% loss for every vehicle, 0 s to the end"
    assert parse_faults({"faults": [LOSS]}, vehicle_ids=[1]).seed is None


def test_load_faults_names_the_option_for_an_unreadable_or_invalid_file(tmp_path) -> None:
    with pytest.raises(ConfigError) as info:
        load_faults(tmp_path / "missing.toml", vehicle_ids=[1, 2])
    assert info.value.field == "--faults"
    assert "missing.toml" in str(info.value)

    bad = tmp_path / "bad.toml"
    bad.write_text('[[faults]]\nkind = "loss\n')
    with pytest.raises(ConfigError) as info:
        load_faults(bad, vehicle_ids=[1, 2])
    assert info.value.field == "--faults"
    assert "not valid TOML" in str(info.value)


def test_load_faults_names_the_file_and_the_field_of_a_bad_value(tmp_path) -> None:
    path = tmp_path / "f.toml"
    path.write_text('[[faults]]\nkind = "loss"\nprobability = 2.0\n')
    with pytest.raises(ConfigError) as info:
        load_faults(path, vehicle_ids=[1, 2])
    assert info.value.field == f"{path}: faults[0].probability"
    assert str(info.value).startswith(f"{path}: faults[0].probability: must be in [0.0, 1.0]")


# What each fault does ---------------------------------------------------------------------


KEY2 = plan_key(FLEET, 2)
KEY3 = plan_key(FLEET, 3)


def test_a_fault_does_nothing_outside_its_window_or_to_vehicles_it_does_not_hit() -> None:
    now = [0]
    sched = schedule({"kind": "loss", "probability": 1.0, "start_s": 10.0, "duration_s": 5.0})
    one = layer(sched, now)
    for t_ns, delivered in [
        (0, 1),
        (10 * S - 1, 1),
        (10 * S, 0),
        (12 * S, 0),
        (15 * S - 1, 0),
        (15 * S, 1),
        (100 * S, 1),
    ]:
        now[0] = t_ns
        assert one.arrive(KEY2, b"p") == [(KEY2, b"p")] * delivered, t_ns
    assert one.counts["lost"] == 3

    others = layer(schedule({"kind": "loss", "probability": 1.0, "vehicles": [2, 3]}), now)
    assert others.arrive(KEY2, b"p") == [(KEY2, b"p")]
    assert others.counts["lost"] == 0


def test_loss_drops_its_share_of_the_payloads_and_counts_them() -> None:
    now = [5 * S]
    lossy = layer(schedule({"kind": "loss", "probability": 0.3}), now, seed=11)
    delivered = []
    for p in payloads(2000):
        delivered += lossy.arrive(KEY2, p)
    lost = 2000 - len(delivered)
    assert 0.25 <= lost / 2000 <= 0.35
    assert lossy.counts["lost"] == lost
    assert {k for k, _ in delivered} == {KEY2}
    kept = [p for _, p in delivered]
    assert kept == sorted(kept)  # loss never reorders
    assert lossy.held == 0 and lossy.release() == []


@pytest.mark.parametrize(("probability", "delivered"), [(1.0, 0), (0.0, 200)])
def test_loss_at_probability_one_drops_everything_and_at_zero_nothing(
    probability, delivered
) -> None:
    now = [S]
    lossy = layer(schedule({"kind": "loss", "probability": probability}), now)
    out = [d for p in payloads(200) for d in lossy.arrive(KEY2, p)]
    assert len(out) == delivered
    assert lossy.counts["lost"] == 200 - delivered


def test_delay_holds_a_payload_until_its_release_time() -> None:
    now = [10 * S]
    late = layer(schedule({"kind": "delay", "delay_s": 0.3}), now)
    assert late.arrive(KEY2, b"a") == []
    now[0] = 10 * S + 100 * MS
    assert late.arrive(KEY2, b"b") == []
    assert late.held == 2
    assert late.counts["delayed"] == 2
    now[0] = 10 * S + 300 * MS - 1
    assert late.release() == []
    now[0] = 10 * S + 300 * MS
    assert late.release() == [(KEY2, b"a")]
    assert late.release() == []
    now[0] = 10 * S + 399 * MS
    assert late.release() == []
    now[0] = 11 * S
    assert late.release() == [(KEY2, b"b")]
    assert late.held == 0


def test_delay_jitter_keeps_every_hold_within_its_bounds() -> None:
    now = [0]
    late = layer(schedule({"kind": "delay", "delay_s": 0.3, "jitter_s": 0.1}), now, seed=3)
    n = 500
    for p in payloads(n):
        assert late.arrive(KEY2, p) == []
    released_at: dict[bytes, int] = {}
    for t_ms in range(501):  # step the clock 1 ms at a time
        now[0] = t_ms * MS
        for _, p in late.release():
            released_at[p] = t_ms
    assert len(released_at) == n and late.held == 0
    holds = np.array(list(released_at.values()))
    assert holds.min() >= 200 and holds.max() <= 400
    assert holds.min() < 220 and holds.max() > 380  # the jitter spreads over its whole range
    assert len(set(holds.tolist())) > 50
    assert late.counts["delayed"] == n


def test_duplicate_at_probability_one_delivers_every_payload_twice() -> None:
    now = [S]
    twice = layer(schedule({"kind": "duplicate", "probability": 1.0}), now)
    assert twice.arrive(KEY2, b"a") == [(KEY2, b"a"), (KEY2, b"a")]
    assert twice.arrive(KEY2, b"b") == [(KEY2, b"b"), (KEY2, b"b")]
    assert twice.counts["duplicated"] == 2
    never = layer(schedule({"kind": "duplicate", "probability": 0.0}), now)
    assert never.arrive(KEY2, b"a") == [(KEY2, b"a")]
    assert never.counts["duplicated"] == 0


def test_reorder_holds_some_payloads_back_so_later_ones_overtake_them() -> None:
    now = [0]
    shuffle = layer(schedule({"kind": "reorder", "probability": 0.5}), now, seed=5)
    sent = payloads(100)
    order: list[bytes] = []
    arrived_at, delivered_at = {}, {}
    for i in range(len(sent) + 11):  # a payload every 50 ms, the bus read after each
        now[0] = i * 50 * MS
        arrived = []
        if i < len(sent):
            arrived_at[sent[i]] = now[0]
            arrived = shuffle.arrive(KEY2, sent[i])
        for _, q in arrived + shuffle.release():
            order.append(q)
            delivered_at[q] = now[0]
    assert shuffle.held == 0
    assert sorted(order) == sent  # nothing lost, nothing doubled
    assert order != sent
    late = [p for p in sent if delivered_at[p] > arrived_at[p]]
    assert 30 <= len(late) <= 70
    assert shuffle.counts["reordered"] == len(late)
    assert all(delivered_at[p] - arrived_at[p] <= REORDER_HOLD_S * S + 50 * MS for p in sent)
    overtaken = sum(1 for a, b in zip(order, order[1:], strict=False) if a > b)
    assert overtaken > 0


def test_blackout_cuts_messages_to_and_from_a_vehicle_but_not_between_others() -> None:
    now = [12 * S]
    sched = schedule({"kind": "blackout", "vehicles": [2], "start_s": 10.0, "duration_s": 5.0})
    one, two = layer(sched, now, vehicle_id=1), layer(sched, now, vehicle_id=2)
    # From vehicle 2, to vehicle 1: cut.
    assert one.arrive(plan_key(FLEET, 2), b"p") == []
    assert one.arrive(status_key(FLEET, 2), b"s") == []
    # Between vehicles 3 and 1: through.
    assert one.arrive(plan_key(FLEET, 3), b"p") == [(plan_key(FLEET, 3), b"p")]
    assert one.arrive(status_key(FLEET, 3), b"s") == [(status_key(FLEET, 3), b"s")]
    # Fleet-wide keys name no sender: through unless the receiver is blacked out.
    assert one.arrive(target_observation_key(FLEET), b"t") == [
        (target_observation_key(FLEET), b"t")
    ]
    assert one.counts["blacked_out"] == 2
    # To vehicle 2: everything cut.
    for key in (
        plan_key(FLEET, 1),
        status_key(FLEET, 3),
        target_observation_key(FLEET),
        epoch_key(FLEET),
    ):
        assert two.arrive(key, b"x") == []
    assert two.counts["blacked_out"] == 4
    # After the window: through again.
    now[0] = 15 * S
    assert one.arrive(plan_key(FLEET, 2), b"p") == [(plan_key(FLEET, 2), b"p")]
    assert two.arrive(plan_key(FLEET, 1), b"p") == [(plan_key(FLEET, 1), b"p")]


def test_partition_cuts_between_groups_and_the_unlisted_vehicles_form_a_group() -> None:
    now = [0]
    sched = schedule({"kind": "partition", "groups": [[1, 2], [3]]})
    layers = {v: layer(sched, now, vehicle_id=v) for v in FLEET_IDS}
    group = {1: "a", 2: "a", 3: "b", 4: "rest", 5: "rest"}
    for receiver in FLEET_IDS:
        for sender in FLEET_IDS:
            if sender == receiver:
                continue
            key = plan_key(FLEET, sender)
            out = layers[receiver].arrive(key, b"p")
            assert out == ([(key, b"p")] if group[sender] == group[receiver] else []), (
                sender,
                receiver,
            )
    # 1 and 2 each lose 3 senders, 3 loses 4, 4 and 5 each lose 3.
    assert {v: l.counts["partitioned"] for v, l in layers.items()} == {1: 3, 2: 3, 3: 4, 4: 3, 5: 3}
    # A fleet-wide key names no sender: it crosses the partition.
    key = target_observation_key(FLEET)
    assert layers[3].arrive(key, b"t") == [(key, b"t")]


def test_a_clock_that_is_not_known_lets_everything_through() -> None:
    now: list = [None]
    sched = schedule(
        {"kind": "blackout"},
        {"kind": "loss", "probability": 1.0},
        {"kind": "delay", "delay_s": 0.3},
    )
    blind = layer(sched, now)
    for p in payloads(20):
        assert blind.arrive(KEY2, p) == [(KEY2, p)]
    assert sum(blind.counts.values()) == 0
    assert blind.release() == []
    # Once the clock is known the faults apply (blackout of every vehicle first).
    now[0] = 0
    assert blind.arrive(KEY2, b"x") == []
    assert blind.counts["blacked_out"] == 1


def test_held_payloads_are_all_released_when_the_clock_becomes_unknown() -> None:
    now: list = [S]
    late = layer(schedule({"kind": "delay", "delay_s": 5.0}), now)
    assert late.arrive(KEY2, b"a") == [] and late.arrive(KEY2, b"b") == []
    now[0] = None
    assert late.release() == [(KEY2, b"a"), (KEY2, b"b")]
    assert late.held == 0


# Random streams ---------------------------------------------------------------------------


MIXED = (
    {"kind": "loss", "probability": 0.3},
    {"kind": "delay", "delay_s": 0.1, "jitter_s": 0.05},
    {"kind": "duplicate", "probability": 0.3},
    {"kind": "reorder", "probability": 0.3},
)


def run_sequence(fl: FaultLayer, now: list, n: int = 300) -> list:
    """What `fl` delivers, step by step, for n payloads 20 ms apart, then a final release."""
    trace = []
    for i, p in enumerate(payloads(n)):
        now[0] = i * 20 * MS
        trace.append((now[0], fl.arrive(KEY2, p), fl.release()))
    now[0] = n * 20 * MS + S
    trace.append((now[0], [], fl.release()))
    return trace


def test_the_same_schedule_seed_and_vehicle_make_the_same_decisions() -> None:
    sched = schedule(*MIXED, seed=7)
    clock_a, clock_b = [0], [0]
    a = layer(sched, clock_a, vehicle_id=2, seed=1)
    b = layer(sched, clock_b, vehicle_id=2, seed=99)  # the schedule's seed wins over the run's
    trace_a, trace_b = run_sequence(a, clock_a), run_sequence(b, clock_b)
    assert trace_a == trace_b
    assert a.counts == b.counts
    assert all(a.counts[k] > 0 for k in ("lost", "delayed", "duplicated", "reordered"))


def test_without_a_schedule_seed_the_run_seed_picks_the_stream() -> None:
    sched = schedule({"kind": "loss", "probability": 0.5})
    kept = []
    for seed in (4, 4, 5):
        now = [0]
        fl = layer(sched, now, vehicle_id=3, seed=seed)
        kept.append([p for p in payloads(200) if fl.arrive(KEY2, p)])
    assert kept[0] == kept[1]
    assert kept[0] != kept[2]


def test_another_vehicle_draws_from_an_independent_stream() -> None:
    sched = schedule({"kind": "loss", "probability": 0.5}, seed=7)
    now = [0]
    drops = {}
    for vid in (1, 2):
        fl = layer(sched, now, vehicle_id=vid)
        drops[vid] = np.array([not fl.arrive(KEY3, p) for p in payloads(1000)])
    assert 400 <= drops[1].sum() <= 600 and 400 <= drops[2].sum() <= 600
    agree = np.mean(drops[1] == drops[2])
    assert 0.4 <= agree <= 0.6  # neither the same stream nor its mirror image


# Behind a bus -----------------------------------------------------------------------------


def test_a_delayed_plan_reaches_the_bus_reader_only_after_its_release_time() -> None:
    now = [10 * S]
    hub = MemoryHub("faults", deliver_immediately=True)
    sched = schedule({"kind": "delay", "delay_s": 0.3})
    with (
        InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1) as sender,
        InMemoryPlanBus(
            hub, fleet=FLEET, vehicle_id=2, faults=layer(sched, now, vehicle_id=2)
        ) as receiver,
    ):
        sender.publish_plan(make_plan(1, 10 * S))
        assert receiver.faults.held == 1
        assert receiver.latest_plans(now[0], S) == {}
        now[0] = 10 * S + 300 * MS - 1
        assert receiver.latest_plans(now[0], S) == {}
        assert receiver.counters().received == 0
        now[0] = 10 * S + 300 * MS
        got = receiver.latest_plans(now[0], S)
        assert sorted(got) == [1]
        assert got[1].stamp_ns == 10 * S
        c = receiver.counters()
        assert (c.received, c.accepted, c.duplicates) == (1, 1, 0)
        assert receiver.faults.held == 0
        assert receiver.faults.counts["delayed"] == 1
        assert sender.counters().published == 1


def test_a_duplicated_plan_is_counted_as_a_duplicate_by_the_bus() -> None:
    now = [10 * S]
    hub = MemoryHub("faults", deliver_immediately=True)
    sched = schedule({"kind": "duplicate", "probability": 1.0})
    with (
        InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1) as sender,
        InMemoryPlanBus(
            hub, fleet=FLEET, vehicle_id=2, faults=layer(sched, now, vehicle_id=2)
        ) as receiver,
        InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=3) as bystander,
    ):
        sender.publish_plan(make_plan(1, 10 * S))
        assert sorted(receiver.latest_plans(now[0], S)) == [1]
        c = receiver.counters()
        assert (c.received, c.accepted, c.duplicates, c.out_of_order) == (2, 1, 1, 0)
        assert receiver.faults.counts["duplicated"] == 1
        b = bystander.counters()  # a bus without faults sees the plan once
        assert (b.received, b.accepted, b.duplicates) == (1, 1, 0)


def test_a_kind_that_is_not_a_string_names_the_field():
    for kind in (["loss"], {"a": 1}):
        with pytest.raises(ConfigError) as e:
            parse_faults({"faults": [{"kind": kind}]}, vehicle_ids=[1])
        assert e.value.field == "faults[0].kind"


def test_a_fault_file_that_is_not_text_names_the_option(tmp_path):
    path = tmp_path / "binary.toml"
    path.write_bytes(b"\xff\xfe")
    with pytest.raises(ConfigError) as e:
        load_faults(path, vehicle_ids=[1])
    assert e.value.field == "--faults"


def test_a_payload_cut_by_a_later_fault_counts_only_as_cut():
    schedule = parse_faults(
        {"faults": [{"kind": "delay", "delay_s": 0.3}, {"kind": "loss", "probability": 1.0}]},
        vehicle_ids=[1, 2],
    )
    layer = FaultLayer(schedule, vehicle_id=1, clock=lambda: 0, seed=0)
    assert layer.arrive(plan_key("t", 2), b"x") == []
    assert layer.counts["lost"] == 1 and layer.counts["delayed"] == 0 and layer.held == 0


def test_a_window_ends_on_its_nanosecond():
    fault = parse_faults(
        {"faults": [{"kind": "loss", "probability": 1.0, "start_s": 4.4, "duration_s": 11.8}]},
        vehicle_ids=[1],
    ).faults[0]
    assert fault.active(4_400_000_000) and fault.active(16_199_999_999)
    assert not fault.active(16_200_000_000) and not fault.active(4_399_999_999)


def test_a_message_meets_the_same_fate_whatever_the_arrival_order():
    schedule = parse_faults(
        {"faults": [{"kind": "loss", "probability": 0.5}], "seed": 7}, vehicle_ids=[1, 2, 3]
    )
    payloads = [(plan_key("t", v), bytes([v, seq])) for seq in range(40) for v in (2, 3)]

    def kept(order):
        layer = FaultLayer(schedule, vehicle_id=1, clock=lambda: 0, seed=0)
        return {p for k, p in order if layer.arrive(k, p)}

    forward = kept(payloads)
    assert 0 < len(forward) < len(payloads)
    assert kept(list(reversed(payloads))) == forward
