"""MAVLink identities and flight modes shared by the SITL autopilot and the onboard agent.

Everything here is plain integers and pure functions (no pymavlink): the numbers PX4 and ArduPilot
put on the wire for the autopilot type, the HEARTBEAT flags and states, command results and
landed states, and the flight-mode encodings of both profiles (HEARTBEAT.custom_mode,
DO_SET_MODE). Setpoints are `fleetmpc.protocol.mavlink_setpoint`'s; positions and headings of the
local frame are `fleetmpc.protocol.local_frame`'s.
"""

from enum import Enum, IntEnum

__all__ = [
    "COPTER_MODE_OF",
    "DISARM_FORCE_MAGIC",
    "MODE_OF_COPTER",
    "MODE_OF_PX4",
    "PX4_CUSTOM_MODE_OF",
    "Autopilot",
    "CopterMode",
    "FlightMode",
    "LandedState",
    "MavResult",
    "MavState",
    "ModeFlag",
    "Px4AutoSubMode",
    "Px4MainMode",
    "Severity",
    "base_mode",
    "custom_mode_name",
    "custom_mode_of",
    "flight_mode_name",
    "mode_from_custom",
    "px4_custom_mode",
    "px4_split_custom_mode",
]


class Autopilot(IntEnum):
    """MAV_AUTOPILOT values of the two profiles."""

    ARDUPILOTMEGA = 3
    PX4 = 12


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


def custom_mode_name(custom_mode: int, autopilot: Autopilot) -> str:
    """The name `autopilot` gives the mode of a HEARTBEAT's custom_mode: ArduCopter's own mode
    names (GUIDED, LOITER, RTL, ...); PX4's as `FlightMode` names them (OFFBOARD, HOLD for
    AUTO.LOITER, POSITION, TAKEOFF, LAND), else its main and AUTO sub mode (AUTO.RTL, ALTCTL)."""
    if autopilot == Autopilot.ARDUPILOTMEGA:
        try:
            return CopterMode(custom_mode).name
        except ValueError:
            return f"mode {custom_mode}"
    mode = mode_from_custom(custom_mode, autopilot)
    if mode is not None:
        return mode.name
    main, sub = px4_split_custom_mode(custom_mode)
    try:
        main_name = Px4MainMode(main).name
    except ValueError:
        return f"mode {main}.{sub}"
    if main != Px4MainMode.AUTO:
        return main_name
    try:
        return f"AUTO.{Px4AutoSubMode(sub).name}"
    except ValueError:
        return f"AUTO.{sub}"


def flight_mode_name(mode: FlightMode, autopilot: Autopilot | None) -> str:
    """The name `autopilot` gives `mode` (ArduCopter: GUIDED for OFFBOARD, LOITER for HOLD,
    POSHOLD for POSITION; PX4 and an unknown autopilot: the `FlightMode` name)."""
    if autopilot == Autopilot.ARDUPILOTMEGA and mode in COPTER_MODE_OF:
        return CopterMode(COPTER_MODE_OF[mode]).name
    return mode.name


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
