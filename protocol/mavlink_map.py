"""MAVLink field mapping shared by the SITL autopilot and the onboard agent.

Everything here is plain integers and pure functions (no pymavlink): the numbers PX4 and ArduPilot
put on the wire, the flight-mode encodings, and the one conversion between a unicycle command
(forward speed V, yaw rate omega) and the fields of SET_POSITION_TARGET_LOCAL_NED.
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

__all__ = [
    "setpoint_message_args",
    "COPTER_MODE_OF",
    "DISARM_FORCE_MAGIC",
    "EARTH_RADIUS_M",
    "MODE_OF_COPTER",
    "MODE_OF_PX4",
    "PX4_CUSTOM_MODE_OF",
    "SUPPORTED_FRAMES",
    "SUPPORTED_TYPE_MASKS",
    "Autopilot",
    "CopterMode",
    "FlightMode",
    "Frame",
    "MAX_PLAUSIBLE_POSITION_M",
    "MAX_PLAUSIBLE_SPEED_M_S",
    "MAX_PLAUSIBLE_YAW_RAD",
    "MAX_PLAUSIBLE_YAW_RATE_RAD_S",
    "LandedState",
    "MavResult",
    "MavState",
    "ModeFlag",
    "Px4AutoSubMode",
    "PositionDemand",
    "Px4MainMode",
    "Rejection",
    "SetpointFields",
    "Severity",
    "TypeMask",
    "UnicycleDemand",
    "base_mode",
    "check_setpoint",
    "custom_mode_of",
    "decode_setpoint",
    "encode_position_setpoint",
    "encode_setpoint",
    "geodetic_from_ned",
    "mode_from_custom",
    "ned_from_geodetic",
    "px4_custom_mode",
    "px4_split_custom_mode",
    "wrap_pi",
]


class Autopilot(IntEnum):
    """MAV_AUTOPILOT values of the two profiles."""

    ARDUPILOTMEGA = 3
    PX4 = 12


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


class ModeFlag(IntEnum):
    """MAV_MODE_FLAG bits of HEARTBEAT.base_mode."""

    CUSTOM_MODE_ENABLED = 1
    TEST_ENABLED = 2
    AUTO_ENABLED = 4
    GUIDED_ENABLED = 8
    STABILIZE_ENABLED = 16
    HIL_ENABLED = 32
    MANUAL_INPUT_ENABLED = 64
    SAFETY_ARMED = 128


class MavResult(IntEnum):
    """MAV_RESULT of a COMMAND_ACK."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5


class MavState(IntEnum):
    """MAV_STATE of HEARTBEAT.system_status."""

    UNINIT = 0
    BOOT = 1
    CALIBRATING = 2
    STANDBY = 3
    ACTIVE = 4
    CRITICAL = 5
    EMERGENCY = 6


class Severity(IntEnum):
    """MAV_SEVERITY of a STATUSTEXT."""

    EMERGENCY = 0
    ALERT = 1
    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    NOTICE = 5
    INFO = 6
    DEBUG = 7


class LandedState(IntEnum):
    """MAV_LANDED_STATE of EXTENDED_SYS_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


DISARM_FORCE_MAGIC = 21196
"""COMMAND_LONG ARM_DISARM param2 that forces a disarm in flight (PX4 and ArduPilot)."""


class Px4MainMode(IntEnum):
    """PX4_CUSTOM_MAIN_MODE."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8


class Px4AutoSubMode(IntEnum):
    """PX4_CUSTOM_SUB_MODE_AUTO (meaningful when the main mode is AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    FOLLOW_TARGET = 8
    PRECLAND = 9


class CopterMode(IntEnum):
    """ArduCopter flight-mode numbers (HEARTBEAT.custom_mode, DO_SET_MODE param2)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    CIRCLE = 7
    LAND = 9
    POSHOLD = 16
    BRAKE = 17
    SMART_RTL = 21


class FlightMode(Enum):
    """The flight modes the simulated vehicle implements, independent of the profile.

    PX4 name first, ArduCopter equivalent in the docstring.
    """

    POSITION = "position"
    """PX4 POSCTL; ArduCopter POSHOLD. Without sticks: hold position."""
    HOLD = "hold"
    """PX4 AUTO.LOITER ("Hold"); ArduCopter LOITER. Zero velocity, altitude held."""
    OFFBOARD = "offboard"
    """PX4 OFFBOARD; ArduCopter GUIDED. Follow external setpoints."""
    TAKEOFF = "takeoff"
    """PX4 AUTO.TAKEOFF; ArduCopter has none (takeoff is a GUIDED command)."""
    LAND = "land"
    """PX4 AUTO.LAND; ArduCopter LAND."""
    STABILIZE = "stabilize"
    """ArduCopter STABILIZE (its boot mode); PX4 has no equivalent here."""


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 custom_mode: main mode in bits 16..23, sub mode in bits 24..31."""
    if not (0 <= main <= 255 and 0 <= sub <= 255):
        raise ValueError(f"PX4 main and sub modes are bytes, got {main}, {sub}")
    return (main << 16) | (sub << 24)


def px4_split_custom_mode(custom_mode: int) -> tuple[int, int]:
    """(main, sub) of a PX4 custom_mode."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


PX4_CUSTOM_MODE_OF: dict[FlightMode, int] = {
    FlightMode.POSITION: px4_custom_mode(Px4MainMode.POSCTL),
    FlightMode.HOLD: px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.LOITER),
    FlightMode.OFFBOARD: px4_custom_mode(Px4MainMode.OFFBOARD),
    FlightMode.TAKEOFF: px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.TAKEOFF),
    FlightMode.LAND: px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.LAND),
}
"""FlightMode -> PX4 custom_mode, for the modes the PX4 profile implements."""

MODE_OF_PX4: dict[int, FlightMode] = {v: k for k, v in PX4_CUSTOM_MODE_OF.items()}
"""PX4 custom_mode -> FlightMode."""

COPTER_MODE_OF: dict[FlightMode, int] = {
    FlightMode.STABILIZE: CopterMode.STABILIZE,
    FlightMode.POSITION: CopterMode.POSHOLD,
    FlightMode.HOLD: CopterMode.LOITER,
    FlightMode.OFFBOARD: CopterMode.GUIDED,
    FlightMode.LAND: CopterMode.LAND,
}
"""FlightMode -> ArduCopter mode number, for the modes the ArduPilot profile implements."""

MODE_OF_COPTER: dict[int, FlightMode] = {int(v): k for k, v in COPTER_MODE_OF.items()}
"""ArduCopter mode number -> FlightMode."""


def custom_mode_of(mode: FlightMode, autopilot: Autopilot) -> int:
    """HEARTBEAT.custom_mode of `mode` for `autopilot`; KeyError if that profile lacks the mode."""
    if autopilot == Autopilot.PX4:
        return PX4_CUSTOM_MODE_OF[mode]
    return int(COPTER_MODE_OF[mode])


def mode_from_custom(custom_mode: int, autopilot: Autopilot) -> FlightMode | None:
    """FlightMode of a custom_mode, or None if it is not one the profile implements.

    For PX4 a sub mode is only meaningful under AUTO: POSCTL with junk in bits 24..31 is POSCTL.
    """
    if autopilot == Autopilot.PX4:
        main, sub = px4_split_custom_mode(custom_mode)
        if main != Px4MainMode.AUTO:
            sub = 0
        return MODE_OF_PX4.get(px4_custom_mode(main, sub))
    return MODE_OF_COPTER.get(custom_mode)


def base_mode(*, armed: bool, mode: FlightMode) -> int:
    """HEARTBEAT.base_mode: custom mode enabled, armed flag, and the flags PX4/ArduPilot set."""
    flags = ModeFlag.CUSTOM_MODE_ENABLED | ModeFlag.STABILIZE_ENABLED
    if mode in (FlightMode.HOLD, FlightMode.OFFBOARD, FlightMode.TAKEOFF, FlightMode.LAND):
        flags |= ModeFlag.AUTO_ENABLED | ModeFlag.GUIDED_ENABLED
    elif mode == FlightMode.POSITION:
        flags |= ModeFlag.MANUAL_INPUT_ENABLED | ModeFlag.GUIDED_ENABLED
    else:
        flags |= ModeFlag.MANUAL_INPUT_ENABLED
    if armed:
        flags |= ModeFlag.SAFETY_ARMED
    return int(flags)


def wrap_pi(angle_rad: float) -> float:
    """Angle wrapped to (-pi, pi]."""
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))


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


EARTH_RADIUS_M = 6_371_000.0
"""Mean Earth radius used by PX4's map projection [m]."""


def geodetic_from_ned(
    north_m: float, east_m: float, *, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """(lat_deg, lon_deg) of a local NED point: azimuthal equidistant projection, as PX4 does."""
    x, y = north_m / EARTH_RADIUS_M, east_m / EARTH_RADIUS_M
    lat0, lon0 = math.radians(home_lat_deg), math.radians(home_lon_deg)
    c = math.hypot(x, y)
    if c == 0.0:
        return home_lat_deg, home_lon_deg
    sin_c, cos_c = math.sin(c), math.cos(c)
    lat = math.asin(cos_c * math.sin(lat0) + x * sin_c * math.cos(lat0) / c)
    lon = lon0 + math.atan2(y * sin_c, c * math.cos(lat0) * cos_c - x * math.sin(lat0) * sin_c)
    return math.degrees(lat), math.degrees(wrap_pi(lon))


def ned_from_geodetic(
    lat_deg: float, lon_deg: float, *, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """(north_m, east_m) of a geodetic point: inverse of `geodetic_from_ned`."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    lat0, lon0 = math.radians(home_lat_deg), math.radians(home_lon_deg)
    cos_dlon = math.cos(lon - lon0)
    arg = min(
        max(math.sin(lat0) * math.sin(lat) + math.cos(lat0) * math.cos(lat) * cos_dlon, -1), 1
    )
    c = math.acos(arg)
    k = 1.0 if abs(c) < 1e-12 else c / math.sin(c)
    north = k * (math.cos(lat0) * math.sin(lat) - math.sin(lat0) * math.cos(lat) * cos_dlon)
    east = k * math.cos(lat) * math.sin(lon - lon0)
    return north * EARTH_RADIUS_M, east * EARTH_RADIUS_M
