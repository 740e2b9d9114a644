"""Binary wire schema of the Zenoh messages (schema version 3), packed with `struct`.

All integers and floats are little-endian; floats are IEEE-754 float64 and round-trip bit-exactly.

Header, 18 bytes, common to every message::

    offset size type  field
    0      2    2s    magic, b"FM"
    2      1    u8    schema version (3)
    3      1    u8    message kind: 1 plan, 2 status, 3 target observation, 4 fleet epoch
    4      1    u8    sender id, the vehicle's MAVLink system id (1..250)
    5      1    u8    reserved, 0
    6      4    u32   sequence number, per sender and kind, increasing
    10     8    i64   simulated timestamp [ns] (>= 0); for a plan, the time of states[0]

PlanMessage (kind 1), 18 + 48 + 40 M + 24 bytes (290 bytes at M = 5)::

    18     8    i64   period_ns, time between plan states (1 .. 60e9)
    26     2    u16   horizon M (1..100)
    28     1    u8    mode (VehicleMode)
    29     1    u8    flags: bit 0 qp_fallback, bit 1 learning_on, bit 2 has_wind; other bits 0
    30     8    f64   first_c_norm, Euclidean norm of the first input correction c_0
    38     4    u32   solve_time_us, QP solve time [us]
    42     24   3 f64 wind sample: heading rad, wind across it m/s, its 1-sigma error m/s
                      (all 0 without)
    66     24(M+1) f64 states, row-major (x North m, y East m, yaw rad) for j = 0..M
    ..     16M  f64   inputs, row-major (speed m/s, yaw rate rad/s) for j = 0..M-1

StatusMessage (kind 2), 149 bytes::

    18     1    u8    mode (VehicleMode)
    19     1    u8    flags: bit 0 armed, bit 1 learning_on, bit 2 learning_frozen, bits 3-4
                      target_state (TargetState); other bits 0
    20     1    u8    number of neighbour entries used (0..8)
    21     32   4 f64 beta: speed effectiveness, yaw-rate effectiveness, drift North m/s,
                      drift East m/s
    53     8    f64   slot_error_m, distance from the vehicle to its formation slot
    61     4    u32   qp_fallbacks, control periods that applied the fallback law
    65     4    u32   rejected_messages, received messages rejected by the vehicle's bus
    69     8    f64   setpoint_rate_hz, setpoints sent to the autopilot per simulated second
    77     72   8 x (u8 neighbour id, i64 age_ns of its latest plan); unused entries all zero

TargetObservation (kind 3), 59 bytes::

    18     1    u8    flags: bit 0 has_velocity; other bits 0
    19     8    f64   north_m
    27     8    f64   east_m
    35     8    f64   velocity North [m/s] (0 without velocity)
    43     8    f64   velocity East [m/s] (0 without velocity)
    51     8    f64   noise_std_m, 1-sigma position noise (>= 0)

FleetEpoch (kind 4), 34 bytes; header stamp 0, sender the ground station::

    18     8    i64   epoch_ns, host wall-clock time (Unix ns) of fleet time 0 (> 0)
    26     8    f64   speed, simulated seconds per wall-clock second (0.01 .. 1000)

Limits checked on both sides: |x|, |y| <= 1e6 m, |yaw| <= 1e4 rad (unwrapped headings are fine),
|speed| <= 1e3 m/s, |yaw rate| <= 1e3 rad/s, |beta| <= 1e3. `decode` checks size, magic, version,
kind, sender, finiteness and ranges and raises one `DecodeError` whose `reason` names the check;
`decode_or_none` counts that reason instead of raising. Encoding or constructing a message with
invalid data raises ConfigError (a ValueError) naming the field. The messages themselves, and
their field checks, are `fleetmpc.protocol.messages`.
"""

import struct
from collections.abc import MutableMapping
from dataclasses import astuple

import numpy as np

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.protocol.messages import (
    MAX_HORIZON,
    MAX_NEIGHBOURS,
    MAX_SENDER_ID,
    MIN_SENDER_ID,
    FieldError,
    FleetEpoch,
    LearnedParams,
    Message,
    MessageKind,
    NeighbourPlanAge,
    PlanMessage,
    PlanStatus,
    RejectReason,
    StatusMessage,
    TargetObservation,
    TargetState,
    VehicleStatus,
    vehicle_mode,
)
from fleetmpc.protocol.plan import Plan, WindSample

__all__ = [
    "MAGIC",
    "SCHEMA_VERSION",
    "DecodeError",
    "decode",
    "decode_or_none",
    "encode",
    "plan_start",
]

MAGIC = b"FM"
SCHEMA_VERSION = 3

_HEADER = struct.Struct("<2sBBBBIq")
_PLAN_FIXED = struct.Struct("<qHBBdI3d")
_WIND = struct.Struct("<3d")
"""The wind sample, the plan's fixed part's last field."""
_STATUS_FIXED = struct.Struct("<BBB4ddIId")
_NEIGHBOUR = struct.Struct("<Bq")
_TARGET = struct.Struct("<B5d")
_EPOCH = struct.Struct("<qd")
_START = struct.Struct("<2d")
"""A plan's first position (x North, y East), right after its fixed part."""
_PLAN_START_END = _HEADER.size + _PLAN_FIXED.size + _START.size
_STATUS_SIZE = _HEADER.size + _STATUS_FIXED.size + MAX_NEIGHBOURS * _NEIGHBOUR.size
_TARGET_SIZE = _HEADER.size + _TARGET.size
_EPOCH_SIZE = _HEADER.size + _EPOCH.size


class DecodeError(FleetMpcError, ValueError):
    """A payload is not a valid message; `reason` says which check failed."""

    def __init__(self, reason: RejectReason, message: str) -> None:
        self.reason = reason
        super().__init__(f"{reason.value}: {message}")


def _header(kind: MessageKind, sender_id: int, seq: int, stamp_ns: int) -> bytes:
    return _HEADER.pack(MAGIC, SCHEMA_VERSION, kind, int(sender_id), 0, int(seq), int(stamp_ns))


def encode(message: Message) -> bytes:
    """Serialize a message (already validated at construction) to its wire bytes."""
    if isinstance(message, PlanMessage):
        p, s = message.plan, message.status
        flags = int(s.qp_fallback) | int(s.learning_on) << 1 | int(p.wind is not None) << 2
        wind = (0.0, 0.0, 0.0) if p.wind is None else astuple(p.wind)
        m = int(np.shape(p.inputs)[0])
        return b"".join(
            (
                _header(MessageKind.PLAN, p.vehicle_id, message.seq, p.stamp_ns),
                _PLAN_FIXED.pack(
                    int(p.period_ns), m, s.mode, flags, s.first_c_norm, s.solve_time_us, *wind
                ),
                np.ascontiguousarray(p.states, dtype="<f8").tobytes(),
                np.ascontiguousarray(p.inputs, dtype="<f8").tobytes(),
            )
        )
    if isinstance(message, StatusMessage):
        st = message.status
        flags = int(st.armed) | int(st.learning_on) << 1 | int(st.learning_frozen) << 2
        flags |= int(st.target_state) << 3
        ages = list(st.neighbour_plan_ages)
        table = b"".join(_NEIGHBOUR.pack(a.vehicle_id, a.age_ns) for a in ages)
        table += bytes(_NEIGHBOUR.size * (MAX_NEIGHBOURS - len(ages)))
        return b"".join(
            (
                _header(MessageKind.STATUS, message.sender_id, message.seq, message.stamp_ns),
                _STATUS_FIXED.pack(
                    st.mode,
                    flags,
                    len(ages),
                    *st.beta.as_tuple(),
                    st.slot_error_m,
                    st.qp_fallbacks,
                    st.rejected_messages,
                    st.setpoint_rate_hz,
                ),
                table,
            )
        )
    if isinstance(message, TargetObservation):
        vel = message.velocity_m_s
        kind = MessageKind.TARGET_OBSERVATION
        return _header(kind, message.sender_id, message.seq, message.stamp_ns) + _TARGET.pack(
            int(vel is not None),
            message.north_m,
            message.east_m,
            *(vel if vel is not None else (0.0, 0.0)),
            message.noise_std_m,
        )
    if isinstance(message, FleetEpoch):
        kind = MessageKind.FLEET_EPOCH
        return _header(kind, message.sender_id, message.seq, message.stamp_ns) + _EPOCH.pack(
            message.epoch_ns, message.speed
        )
    raise ConfigError("message", f"cannot encode {type(message).__name__}")


def _reject(reason: RejectReason, message: str) -> DecodeError:
    return DecodeError(reason, message)


def _read_f64(data: bytes, offset: int, count: int, cols: int) -> np.ndarray:
    a = np.frombuffer(data, dtype="<f8", count=count * cols, offset=offset)
    a = a.reshape(count, cols).astype(np.float64)
    a.flags.writeable = False
    return a


def _plan_size(m: int) -> int:
    """Bytes of a plan of horizon `m`."""
    return _HEADER.size + _PLAN_FIXED.size + 8 * (3 * (m + 1) + 2 * m)


def _decode_plan(data: bytes, sender: int, seq: int, stamp: int) -> PlanMessage:
    base = _HEADER.size + _PLAN_FIXED.size
    if len(data) < base:
        raise _reject(RejectReason.SIZE, f"plan needs at least {base} bytes, got {len(data)}")
    period, m, mode, flags, c_norm, solve_us, *wind = _PLAN_FIXED.unpack_from(data, _HEADER.size)
    if not 1 <= m <= MAX_HORIZON:
        raise _reject(RejectReason.RANGE, f"horizon must be in [1, {MAX_HORIZON}], got {m}")
    size = _plan_size(m)
    if len(data) != size:
        raise _reject(RejectReason.SIZE, f"plan of horizon {m} is {size} bytes, got {len(data)}")
    if flags & ~0b111:
        raise _reject(RejectReason.RANGE, f"reserved plan flag bits set: {flags:#04x}")
    wind_at = _HEADER.size + _PLAN_FIXED.size - _WIND.size
    if not flags & 4 and data[wind_at : wind_at + _WIND.size] != bytes(_WIND.size):
        raise _reject(RejectReason.RANGE, "wind bytes must be 0 when has_wind is clear")
    states = _read_f64(data, base, m + 1, 3)
    inputs = _read_f64(data, base + 24 * (m + 1), m, 2)
    status = PlanStatus(
        mode=vehicle_mode("status.mode", mode),
        qp_fallback=bool(flags & 1),
        learning_on=bool(flags & 2),
        first_c_norm=c_norm,
        solve_time_us=solve_us,
    )
    plan = Plan(
        vehicle_id=sender,
        stamp_ns=stamp,
        period_ns=period,
        states=states,
        inputs=inputs,
        wind=WindSample(*wind) if flags & 4 else None,
    )
    return PlanMessage(seq=seq, plan=plan, status=status)


def _decode_status(data: bytes, sender: int, seq: int, stamp: int) -> StatusMessage:
    if len(data) != _STATUS_SIZE:
        raise _reject(RejectReason.SIZE, f"status is {_STATUS_SIZE} bytes, got {len(data)}")
    mode, flags, count, *rest = _STATUS_FIXED.unpack_from(data, _HEADER.size)
    beta, (slot_error, fallbacks, rejected, setpoint_rate) = rest[:4], rest[4:]
    if flags & ~0b11111:
        raise _reject(RejectReason.RANGE, f"reserved status flag bits set: {flags:#04x}")
    if count > MAX_NEIGHBOURS:
        raise _reject(RejectReason.RANGE, f"at most {MAX_NEIGHBOURS} neighbours, got {count}")
    offset = _HEADER.size + _STATUS_FIXED.size
    entries = [_NEIGHBOUR.unpack_from(data, offset + i * _NEIGHBOUR.size) for i in range(8)]
    if any(e != (0, 0) for e in entries[count:]):
        raise _reject(RejectReason.RANGE, "unused neighbour entries must be zero")
    status = VehicleStatus(
        mode=vehicle_mode("status.mode", mode),
        armed=bool(flags & 1),
        learning_on=bool(flags & 2),
        learning_frozen=bool(flags & 4),
        beta=LearnedParams(*beta),
        slot_error_m=slot_error,
        neighbour_plan_ages=tuple(NeighbourPlanAge(i, age) for i, age in entries[:count]),
        qp_fallbacks=fallbacks,
        rejected_messages=rejected,
        setpoint_rate_hz=setpoint_rate,
        target_state=TargetState(flags >> 3 & 0b11),
    )
    return StatusMessage(sender_id=sender, seq=seq, stamp_ns=stamp, status=status)


def _decode_target(data: bytes, sender: int, seq: int, stamp: int) -> TargetObservation:
    if len(data) != _TARGET_SIZE:
        raise _reject(RejectReason.SIZE, f"target is {_TARGET_SIZE} bytes, got {len(data)}")
    flags, north, east, vn, ve, noise = _TARGET.unpack_from(data, _HEADER.size)
    if flags & ~1:
        raise _reject(RejectReason.RANGE, f"reserved target flag bits set: {flags:#04x}")
    velocity_at = _HEADER.size + 1 + 16
    if not flags and data[velocity_at : velocity_at + 16] != bytes(16):
        raise _reject(RejectReason.RANGE, "velocity bytes must be 0 when has_velocity is clear")
    return TargetObservation(
        sender_id=sender,
        seq=seq,
        stamp_ns=stamp,
        north_m=north,
        east_m=east,
        noise_std_m=noise,
        velocity_m_s=(vn, ve) if flags else None,
    )


def _decode_epoch(data: bytes, sender: int, seq: int, stamp: int) -> FleetEpoch:
    if len(data) != _EPOCH_SIZE:
        raise _reject(RejectReason.SIZE, f"epoch is {_EPOCH_SIZE} bytes, got {len(data)}")
    epoch_ns, speed = _EPOCH.unpack_from(data, _HEADER.size)
    return FleetEpoch(sender_id=sender, seq=seq, epoch_ns=epoch_ns, speed=speed, stamp_ns=stamp)


_DECODERS = {
    MessageKind.PLAN: _decode_plan,
    MessageKind.STATUS: _decode_status,
    MessageKind.TARGET_OBSERVATION: _decode_target,
    MessageKind.FLEET_EPOCH: _decode_epoch,
}


def decode(payload: bytes, *, expect: MessageKind | None = None) -> Message:
    """Parse and validate wire bytes; raise DecodeError (with a `reason`) if they are invalid.

    With `expect`, a message of another kind is rejected with reason KIND.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise _reject(RejectReason.SIZE, f"payload must be bytes, got {type(payload).__name__}")
    data = bytes(payload)
    if len(data) < _HEADER.size:
        raise _reject(RejectReason.SIZE, f"header needs {_HEADER.size} bytes, got {len(data)}")
    magic, version, kind, sender, reserved, seq, stamp = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise _reject(RejectReason.MAGIC, f"magic must be {MAGIC!r}, got {magic!r}")
    if version != SCHEMA_VERSION:
        raise _reject(RejectReason.VERSION, f"schema version {version} (expected {SCHEMA_VERSION})")
    if kind not in _DECODERS:
        raise _reject(RejectReason.KIND, f"unknown message kind {kind}")
    if expect is not None and kind != expect:
        raise _reject(RejectReason.KIND, f"expected {expect.name}, got {MessageKind(kind).name}")
    if not MIN_SENDER_ID <= sender <= MAX_SENDER_ID:
        raise _reject(RejectReason.SENDER, f"sender id {sender} outside 1..250")
    if reserved:
        raise _reject(RejectReason.RANGE, f"reserved header byte must be 0, got {reserved}")
    if stamp < 0:
        raise _reject(RejectReason.RANGE, f"timestamp must be >= 0, got {stamp}")
    try:
        return _DECODERS[MessageKind(kind)](data, sender, seq, stamp)
    except FieldError as e:
        raise _reject(e.reason, str(e)) from None


def plan_start(payload: bytes) -> tuple[int, float, float] | None:
    """(sender id, x North, y East) of a plan's first state, read from its bytes without
    decoding them, or None if the payload is not framed as a plan (magic, version, kind,
    horizon and size). Nothing else is checked: for a receiver that drops the plans of vehicles
    far away, so that it spends a look at a few bytes on them, not a decode."""
    if not isinstance(payload, bytes) or len(payload) < _PLAN_START_END:
        return None
    magic, version, kind, sender, _, _, _ = _HEADER.unpack_from(payload)
    m = _PLAN_FIXED.unpack_from(payload, _HEADER.size)[1]
    framed = (magic, version, kind) == (MAGIC, SCHEMA_VERSION, MessageKind.PLAN)
    if not framed or not 1 <= m <= MAX_HORIZON or len(payload) != _plan_size(m):
        return None
    x, y = _START.unpack_from(payload, _HEADER.size + _PLAN_FIXED.size)
    return sender, x, y


def decode_or_none(
    payload: bytes,
    counters: MutableMapping[RejectReason, int],
    *,
    expect: MessageKind | None = None,
) -> Message | None:
    """`decode`, but on a DecodeError count its reason in `counters` and return None."""
    try:
        return decode(payload, expect=expect)
    except DecodeError as e:
        counters[e.reason] = counters.get(e.reason, 0) + 1
        return None
