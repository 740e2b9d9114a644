"""The messages of the fleet's Zenoh keys: plans, statuses, target observations, fleet epochs.

Each message is a frozen dataclass checked when it is constructed: invalid data raises ConfigError
(a ValueError) naming the field. Limits: |x|, |y| <= 1e6 m, |yaw| <= 1e4 rad (unwrapped headings
are fine), |speed| <= 1e3 m/s, |yaw rate| <= 1e3 rad/s, |beta| <= 1e3. A failed field check also
carries the `RejectReason` a decoder reports for the same defect. `fleetmpc.protocol.codec` puts
the messages on the wire.
"""

import math
import numbers
from dataclasses import dataclass, field
from enum import IntEnum, StrEnum

import numpy as np

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.plan import Plan, WindSample

__all__ = [
    "MAX_HORIZON",
    "MAX_NEIGHBOURS",
    "MAX_SENDER_ID",
    "MIN_SENDER_ID",
    "FieldError",
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
    "vehicle_mode",
]

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


class TargetState(IntEnum):
    """What a vehicle's formation follows (`fleetmpc.onboard.core.target_watch`)."""

    TRACKING = 0
    """The target's observations come; its estimate."""
    PREDICTING = 1
    """Lost: its prediction, for a bounded time."""
    HOLDING = 2
    """Lost for longer: the formation holds where it is."""
    REACQUIRING = 3
    """Back: the reference glides onto the new estimate."""


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


class FieldError(ConfigError):
    """ConfigError that also carries the rejection reason `decode` reports."""

    def __init__(self, field_name: str, reason: RejectReason, message: str) -> None:
        self.reason = reason
        super().__init__(field_name, message)


def _int(name: str, value: object, lo: int, hi: int, *, reason=RejectReason.RANGE) -> int:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise FieldError(name, reason, f"must be an integer, got {value!r}")
    v = int(value)
    if not lo <= v <= hi:
        raise FieldError(name, reason, f"must be in [{lo}, {hi}], got {v}")
    return v


def _float(name: str, value: object, bound: float, *, lo: float | None = None) -> float:
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise FieldError(name, RejectReason.RANGE, f"must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise FieldError(name, RejectReason.NON_FINITE, f"must be finite, got {x}")
    low = -bound if lo is None else lo
    if not low <= x <= bound:
        raise FieldError(name, RejectReason.RANGE, f"must be in [{low}, {bound}], got {x}")
    return x


def _wind_sample(w: object) -> None:
    if not isinstance(w, WindSample):
        raise FieldError("plan.wind", RejectReason.RANGE, f"must be a WindSample, got {w!r}")
    _float("plan.wind.heading_rad", w.heading_rad, MAX_ABS_YAW_RAD)
    _float("plan.wind.across_m_s", w.across_m_s, MAX_ABS_SPEED_M_S)
    _float("plan.wind.std_m_s", w.std_m_s, MAX_ABS_SPEED_M_S, lo=0.0)
    if w.std_m_s == 0.0:
        raise FieldError("plan.wind.std_m_s", RejectReason.RANGE, "must be > 0, got 0.0")


def _bool(name: str, value: object) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise FieldError(name, RejectReason.RANGE, f"must be a bool, got {value!r}")
    return bool(value)


def vehicle_mode(name: str, value: object) -> VehicleMode:
    """The VehicleMode of a field's value; a FieldError naming the field if there is none."""
    try:
        return VehicleMode(value)
    except ValueError:
        raise FieldError(name, RejectReason.RANGE, f"unknown mode {value!r}") from None


def _array(name: str, value: object, rows: int, bounds: tuple[float, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FieldError(name, RejectReason.RANGE, "must be an array of numbers") from None
    if a.shape != (rows, len(bounds)):
        raise FieldError(name, RejectReason.RANGE, f"must have shape {(rows, len(bounds))}")
    if not np.isfinite(a).all():
        raise FieldError(name, RejectReason.NON_FINITE, "must be finite")
    if (np.abs(a) > np.asarray(bounds)).any():
        raise FieldError(name, RejectReason.RANGE, f"columns must stay within +-{bounds}")
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
        vehicle_mode("status.mode", self.mode)
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
            raise FieldError("plan", RejectReason.RANGE, f"must be a Plan, got {p!r}")
        if not isinstance(self.status, PlanStatus):
            raise FieldError("status", RejectReason.RANGE, "must be a PlanStatus")
        _int("plan.vehicle_id", p.vehicle_id, MIN_SENDER_ID, MAX_SENDER_ID)
        _int("plan.stamp_ns", p.stamp_ns, 0, _I64_MAX)
        _int("plan.period_ns", p.period_ns, 1, MAX_PERIOD_NS)
        inputs_shape = np.shape(p.inputs)
        if len(inputs_shape) != 2 or inputs_shape[1] != 2:
            raise FieldError("plan.inputs", RejectReason.RANGE, "must have shape (M, 2)")
        m = inputs_shape[0]
        _int("plan.horizon", m, 1, MAX_HORIZON)
        pos, yaw = MAX_ABS_POSITION_M, MAX_ABS_YAW_RAD
        _array("plan.states", p.states, m + 1, (pos, pos, yaw))
        _array("plan.inputs", p.inputs, m, (MAX_ABS_SPEED_M_S, MAX_ABS_YAW_RATE_RAD_S))
        if p.wind is not None:
            _wind_sample(p.wind)

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
    target_state: TargetState = TargetState.TRACKING
    """What the vehicle's formation follows: the target, its prediction, a hold, a glide back."""

    def __post_init__(self) -> None:
        vehicle_mode("status.mode", self.mode)
        if not isinstance(self.target_state, TargetState):
            raise FieldError("status.target_state", RejectReason.RANGE, "must be a TargetState")
        for name in ("armed", "learning_on", "learning_frozen"):
            _bool(f"status.{name}", getattr(self, name))
        if not isinstance(self.beta, LearnedParams):
            raise FieldError("status.beta", RejectReason.RANGE, "must be a LearnedParams")
        _float("status.slot_error_m", self.slot_error_m, MAX_DISTANCE_M, lo=0.0)
        ages = tuple(self.neighbour_plan_ages)
        object.__setattr__(self, "neighbour_plan_ages", ages)
        if len(ages) > MAX_NEIGHBOURS or not all(isinstance(a, NeighbourPlanAge) for a in ages):
            raise FieldError(
                "status.neighbour_plan_ages",
                RejectReason.RANGE,
                f"must be at most {MAX_NEIGHBOURS} NeighbourPlanAge entries",
            )
        if len({a.vehicle_id for a in ages}) != len(ages):
            raise FieldError(
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
            raise FieldError("status", RejectReason.RANGE, "must be a VehicleStatus")


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
                raise FieldError("velocity_m_s", RejectReason.RANGE, "must be (north, east)")
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
