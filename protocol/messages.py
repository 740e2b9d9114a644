"""Binary wire schema of the Zenoh messages (schema version 2), packed with `struct`.

All integers and floats are little-endian; floats are IEEE-754 float64 and round-trip bit-exactly.

Header, 18 bytes, common to every message::

    offset size type  field
    0      2    2s    magic, b"FM"
    2      1    u8    schema version (2)
    3      1    u8    message kind: 1 plan, 2 status, 3 target observation, 4 fleet epoch
    4      1    u8    sender id, the vehicle's MAVLink system id (1..250)
    5      1    u8    reserved, 0
    6      4    u32   sequence number, per sender and kind, increasing
    10     8    i64   simulated timestamp [ns] (>= 0); for a plan, the time of states[0]

PlanMessage (kind 1), 18 + 24 + 40 M + 24 bytes (266 bytes at M = 5)::

    18     8    i64   period_ns, time between plan states (1 .. 60e9)
    26     2    u16   horizon M (1..100)
    28     1    u8    mode (VehicleMode)
    29     1    u8    flags: bit 0 qp_fallback, bit 1 learning_on; other bits 0
    30     8    f64   first_c_norm, Euclidean norm of the first input correction c_0
    38     4    u32   solve_time_us, QP solve time [us]
    42     24(M+1) f64 states, row-major (x North m, y East m, yaw rad) for j = 0..M
    ..     16M  f64   inputs, row-major (speed m/s, yaw rate rad/s) for j = 0..M-1

StatusMessage (kind 2), 149 bytes::

    18     1    u8    mode (VehicleMode)
    19     1    u8    flags: bit 0 armed, bit 1 learning_on, bit 2 learning_frozen; other bits 0
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
invalid data raises ConfigError (a ValueError) naming the field.
"""

import math
import numbers
import struct
from collections.abc import MutableMapping
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum

import numpy as np

from fleetmpc.errors import ConfigError, FleetMpcError
from fleetmpc.protocol.plan import Plan

__all__ = [
    "MAGIC",
    "MAX_HORIZON",
    "MAX_NEIGHBOURS",
    "MAX_SENDER_ID",
    "MIN_SENDER_ID",
    "SCHEMA_VERSION",
    "DecodeError",
    "FleetEpoch",
    "GROUND_STATION_ID",
    "TARGET_ID",
    "LearnedParams",
    "Message",
    "MessageKind",
    "NeighbourPlanAge",
    "PlanMessage",
    "PlanStatus",
    "RejectReason",
    "StatusMessage",
    "TargetObservation",
    "VehicleMode",
    "VehicleStatus",
    "decode",
    "decode_or_none",
    "encode",
]

MAGIC = b"FM"
SCHEMA_VERSION = 2
MIN_SENDER_ID = 1
MAX_SENDER_ID = 250
GROUND_STATION_ID = 249
"""Sender id of the ground station (it announces the fleet epoch)."""
TARGET_ID = 250
"""Sender id of the scripted target's observations."""
MAX_HORIZON = 100
MAX_NEIGHBOURS = 8
MAX_PERIOD_NS = 60_000_000_000
MAX_ABS_POSITION_M = 1e6
MAX_ABS_YAW_RAD = 1e4
MAX_ABS_SPEED_M_S = 1e3
MAX_ABS_YAW_RATE_RAD_S = 1e3
MAX_ABS_PARAM = 1e3
MAX_DISTANCE_M = 1e7
_U32 = 2**32 - 1
_I64_MIN, _I64_MAX = -(2**63), 2**63 - 1

_HEADER = struct.Struct("<2sBBBBIq")
_PLAN_FIXED = struct.Struct("<qHBBdI")
_STATUS_FIXED = struct.Struct("<BBB4ddIId")
_NEIGHBOUR = struct.Struct("<Bq")
_TARGET = struct.Struct("<B5d")
_EPOCH = struct.Struct("<qd")
_STATUS_SIZE = _HEADER.size + _STATUS_FIXED.size + MAX_NEIGHBOURS * _NEIGHBOUR.size
_TARGET_SIZE = _HEADER.size + _TARGET.size
_EPOCH_SIZE = _HEADER.size + _EPOCH.size
MIN_SPEED, MAX_SPEED = 0.01, 1000.0
MAX_SETPOINT_RATE_HZ = 1e4


class MessageKind(IntEnum):
    """Message kind byte of the header."""

    PLAN = 1
    STATUS = 2
    TARGET_OBSERVATION = 3
    FLEET_EPOCH = 4


class VehicleMode(IntEnum):
    """What the onboard agent is doing."""

    UNKNOWN = 0
    STANDBY = 1
    """On the ground or disarmed."""
    TAKEOFF = 2
    OFFBOARD = 3
    """Flying the formation under MPC (PX4 offboard / ArduPilot guided)."""
    HOLD = 4
    LAND = 5
    FAILSAFE = 6


class RejectReason(StrEnum):
    """Why a received message was rejected; the key of the rejection counters."""

    SIZE = "size"
    """Not bytes, truncated, or the wrong length for its kind and horizon."""
    MAGIC = "magic"
    VERSION = "version"
    KIND = "kind"
    """Unknown kind, or not the kind its key carries."""
    SENDER = "sender"
    """Sender id outside 1..250."""
    NON_FINITE = "non_finite"
    RANGE = "range"
    """A field outside its documented range, including reserved bits and bytes."""
    KEY = "key"
    """Arrived on a key that is not a fleetmpc key (checked by the plan bus)."""
    KEY_MISMATCH = "key_mismatch"
    """Its sender id differs from the vehicle id in its key (checked by the plan bus)."""
    INTERNAL = "internal"
    """An unexpected error while handling it: a bug, should stay 0."""


class DecodeError(FleetMpcError, ValueError):
    """A payload is not a valid message; `reason` says which check failed."""

    def __init__(self, reason: RejectReason, message: str) -> None:
        self.reason = reason
        super().__init__(f"{reason.value}: {message}")


class _FieldError(ConfigError):
    """ConfigError that also carries the rejection reason `decode` reports."""

    def __init__(self, field_name: str, reason: RejectReason, message: str) -> None:
        self.reason = reason
        super().__init__(field_name, message)


def _int(name: str, value: object, lo: int, hi: int, *, reason=RejectReason.RANGE) -> int:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise _FieldError(name, reason, f"must be an integer, got {value!r}")
    v = int(value)
    if not lo <= v <= hi:
        raise _FieldError(name, reason, f"must be in [{lo}, {hi}], got {v}")
    return v


def _float(name: str, value: object, bound: float, *, lo: float | None = None) -> float:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise _FieldError(name, RejectReason.RANGE, f"must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise _FieldError(name, RejectReason.NON_FINITE, f"must be finite, got {x}")
    low = -bound if lo is None else lo
    if not low <= x <= bound:
        raise _FieldError(name, RejectReason.RANGE, f"must be in [{low}, {bound}], got {x}")
    return x


def _bool(name: str, value: object) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise _FieldError(name, RejectReason.RANGE, f"must be a bool, got {value!r}")
    return bool(value)


def _mode(name: str, value: object) -> VehicleMode:
    try:
        return VehicleMode(value)
    except ValueError:
        raise _FieldError(name, RejectReason.RANGE, f"unknown mode {value!r}") from None


def _array(name: str, value: object, rows: int, bounds: tuple[float, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _FieldError(name, RejectReason.RANGE, "must be an array of numbers") from None
    if a.shape != (rows, len(bounds)):
        raise _FieldError(name, RejectReason.RANGE, f"must have shape {(rows, len(bounds))}")
    if not np.isfinite(a).all():
        raise _FieldError(name, RejectReason.NON_FINITE, "must be finite")
    if (np.abs(a) > np.asarray(bounds)).any():
        raise _FieldError(name, RejectReason.RANGE, f"columns must stay within +-{bounds}")
    return a


@dataclass(frozen=True)
class PlanStatus:
    """The small status block carried with every plan."""

    mode: VehicleMode = VehicleMode.OFFBOARD
    """What the agent was doing when it planned."""
    qp_fallback: bool = False
    """True if the QP failed and the first input is the clipped tube feedback law."""
    learning_on: bool = False
    """True if the plan used the learned model."""
    first_c_norm: float = 0.0
    """Euclidean norm of the first input correction c_0 (mixed m/s and rad/s units)."""
    solve_time_us: int = 0
    """QP solve time [us]."""

    def __post_init__(self) -> None:
        _mode("status.mode", self.mode)
        _bool("status.qp_fallback", self.qp_fallback)
        _bool("status.learning_on", self.learning_on)
        _float("status.first_c_norm", self.first_c_norm, MAX_DISTANCE_M, lo=0.0)
        _int("status.solve_time_us", self.solve_time_us, 0, _U32)


@dataclass(frozen=True, eq=False)
class PlanMessage:
    """A vehicle's assumed trajectory plus its status block; sender and stamp come from `plan`."""

    seq: int
    """Sequence number of the sender's plan messages (u32)."""
    plan: Plan
    """The assumed trajectory."""
    status: PlanStatus = field(default_factory=PlanStatus)
    """Status of the solve that produced the plan."""

    def __post_init__(self) -> None:
        _int("seq", self.seq, 0, _U32)
        p = self.plan
        if not isinstance(p, Plan):
            raise _FieldError("plan", RejectReason.RANGE, f"must be a Plan, got {p!r}")
        if not isinstance(self.status, PlanStatus):
            raise _FieldError("status", RejectReason.RANGE, "must be a PlanStatus")
        _int("plan.vehicle_id", p.vehicle_id, MIN_SENDER_ID, MAX_SENDER_ID)
        _int("plan.stamp_ns", p.stamp_ns, 0, _I64_MAX)
        _int("plan.period_ns", p.period_ns, 1, MAX_PERIOD_NS)
        inputs_shape = np.shape(p.inputs)
        if len(inputs_shape) != 2 or inputs_shape[1] != 2:
            raise _FieldError("plan.inputs", RejectReason.RANGE, "must have shape (M, 2)")
        m = inputs_shape[0]
        _int("plan.horizon", m, 1, MAX_HORIZON)
        pos, yaw = MAX_ABS_POSITION_M, MAX_ABS_YAW_RAD
        _array("plan.states", p.states, m + 1, (pos, pos, yaw))
        _array("plan.inputs", p.inputs, m, (MAX_ABS_SPEED_M_S, MAX_ABS_YAW_RATE_RAD_S))

    kind = MessageKind.PLAN

    @property
    def sender_id(self) -> int:
        return int(self.plan.vehicle_id)

    @property
    def stamp_ns(self) -> int:
        return int(self.plan.stamp_ns)


@dataclass(frozen=True)
class LearnedParams:
    """The learned parameter vector beta of the oracle (DEKF estimate)."""

    speed_effectiveness: float = 1.0
    """Achieved / commanded forward speed [-]."""
    yaw_rate_effectiveness: float = 1.0
    """Achieved / commanded yaw rate [-]."""
    drift_north_m_s: float = 0.0
    """Constant drift (wind) North [m/s]."""
    drift_east_m_s: float = 0.0
    """Constant drift (wind) East [m/s]."""

    def __post_init__(self) -> None:
        for name in (
            "speed_effectiveness",
            "yaw_rate_effectiveness",
            "drift_north_m_s",
            "drift_east_m_s",
        ):
            _float(f"beta.{name}", getattr(self, name), MAX_ABS_PARAM)

    def as_tuple(self) -> tuple[float, float, float, float]:
        return (
            self.speed_effectiveness,
            self.yaw_rate_effectiveness,
            self.drift_north_m_s,
            self.drift_east_m_s,
        )


@dataclass(frozen=True)
class NeighbourPlanAge:
    """How old the latest plan received from one neighbour was."""

    vehicle_id: int
    """Neighbour system id (1..250)."""
    age_ns: int
    """Reporter's time minus the plan's stamp [ns] (negative if stamped in the future)."""

    def __post_init__(self) -> None:
        _int("neighbour.vehicle_id", self.vehicle_id, MIN_SENDER_ID, MAX_SENDER_ID)
        _int("neighbour.age_ns", self.age_ns, _I64_MIN, _I64_MAX)


@dataclass(frozen=True)
class VehicleStatus:
    """A vehicle's status as broadcast on its status key."""

    mode: VehicleMode = VehicleMode.UNKNOWN
    """What the agent is doing."""
    armed: bool = False
    """True if the autopilot reports armed."""
    learning_on: bool = False
    """True if the controller uses the learned model."""
    learning_frozen: bool = False
    """True if the parameter filter has been frozen."""
    beta: LearnedParams = field(default_factory=LearnedParams)
    """Current learned parameter estimate."""
    slot_error_m: float = 0.0
    """Distance from the vehicle to its formation slot [m]."""
    neighbour_plan_ages: tuple[NeighbourPlanAge, ...] = ()
    """Age of the latest plan of up to 8 neighbours, distinct ids."""
    qp_fallbacks: int = 0
    """Control periods so far that applied the fallback law (u32)."""
    rejected_messages: int = 0
    """Received messages so far rejected by the vehicle's bus (u32)."""
    setpoint_rate_hz: float = 0.0
    """Setpoints sent to the autopilot per simulated second, over the last period."""

    def __post_init__(self) -> None:
        _mode("status.mode", self.mode)
        for name in ("armed", "learning_on", "learning_frozen"):
            _bool(f"status.{name}", getattr(self, name))
        if not isinstance(self.beta, LearnedParams):
            raise _FieldError("status.beta", RejectReason.RANGE, "must be a LearnedParams")
        _float("status.slot_error_m", self.slot_error_m, MAX_DISTANCE_M, lo=0.0)
        ages = tuple(self.neighbour_plan_ages)
        object.__setattr__(self, "neighbour_plan_ages", ages)
        if len(ages) > MAX_NEIGHBOURS or not all(isinstance(a, NeighbourPlanAge) for a in ages):
            raise _FieldError(
                "status.neighbour_plan_ages",
                RejectReason.RANGE,
                f"must be at most {MAX_NEIGHBOURS} NeighbourPlanAge entries",
            )
        if len({a.vehicle_id for a in ages}) != len(ages):
            raise _FieldError(
                "status.neighbour_plan_ages", RejectReason.RANGE, "neighbour ids must be distinct"
            )
        _int("status.qp_fallbacks", self.qp_fallbacks, 0, _U32)
        _int("status.rejected_messages", self.rejected_messages, 0, _U32)
        _float("status.setpoint_rate_hz", self.setpoint_rate_hz, MAX_SETPOINT_RATE_HZ, lo=0.0)


@dataclass(frozen=True)
class StatusMessage:
    """Header plus a VehicleStatus."""

    sender_id: int
    """Reporting vehicle's system id (1..250)."""
    seq: int
    """Sequence number of the sender's status messages (u32)."""
    stamp_ns: int
    """Simulated time of the status [ns]."""
    status: VehicleStatus
    """The status."""

    kind = MessageKind.STATUS

    def __post_init__(self) -> None:
        _header_fields(self.sender_id, self.seq, self.stamp_ns)
        if not isinstance(self.status, VehicleStatus):
            raise _FieldError("status", RejectReason.RANGE, "must be a VehicleStatus")


@dataclass(frozen=True)
class TargetObservation:
    """An observation of the target's position (and optionally velocity) in the local frame."""

    sender_id: int
    """Observer's system id (1..250)."""
    seq: int
    """Sequence number of the sender's observations (u32)."""
    stamp_ns: int
    """Simulated time of the observation [ns]."""
    north_m: float
    """Target position North [m]."""
    east_m: float
    """Target position East [m]."""
    noise_std_m: float = 0.0
    """1-sigma noise of the position [m]."""
    velocity_m_s: tuple[float, float] | None = None
    """Target velocity (North, East) [m/s], if observed."""

    kind = MessageKind.TARGET_OBSERVATION

    def __post_init__(self) -> None:
        _header_fields(self.sender_id, self.seq, self.stamp_ns)
        _float("north_m", self.north_m, MAX_ABS_POSITION_M)
        _float("east_m", self.east_m, MAX_ABS_POSITION_M)
        _float("noise_std_m", self.noise_std_m, MAX_DISTANCE_M, lo=0.0)
        if self.velocity_m_s is not None:
            v = self.velocity_m_s
            if isinstance(v, str) or not hasattr(v, "__len__") or len(v) != 2:
                raise _FieldError("velocity_m_s", RejectReason.RANGE, "must be (north, east)")
            vel = tuple(_float(f"velocity_m_s[{i}]", x, MAX_ABS_SPEED_M_S) for i, x in enumerate(v))
            object.__setattr__(self, "velocity_m_s", vel)


@dataclass(frozen=True)
class FleetEpoch:
    """When fleet time 0 is on the host's wall clock, and how fast fleet time runs."""

    sender_id: int
    """Announcer's id (the ground station's, 1..250)."""
    seq: int
    """Sequence number of the sender's announcements (u32)."""
    epoch_ns: int
    """Host wall-clock time (Unix ns) of fleet time 0."""
    speed: float
    """Simulated seconds per wall-clock second."""
    stamp_ns: int = 0
    """Always 0: an epoch is not a sample of fleet time."""

    kind = MessageKind.FLEET_EPOCH

    def __post_init__(self) -> None:
        _header_fields(self.sender_id, self.seq, self.stamp_ns)
        _int("epoch_ns", self.epoch_ns, 1, _I64_MAX)
        _float("speed", self.speed, MAX_SPEED, lo=MIN_SPEED)


Message = PlanMessage | StatusMessage | TargetObservation | FleetEpoch


def _header_fields(sender_id: object, seq: object, stamp_ns: object) -> None:
    _int("sender_id", sender_id, MIN_SENDER_ID, MAX_SENDER_ID, reason=RejectReason.SENDER)
    _int("seq", seq, 0, _U32)
    _int("stamp_ns", stamp_ns, 0, _I64_MAX)


def _header(kind: MessageKind, sender_id: int, seq: int, stamp_ns: int) -> bytes:
    return _HEADER.pack(MAGIC, SCHEMA_VERSION, kind, int(sender_id), 0, int(seq), int(stamp_ns))


def encode(message: Message) -> bytes:
    """Serialize a message (already validated at construction) to its wire bytes."""
    if isinstance(message, PlanMessage):
        p, s = message.plan, message.status
        flags = int(s.qp_fallback) | int(s.learning_on) << 1
        m = int(np.shape(p.inputs)[0])
        return b"".join(
            (
                _header(MessageKind.PLAN, p.vehicle_id, message.seq, p.stamp_ns),
                _PLAN_FIXED.pack(
                    int(p.period_ns), m, s.mode, flags, s.first_c_norm, s.solve_time_us
                ),
                np.ascontiguousarray(p.states, dtype="<f8").tobytes(),
                np.ascontiguousarray(p.inputs, dtype="<f8").tobytes(),
            )
        )
    if isinstance(message, StatusMessage):
        st = message.status
        flags = int(st.armed) | int(st.learning_on) << 1 | int(st.learning_frozen) << 2
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


def _decode_plan(data: bytes, sender: int, seq: int, stamp: int) -> PlanMessage:
    base = _HEADER.size + _PLAN_FIXED.size
    if len(data) < base:
        raise _reject(RejectReason.SIZE, f"plan needs at least {base} bytes, got {len(data)}")
    period, m, mode, flags, c_norm, solve_us = _PLAN_FIXED.unpack_from(data, _HEADER.size)
    if not 1 <= m <= MAX_HORIZON:
        raise _reject(RejectReason.RANGE, f"horizon must be in [1, {MAX_HORIZON}], got {m}")
    size = base + 8 * (3 * (m + 1) + 2 * m)
    if len(data) != size:
        raise _reject(RejectReason.SIZE, f"plan of horizon {m} is {size} bytes, got {len(data)}")
    if flags & ~0b11:
        raise _reject(RejectReason.RANGE, f"reserved plan flag bits set: {flags:#04x}")
    states = _read_f64(data, base, m + 1, 3)
    inputs = _read_f64(data, base + 24 * (m + 1), m, 2)
    status = PlanStatus(
        mode=_mode("status.mode", mode),
        qp_fallback=bool(flags & 1),
        learning_on=bool(flags & 2),
        first_c_norm=c_norm,
        solve_time_us=solve_us,
    )
    plan = Plan(vehicle_id=sender, stamp_ns=stamp, period_ns=period, states=states, inputs=inputs)
    return PlanMessage(seq=seq, plan=plan, status=status)


def _decode_status(data: bytes, sender: int, seq: int, stamp: int) -> StatusMessage:
    if len(data) != _STATUS_SIZE:
        raise _reject(RejectReason.SIZE, f"status is {_STATUS_SIZE} bytes, got {len(data)}")
    mode, flags, count, *rest = _STATUS_FIXED.unpack_from(data, _HEADER.size)
    beta, (slot_error, fallbacks, rejected, setpoint_rate) = rest[:4], rest[4:]
    if flags & ~0b111:
        raise _reject(RejectReason.RANGE, f"reserved status flag bits set: {flags:#04x}")
    if count > MAX_NEIGHBOURS:
        raise _reject(RejectReason.RANGE, f"at most {MAX_NEIGHBOURS} neighbours, got {count}")
    offset = _HEADER.size + _STATUS_FIXED.size
    entries = [_NEIGHBOUR.unpack_from(data, offset + i * _NEIGHBOUR.size) for i in range(8)]
    if any(e != (0, 0) for e in entries[count:]):
        raise _reject(RejectReason.RANGE, "unused neighbour entries must be zero")
    status = VehicleStatus(
        mode=_mode("status.mode", mode),
        armed=bool(flags & 1),
        learning_on=bool(flags & 2),
        learning_frozen=bool(flags & 4),
        beta=LearnedParams(*beta),
        slot_error_m=slot_error,
        neighbour_plan_ages=tuple(NeighbourPlanAge(i, age) for i, age in entries[:count]),
        qp_fallbacks=fallbacks,
        rejected_messages=rejected,
        setpoint_rate_hz=setpoint_rate,
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
    except _FieldError as e:
        raise _reject(e.reason, str(e)) from None


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
