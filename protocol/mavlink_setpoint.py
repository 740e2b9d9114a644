"""SET_POSITION_TARGET_LOCAL_NED as the SITL autopilot and the onboard agent write and read it.

Everything here is plain numbers and pure functions (no pymavlink): the frames and type masks
accepted, the one conversion between a unicycle command (forward speed V, yaw rate omega) and the
fields of SET_POSITION_TARGET_LOCAL_NED, and the checks made before a setpoint is acted on.
A position setpoint (`TypeMask.POSITION`, LOCAL_NED only) asks the autopilot's own position
controller to fly to and hold a point: what an agent streams while the fleet waits to start.

Frames (x North, y East, z Down; yaw clockwise from North seen from above):
- LOCAL_NED (1): velocity in the local NED frame; yaw is an absolute heading.
- BODY_NED (8) and BODY_OFFSET_NED (9): velocity in the body frame (x forward, y right, z down)
  rotated by yaw only. PX4 reads yaw as an absolute heading in every frame; ArduPilot reads it as
  relative to the current heading in the two body frames (`yaw_relative_in_body`).

A unicycle can only fly along its heading. Decoding keeps the horizontal velocity's projection
on the current heading as the forward speed and drops the lateral component (it cannot be flown);
the vertical component (z Down) is returned separately as a climb rate.
"""

import math
from dataclasses import dataclass
from enum import Enum, IntEnum

from fleetmpc.protocol.local_frame import wrap_pi

__all__ = [
    "MAX_PLAUSIBLE_POSITION_M",
    "MAX_PLAUSIBLE_SPEED_M_S",
    "MAX_PLAUSIBLE_YAW_RAD",
    "MAX_PLAUSIBLE_YAW_RATE_RAD_S",
    "SUPPORTED_FRAMES",
    "SUPPORTED_TYPE_MASKS",
    "Frame",
    "PositionDemand",
    "Rejection",
    "SetpointFields",
    "TypeMask",
    "UnicycleDemand",
    "check_setpoint",
    "decode_setpoint",
    "encode_position_setpoint",
    "encode_setpoint",
    "setpoint_message_args",
]


class Frame(IntEnum):
    """MAV_FRAME values accepted in SET_POSITION_TARGET_LOCAL_NED."""

    LOCAL_NED = 1
    BODY_NED = 8
    BODY_OFFSET_NED = 9


SUPPORTED_FRAMES = frozenset(int(f) for f in Frame)


class TypeMask(IntEnum):
    """POSITION_TARGET_TYPEMASK combinations (bits set = field ignored)."""

    VELOCITY_YAW_RATE = 1479
    """vx, vy, vz, yaw_rate used; ignored: position 1|2|4, acceleration 64|128|256, yaw 1024."""
    VELOCITY_YAW = 2503
    """vx, vy, vz and yaw used: ignore position, acceleration and yaw_rate (2048)."""
    POSITION = 3576
    """x, y, z used (LOCAL_NED only): ignore velocity 8|16|32, acceleration, yaw and yaw_rate."""


SUPPORTED_TYPE_MASKS = frozenset(int(m) for m in TypeMask)


class Rejection(Enum):
    """Why a SET_POSITION_TARGET_LOCAL_NED was not acted on."""

    UNSUPPORTED_FRAME = "unsupported frame"
    UNSUPPORTED_MASK = "unsupported type_mask"
    NON_FINITE = "NaN or Inf field"
    IMPLAUSIBLE = "implausibly large value"


@dataclass(frozen=True)
class SetpointFields:
    """The SET_POSITION_TARGET_LOCAL_NED fields a velocity or position setpoint uses."""

    frame: int
    """MAV_FRAME (see Frame)."""
    type_mask: int
    """POSITION_TARGET_TYPEMASK (see TypeMask)."""
    vx_m_s: float = 0.0
    """Velocity x [m/s]: North (LOCAL_NED) or forward (body frames)."""
    vy_m_s: float = 0.0
    """Velocity y [m/s]: East (LOCAL_NED) or right (body frames)."""
    vz_m_s: float = 0.0
    """Velocity z [m/s], positive down."""
    yaw_rad: float = 0.0
    """Yaw setpoint [rad] (used with TypeMask.VELOCITY_YAW)."""
    yaw_rate_rad_s: float = 0.0
    """Yaw-rate setpoint [rad/s] (used with TypeMask.VELOCITY_YAW_RATE)."""
    x_m: float = 0.0
    """Position North [m] (used with TypeMask.POSITION)."""
    y_m: float = 0.0
    """Position East [m] (used with TypeMask.POSITION)."""
    z_m: float = 0.0
    """Position Down [m] (used with TypeMask.POSITION)."""


def setpoint_message_args(
    sp: SetpointFields, *, time_boot_ms: int, target_system: int, target_component: int = 1
) -> tuple:
    """Positional arguments of pymavlink's SET_POSITION_TARGET_LOCAL_NED encode/send for `sp`.

    Field order: time_boot_ms, target system, target component, frame, type_mask, x, y, z,
    vx, vy, vz, afx, afy, afz, yaw, yaw_rate (acceleration unused, sent as 0).
    """
    return (
        time_boot_ms,
        target_system,
        target_component,
        sp.frame,
        sp.type_mask,
        sp.x_m,
        sp.y_m,
        sp.z_m,
        sp.vx_m_s,
        sp.vy_m_s,
        sp.vz_m_s,
        0.0,
        0.0,
        0.0,
        sp.yaw_rad,
        sp.yaw_rate_rad_s,
    )


@dataclass(frozen=True)
class UnicycleDemand:
    """What a setpoint asks of the unicycle, before the vehicle's limits are applied."""

    speed_m_s: float
    """Forward speed along the current heading [m/s]."""
    yaw_rate_rad_s: float
    """Yaw rate [rad/s], clockwise seen from above."""
    climb_rate_m_s: float
    """Vertical speed, positive up [m/s]."""


MAX_PLAUSIBLE_SPEED_M_S = 100.0
"""Velocity components beyond this are treated as corrupt, not clamped."""
MAX_PLAUSIBLE_YAW_RATE_RAD_S = 50.0
"""Yaw rates beyond this are treated as corrupt, not clamped."""
MAX_PLAUSIBLE_YAW_RAD = 4.0 * math.pi
"""Yaw setpoints beyond this magnitude are treated as corrupt."""
MAX_PLAUSIBLE_POSITION_M = 1.0e5
"""Position setpoints farther than this from home (any axis) are treated as corrupt."""


@dataclass(frozen=True)
class PositionDemand:
    """What a position setpoint asks of the autopilot's position controller."""

    north_m: float
    """Point to fly to and hold, North [m]."""
    east_m: float
    """Point to fly to and hold, East [m]."""
    altitude_m: float
    """Altitude above home to hold [m] (the setpoint's z is Down)."""


def check_setpoint(sp: SetpointFields) -> Rejection | None:
    """None if a decoder may act on `sp`, else why not. Checks only the fields the mask uses."""
    if sp.frame not in SUPPORTED_FRAMES:
        return Rejection.UNSUPPORTED_FRAME
    if sp.type_mask not in SUPPORTED_TYPE_MASKS:
        return Rejection.UNSUPPORTED_MASK
    if sp.type_mask == TypeMask.POSITION:
        if sp.frame != Frame.LOCAL_NED:
            return Rejection.UNSUPPORTED_FRAME  # a body-frame point would move with the vehicle
        position = (sp.x_m, sp.y_m, sp.z_m)
        if not all(math.isfinite(v) for v in position):
            return Rejection.NON_FINITE
        if max(abs(v) for v in position) > MAX_PLAUSIBLE_POSITION_M:
            return Rejection.IMPLAUSIBLE
        return None
    yaw_value = sp.yaw_rad if sp.type_mask == TypeMask.VELOCITY_YAW else sp.yaw_rate_rad_s
    values = (sp.vx_m_s, sp.vy_m_s, sp.vz_m_s, yaw_value)
    if not all(math.isfinite(v) for v in values):
        return Rejection.NON_FINITE
    if max(abs(sp.vx_m_s), abs(sp.vy_m_s), abs(sp.vz_m_s)) > MAX_PLAUSIBLE_SPEED_M_S:
        return Rejection.IMPLAUSIBLE
    yaw_limit = (
        MAX_PLAUSIBLE_YAW_RAD
        if sp.type_mask == TypeMask.VELOCITY_YAW
        else MAX_PLAUSIBLE_YAW_RATE_RAD_S
    )
    if abs(yaw_value) > yaw_limit:
        return Rejection.IMPLAUSIBLE
    return None


def decode_setpoint(
    sp: SetpointFields,
    *,
    heading_rad: float,
    yaw_gain_1_s: float,
    yaw_relative_in_body: bool = False,
) -> UnicycleDemand | PositionDemand | Rejection:
    """The demand of a setpoint at the current heading, or why it is rejected.

    A position setpoint is a `PositionDemand` (heading-independent). For a velocity setpoint the
    forward speed is the horizontal velocity projected on the heading (the lateral part is
    dropped: a unicycle cannot fly it). With TypeMask.VELOCITY_YAW the yaw rate is
    `yaw_gain_1_s` times the wrapped heading error.
    """
    rejection = check_setpoint(sp)
    if rejection is not None:
        return rejection
    if sp.type_mask == TypeMask.POSITION:
        return PositionDemand(north_m=sp.x_m, east_m=sp.y_m, altitude_m=-sp.z_m)
    body = sp.frame != Frame.LOCAL_NED
    if body:
        speed = sp.vx_m_s
    else:
        speed = sp.vx_m_s * math.cos(heading_rad) + sp.vy_m_s * math.sin(heading_rad)
    if sp.type_mask == TypeMask.VELOCITY_YAW_RATE:
        yaw_rate = sp.yaw_rate_rad_s
    else:
        error = sp.yaw_rad if (body and yaw_relative_in_body) else sp.yaw_rad - heading_rad
        yaw_rate = yaw_gain_1_s * wrap_pi(error)
    return UnicycleDemand(speed_m_s=speed, yaw_rate_rad_s=yaw_rate, climb_rate_m_s=-sp.vz_m_s)


def encode_setpoint(
    speed_m_s: float,
    yaw_rate_rad_s: float,
    *,
    frame: Frame = Frame.BODY_NED,
    heading_rad: float = 0.0,
    climb_rate_m_s: float = 0.0,
) -> SetpointFields:
    """SET_POSITION_TARGET_LOCAL_NED fields (mask 1479) for a unicycle command.

    In body frames the velocity is (forward, 0); in LOCAL_NED it is rotated by `heading_rad`.
    """
    if frame == Frame.LOCAL_NED:
        vx, vy = speed_m_s * math.cos(heading_rad), speed_m_s * math.sin(heading_rad)
    else:
        vx, vy = speed_m_s, 0.0
    return SetpointFields(
        frame=int(frame),
        type_mask=int(TypeMask.VELOCITY_YAW_RATE),
        vx_m_s=vx,
        vy_m_s=vy,
        vz_m_s=-climb_rate_m_s,
        yaw_rate_rad_s=yaw_rate_rad_s,
    )


def encode_position_setpoint(north_m: float, east_m: float, down_m: float) -> SetpointFields:
    """SET_POSITION_TARGET_LOCAL_NED fields (mask 3576): fly to and hold a point, yaw unchanged."""
    return SetpointFields(
        frame=int(Frame.LOCAL_NED),
        type_mask=int(TypeMask.POSITION),
        x_m=north_m,
        y_m=east_m,
        z_m=down_m,
    )
