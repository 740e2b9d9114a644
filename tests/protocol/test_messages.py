"""Wire schema: bit-exact round trips, documented layout, and one rejection reason per defect."""

import math
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.codec import DecodeError, decode, decode_or_none, encode, plan_start
from fleetmpc.protocol.messages import (
    FleetEpoch,
    LearnedParams,
    MessageKind,
    NeighbourPlanAge,
    PlanMessage,
    PlanStatus,
    RejectReason,
    StatusMessage,
    TargetObservation,
    TargetState,
    VehicleMode,
    VehicleStatus,
)
from fleetmpc.protocol.plan import Plan, WindSample

U32 = st.integers(0, 2**32 - 1)
STAMP = st.integers(0, 2**63 - 1)
SENDER = st.integers(1, 250)


def f64(bound: float, *, lo: float | None = None) -> st.SearchStrategy[float]:
    return st.floats(-bound if lo is None else lo, bound, allow_nan=False)


@st.composite
def plans(draw: st.DrawFn) -> Plan:
    m = draw(st.integers(1, 12))
    xy = draw(hnp.arrays(np.float64, (m + 1, 2), elements=f64(1e6)))
    yaw = draw(hnp.arrays(np.float64, (m + 1, 1), elements=f64(1e4)))
    inputs = draw(hnp.arrays(np.float64, (m, 2), elements=f64(1e3)))
    return Plan(
        vehicle_id=draw(SENDER),
        stamp_ns=draw(STAMP),
        period_ns=draw(st.integers(1, 60_000_000_000)),
        states=np.hstack([xy, yaw]),
        inputs=inputs,
        wind=draw(st.none() | st.builds(WindSample, f64(1e4), f64(1e3), f64(1e3, lo=1e-9))),
    )


plan_statuses = st.builds(
    PlanStatus,
    mode=st.sampled_from(VehicleMode),
    qp_fallback=st.booleans(),
    learning_on=st.booleans(),
    first_c_norm=f64(1e7, lo=0.0),
    solve_time_us=U32,
)
plan_messages = st.builds(PlanMessage, seq=U32, plan=plans(), status=plan_statuses)
vehicle_statuses = st.builds(
    VehicleStatus,
    mode=st.sampled_from(VehicleMode),
    armed=st.booleans(),
    learning_on=st.booleans(),
    learning_frozen=st.booleans(),
    beta=st.builds(LearnedParams, f64(1e3), f64(1e3), f64(1e3), f64(1e3)),
    slot_error_m=f64(1e7, lo=0.0),
    neighbour_plan_ages=st.lists(
        st.builds(NeighbourPlanAge, vehicle_id=SENDER, age_ns=st.integers(-(2**63), 2**63 - 1)),
        max_size=8,
        unique_by=lambda a: a.vehicle_id,
    ).map(tuple),
    qp_fallbacks=U32,
    rejected_messages=U32,
    target_state=st.sampled_from(TargetState),
)
status_messages = st.builds(
    StatusMessage, sender_id=SENDER, seq=U32, stamp_ns=STAMP, status=vehicle_statuses
)
targets = st.builds(
    TargetObservation,
    sender_id=SENDER,
    seq=U32,
    stamp_ns=STAMP,
    north_m=f64(1e6),
    east_m=f64(1e6),
    noise_std_m=f64(1e7, lo=0.0),
    velocity_m_s=st.none() | st.tuples(f64(1e3), f64(1e3)),
)


def bits(x: object) -> bytes:
    """Bit pattern of a float or float array, so -0.0 != 0.0 and equality is exact."""
    return np.asarray(x, dtype="<f8").tobytes()


@given(message=plan_messages)
def test_plan_round_trip_is_bit_exact(message: PlanMessage) -> None:
    payload = encode(message)
    out = decode(payload)
    assert isinstance(out, PlanMessage)
    p, q = message.plan, out.plan
    assert (out.seq, out.sender_id, out.stamp_ns) == (message.seq, p.vehicle_id, p.stamp_ns)
    assert (q.vehicle_id, q.stamp_ns, q.period_ns, q.horizon) == (
        p.vehicle_id,
        p.stamp_ns,
        p.period_ns,
        p.horizon,
    )
    assert bits(q.states) == bits(p.states) and bits(q.inputs) == bits(p.inputs)
    assert q.states.shape == p.states.shape and q.inputs.shape == p.inputs.shape
    assert out.status == message.status
    assert bits(out.status.first_c_norm) == bits(message.status.first_c_norm)
    assert q.wind == p.wind
    assert encode(out) == payload
    assert len(payload) == 18 + 48 + 8 * (3 * (p.horizon + 1) + 2 * p.horizon)


@given(message=status_messages)
def test_status_round_trip_is_bit_exact(message: StatusMessage) -> None:
    payload = encode(message)
    out = decode(payload)
    assert out == message
    assert bits(out.status.beta.as_tuple()) == bits(message.status.beta.as_tuple())
    assert encode(out) == payload and len(payload) == 149


@given(message=targets)
def test_target_round_trip_is_bit_exact(message: TargetObservation) -> None:
    payload = encode(message)
    out = decode(payload)
    assert out == message
    assert bits([out.north_m, out.east_m]) == bits([message.north_m, message.east_m])
    assert encode(out) == payload and len(payload) == 59


def make_plan(
    m: int = 5,
    *,
    vehicle_id: int = 2,
    stamp_ns: int = 1_000_000_000,
    wind: WindSample | None = None,
) -> Plan:
    states = np.column_stack([np.arange(m + 1.0), -np.arange(m + 1.0), np.full(m + 1, 0.5)])
    return Plan(
        vehicle_id=vehicle_id,
        stamp_ns=stamp_ns,
        period_ns=200_000_000,
        states=states,
        inputs=np.tile([1.0, -0.25], (m, 1)),
        wind=wind,
    )


SAMPLE = WindSample(0.3, -0.2, 0.05)
"""Heading 0.3 rad, 0.2 m/s across it to the left, 5 cm/s of error."""


def plan_bytes(m: int = 5, wind: WindSample | None = SAMPLE) -> bytes:
    status = PlanStatus(
        mode=VehicleMode.OFFBOARD,
        qp_fallback=True,
        learning_on=False,
        first_c_norm=0.125,
        solve_time_us=777,
    )
    return encode(PlanMessage(seq=42, plan=make_plan(m, wind=wind), status=status))


def status_bytes() -> bytes:
    status = VehicleStatus(
        mode=VehicleMode.HOLD,
        armed=True,
        learning_frozen=True,
        beta=LearnedParams(0.8, 1.1, 0.3, -0.2),
        slot_error_m=1.5,
        neighbour_plan_ages=(NeighbourPlanAge(1, 200_000_000), NeighbourPlanAge(3, -5)),
        qp_fallbacks=4,
        rejected_messages=9,
        setpoint_rate_hz=20.5,
    )
    return encode(StatusMessage(sender_id=2, seq=7, stamp_ns=5, status=status))


def epoch_bytes() -> bytes:
    return encode(FleetEpoch(sender_id=249, seq=3, epoch_ns=1_700_000_000_000_000_000, speed=4.0))


def test_epoch_layout_and_round_trip() -> None:
    e = epoch_bytes()
    assert len(e) == 34 and e[3] == MessageKind.FLEET_EPOCH and e[4] == 249
    assert struct.unpack_from("<qd", e, 18) == (1_700_000_000_000_000_000, 4.0)
    out = decode(e)
    assert isinstance(out, FleetEpoch) and (out.epoch_ns, out.speed, out.seq) == (
        1_700_000_000_000_000_000,
        4.0,
        3,
    )
    assert encode(out) == e


def target_bytes(velocity: tuple[float, float] | None = (1.0, 1.0)) -> bytes:
    obs = TargetObservation(
        sender_id=9, seq=1, stamp_ns=3, north_m=5.0, east_m=6.0, noise_std_m=0.1,
        velocity_m_s=velocity,
    )  # fmt: skip
    return encode(obs)


def test_byte_layout_matches_the_documentation() -> None:
    b = plan_bytes(5)
    assert len(b) == 290
    assert b[0:2] == b"FM" and b[2] == 3 and b[3] == MessageKind.PLAN and b[4] == 2 and b[5] == 0
    assert struct.unpack_from("<Iq", b, 6) == (42, 1_000_000_000)
    assert struct.unpack_from("<qHBBdI", b, 18) == (
        200_000_000,
        5,
        VehicleMode.OFFBOARD,
        0b101,
        0.125,
        777,
    )
    assert struct.unpack_from("<3d", b, 42) == (0.3, -0.2, 0.05)
    assert struct.unpack_from("<3d", b, 66) == (0.0, -0.0, 0.5)
    assert struct.unpack_from("<3d", b, 66 + 24 * 5) == (5.0, -5.0, 0.5)
    assert struct.unpack_from("<2d", b, 66 + 24 * 6) == (1.0, -0.25)
    assert plan_bytes(wind=None)[29] == 1 and plan_bytes(wind=None)[42:66] == bytes(24)
    s = status_bytes()
    assert s[3] == MessageKind.STATUS and s[18:21] == bytes([VehicleMode.HOLD, 0b101, 2])
    assert struct.unpack_from("<4ddIId", s, 21) == (0.8, 1.1, 0.3, -0.2, 1.5, 4, 9, 20.5)
    assert struct.unpack_from("<BqBq", s, 77) == (1, 200_000_000, 3, -5)
    assert s[95:] == bytes(149 - 95)
    t = target_bytes()
    assert t[3] == MessageKind.TARGET_OBSERVATION and t[18] == 1
    assert struct.unpack_from("<5d", t, 19) == (5.0, 6.0, 1.0, 1.0, 0.1)


def test_decoded_plan_arrays_are_read_only() -> None:
    out = decode(plan_bytes())
    with pytest.raises(ValueError):
        out.plan.states[0, 0] = 1.0


def patched(payload: bytes, offset: int, fmt: str, *values: object) -> bytes:
    b = bytearray(payload)
    struct.pack_into(fmt, b, offset, *values)
    return bytes(b)


NAN, INF = math.nan, math.inf
REJECTIONS = {
    "not bytes": ("not bytes", RejectReason.SIZE),
    "empty": (b"", RejectReason.SIZE),
    "truncated header": (plan_bytes()[:17], RejectReason.SIZE),
    "truncated plan fixed part": (plan_bytes()[:40], RejectReason.SIZE),
    "truncated plan arrays": (plan_bytes()[:-1], RejectReason.SIZE),
    "trailing byte": (plan_bytes() + b"\0", RejectReason.SIZE),
    "truncated status": (status_bytes()[:-8], RejectReason.SIZE),
    "truncated target": (target_bytes()[:-1], RejectReason.SIZE),
    "wrong magic": (b"XX" + plan_bytes()[2:], RejectReason.MAGIC),
    "wrong version": (patched(plan_bytes(), 2, "<B", 1), RejectReason.VERSION),
    "future version": (patched(plan_bytes(), 2, "<B", 4), RejectReason.VERSION),
    "the version before the wind sample": (patched(plan_bytes(), 2, "<B", 2), RejectReason.VERSION),
    "unknown kind": (patched(plan_bytes(), 3, "<B", 9), RejectReason.KIND),
    "kind zero": (patched(plan_bytes(), 3, "<B", 0), RejectReason.KIND),
    "sender zero": (patched(plan_bytes(), 4, "<B", 0), RejectReason.SENDER),
    "sender 251": (patched(status_bytes(), 4, "<B", 251), RejectReason.SENDER),
    "reserved header byte": (patched(plan_bytes(), 5, "<B", 1), RejectReason.RANGE),
    "negative stamp": (patched(plan_bytes(), 10, "<q", -1), RejectReason.RANGE),
    "NaN state": (patched(plan_bytes(), 42 + 8, "<d", NAN), RejectReason.NON_FINITE),
    "inf input": (patched(plan_bytes(), 42 + 24 * 6 + 8, "<d", -INF), RejectReason.NON_FINITE),
    "NaN c norm": (patched(plan_bytes(), 30, "<d", NAN), RejectReason.NON_FINITE),
    "NaN beta": (patched(status_bytes(), 21 + 16, "<d", NAN), RejectReason.NON_FINITE),
    "inf slot error": (patched(status_bytes(), 53, "<d", INF), RejectReason.NON_FINITE),
    "NaN target north": (patched(target_bytes(), 19, "<d", NAN), RejectReason.NON_FINITE),
    "NaN target velocity": (patched(target_bytes(), 35, "<d", NAN), RejectReason.NON_FINITE),
    "horizon zero": (patched(plan_bytes(), 26, "<H", 0), RejectReason.RANGE),
    "horizon 101": (patched(plan_bytes(), 26, "<H", 101), RejectReason.RANGE),
    "horizon disagrees with size": (patched(plan_bytes(), 26, "<H", 4), RejectReason.SIZE),
    "period zero": (patched(plan_bytes(), 18, "<q", 0), RejectReason.RANGE),
    "negative period": (patched(plan_bytes(), 18, "<q", -200_000_000), RejectReason.RANGE),
    "position beyond 1e6 m": (patched(plan_bytes(), 66 + 24, "<d", 1.000001e6), RejectReason.RANGE),
    "speed beyond 1e3 m/s": (patched(plan_bytes(), 66 + 24 * 6, "<d", 2e3), RejectReason.RANGE),
    "wind without flag": (patched(plan_bytes(wind=None), 42, "<d", -0.0), RejectReason.RANGE),
    "NaN wind": (patched(plan_bytes(), 50, "<d", NAN), RejectReason.NON_FINITE),
    "wind std zero": (patched(plan_bytes(), 58, "<d", 0.0), RejectReason.RANGE),
    "unknown plan mode": (patched(plan_bytes(), 28, "<B", 99), RejectReason.RANGE),
    "reserved plan flags": (patched(plan_bytes(), 29, "<B", 0x80), RejectReason.RANGE),
    "negative c norm": (patched(plan_bytes(), 30, "<d", -1.0), RejectReason.RANGE),
    "unknown status mode": (patched(status_bytes(), 18, "<B", 7), RejectReason.RANGE),
    "reserved status flags": (patched(status_bytes(), 19, "<B", 0x20), RejectReason.RANGE),
    "nine neighbours": (patched(status_bytes(), 20, "<B", 9), RejectReason.RANGE),
    "stale neighbour entry": (patched(status_bytes(), 20, "<B", 1), RejectReason.RANGE),
    "neighbour id zero": (patched(status_bytes(), 77, "<B", 0), RejectReason.RANGE),
    "NaN setpoint rate": (patched(status_bytes(), 69, "<d", NAN), RejectReason.NON_FINITE),
    "negative setpoint rate": (patched(status_bytes(), 69, "<d", -1.0), RejectReason.RANGE),
    "epoch zero": (patched(epoch_bytes(), 18, "<q", 0), RejectReason.RANGE),
    "epoch speed zero": (patched(epoch_bytes(), 26, "<d", 0.0), RejectReason.RANGE),
    "epoch speed NaN": (patched(epoch_bytes(), 26, "<d", NAN), RejectReason.NON_FINITE),
    "epoch truncated": (epoch_bytes()[:-1], RejectReason.SIZE),
    "duplicate neighbour": (patched(status_bytes(), 86, "<B", 1), RejectReason.RANGE),
    "beta beyond 1e3": (patched(status_bytes(), 21, "<d", 1e4), RejectReason.RANGE),
    "negative slot error": (patched(status_bytes(), 53, "<d", -1.0), RejectReason.RANGE),
    "reserved target flags": (patched(target_bytes(), 18, "<B", 3), RejectReason.RANGE),
    "velocity without flag": (patched(target_bytes(None), 35, "<d", 1.0), RejectReason.RANGE),
    "negative zero velocity without flag": (
        patched(target_bytes(None), 43, "<d", -0.0),
        RejectReason.RANGE,
    ),
    "negative noise": (patched(target_bytes(), 51, "<d", -0.1), RejectReason.RANGE),
}


@pytest.mark.parametrize("name", REJECTIONS)
def test_each_defect_is_rejected_with_its_reason(name: str) -> None:
    payload, reason = REJECTIONS[name]
    with pytest.raises(DecodeError) as info:
        decode(payload)
    assert info.value.reason is reason
    counters: dict[RejectReason, int] = {}
    assert decode_or_none(payload, counters) is None
    assert counters == {reason: 1}


def test_the_unpatched_fixtures_are_valid() -> None:
    """The rejection cases differ from these valid payloads only by their patch."""
    for payload in (plan_bytes(), status_bytes(), target_bytes(), target_bytes(None)):
        assert encode(decode(payload)) == payload


def test_wrong_kind_for_the_key_is_rejected() -> None:
    counters: dict[RejectReason, int] = {}
    assert decode_or_none(status_bytes(), counters, expect=MessageKind.PLAN) is None
    assert decode_or_none(plan_bytes(), counters, expect=MessageKind.PLAN) is not None
    assert decode_or_none(target_bytes(), counters, expect=MessageKind.STATUS) is None
    assert counters == {RejectReason.KIND: 2}


@settings(max_examples=300)
@given(payload=st.binary(max_size=400))
def test_random_bytes_never_raise(payload: bytes) -> None:
    counters: dict[RejectReason, int] = {}
    out = decode_or_none(payload, counters)
    assert (out is None) == (sum(counters.values()) == 1)
    start = plan_start(payload)  # (never raises either)
    assert start is None or (len(payload) - 18 - 24 - 24) % 40 == 0


@given(message=plan_messages)
def test_a_plans_start_is_read_from_its_bytes_as_decoded(message: PlanMessage) -> None:
    payload = encode(message)
    sender, x, y = plan_start(payload)
    assert sender == message.plan.vehicle_id
    assert bits([x, y]) == bits(message.plan.states[0, :2])


def test_a_plans_start_is_none_for_what_is_not_framed_as_a_plan() -> None:
    plan = plan_bytes(5)
    assert plan_start(plan) is not None
    assert plan_start(plan[:-1]) is None  # size not that of its horizon
    assert plan_start(plan + b"\0") is None
    assert plan_start(b"XX" + plan[2:]) is None  # magic
    assert plan_start(plan[:2] + b"\x01" + plan[3:]) is None  # schema version
    assert plan_start(status_bytes()) is None and plan_start(target_bytes()) is None
    no_horizon = bytearray(plan)
    no_horizon[26:28] = bytes(2)
    assert plan_start(bytes(no_horizon)) is None


@settings(max_examples=300)
@given(
    base=st.sampled_from([plan_bytes(1), plan_bytes(5), status_bytes(), target_bytes()]),
    edits=st.lists(st.tuples(st.integers(0, 300), st.integers(0, 255)), min_size=1, max_size=4),
    cut=st.integers(0, 300),
)
def test_corrupted_messages_never_raise(base: bytes, edits: list, cut: int) -> None:
    b = bytearray(base)
    for offset, value in edits:
        b[offset % len(b)] = value
    for payload in (bytes(b), bytes(b[:cut])):
        counters: dict[RejectReason, int] = {}
        out = decode_or_none(payload, counters)
        if out is None:
            assert sum(counters.values()) == 1
        else:
            assert encode(out) == payload  # anything accepted is canonical


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: PlanMessage(seq=-1, plan=make_plan()), "seq"),
        (lambda: PlanMessage(seq=2**32, plan=make_plan()), "seq"),
        (lambda: PlanMessage(seq=0, plan=make_plan(vehicle_id=0)), "plan.vehicle_id"),
        (lambda: PlanMessage(seq=0, plan=make_plan(stamp_ns=-1)), "plan.stamp_ns"),
        (lambda: PlanMessage(seq=0, plan=make_plan(101)), "plan.horizon"),
        (lambda: PlanMessage(seq=0, plan=nan_plan()), "plan.states"),
        (lambda: PlanMessage(seq=0, plan=make_plan(), status=PlanStatus(solve_time_us=-1)),
         "status.solve_time_us"),
        (lambda: PlanStatus(first_c_norm=math.nan), "status.first_c_norm"),
        (lambda: LearnedParams(drift_east_m_s=math.inf), "beta.drift_east_m_s"),
        (lambda: VehicleStatus(neighbour_plan_ages=tuple(
            NeighbourPlanAge(i, 0) for i in range(1, 10))), "status.neighbour_plan_ages"),
        (lambda: VehicleStatus(armed=1), "status.armed"),
        (lambda: VehicleStatus(target_state=2), "status.target_state"),
        (lambda: StatusMessage(sender_id=0, seq=0, stamp_ns=0, status=VehicleStatus()),
         "sender_id"),
        (lambda: TargetObservation(sender_id=1, seq=0, stamp_ns=0, north_m=2e6, east_m=0.0),
         "north_m"),
        (lambda: TargetObservation(sender_id=1, seq=0, stamp_ns=0, north_m=0.0, east_m=0.0,
                                   velocity_m_s=(1.0,)), "velocity_m_s"),
    ],
)  # fmt: skip
def test_invalid_data_is_refused_at_construction_naming_the_field(build, field: str) -> None:
    with pytest.raises(ConfigError) as info:
        build()
    assert info.value.field == field
    assert isinstance(info.value, ValueError)


def nan_plan() -> Plan:
    p = make_plan()
    states = p.states.copy()
    states[2, 1] = math.nan
    return Plan(vehicle_id=2, stamp_ns=0, period_ns=p.period_ns, states=states, inputs=p.inputs)
