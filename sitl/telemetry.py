"""What the simulated vehicle reports: message builders and per-link stream schedules.

Telemetry is sampled on plant ticks, so `time_boot_ms` is the simulated time of the state it
describes and no stream is faster than the plant rate. Rates follow PX4's defaults for its
"onboard" (offboard-API) and "normal" (ground-station) links; ArduPilot streams nothing but
HEARTBEAT until a client asks (SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM).
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from fleetmpc.protocol.local_frame import geodetic_from_ned, yaw_quaternion
from fleetmpc.protocol.mavlink_map import (
    Autopilot,
    FlightMode,
    LandedState,
    MavState,
    base_mode,
    custom_mode_of,
)
from fleetmpc.scenario import Site
from fleetmpc.sitl.mavlink_io import mavlink

__all__ = [
    "ARDUPILOT_DATA_STREAMS",
    "HEARTBEAT_ID",
    "ON_REQUEST",
    "PX4_ONLY",
    "PX4_GCS_RATES_HZ",
    "PX4_ONBOARD_RATES_HZ",
    "STREAMABLE",
    "Identity",
    "Snapshot",
    "StreamSchedule",
    "autopilot_version",
    "build",
    "heartbeat",
    "statustext",
]

M = mavlink
STREAMABLE = frozenset(
    {
        M.MAVLINK_MSG_ID_SYS_STATUS,
        M.MAVLINK_MSG_ID_ATTITUDE,
        M.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        M.MAVLINK_MSG_ID_VFR_HUD,
        M.MAVLINK_MSG_ID_HOME_POSITION,
        M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        M.MAVLINK_MSG_ID_ODOMETRY,
        M.MAVLINK_MSG_ID_HIL_STATE_QUATERNION,
        M.MAVLINK_MSG_ID_WIND_COV,
    }
)
"""Message ids a client may stream with SET_MESSAGE_INTERVAL (`PX4_ONLY`: on PX4 alone).
HIL_STATE_QUATERNION is the simulator's ground truth, as PX4's SITL streams it (its
GROUND_TRUTH stream, `src/modules/mavlink/streams/GROUND_TRUTH.hpp`), here with its time set
(`build`); both profiles send it, for a ground station to judge a flight by where the vehicles
were rather than by what their noisy estimates said (docs/design.md, "Ground truth"). WIND_COV,
which PX4 streams from its estimator's wind states, carries the simulator's true wind where the
vehicle is: the estimator here is perfect, and the ground station records it beside each
vehicle's learned drift."""

PX4_ONLY = frozenset({M.MAVLINK_MSG_ID_ODOMETRY})
"""Message ids only the PX4 profile sends (an ArduPilot SET_MESSAGE_INTERVAL for them is
denied): ODOMETRY, the pose and attitude in one message, which PX4 streams at 30 Hz on an
onboard link (`src/modules/mavlink/mavlink_main.cpp`, MAVLINK_MODE_ONBOARD)."""

ON_REQUEST = STREAMABLE | {M.MAVLINK_MSG_ID_HEARTBEAT, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION}
"""Message ids a client may ask for once with REQUEST_MESSAGE."""

PX4_ONBOARD_RATES_HZ: Mapping[int, float] = MappingProxyType(
    {
        M.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
        M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
        M.MAVLINK_MSG_ID_ATTITUDE: 50.0,
        M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
        M.MAVLINK_MSG_ID_ODOMETRY: 30.0,
        M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 50.0,
        M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
        M.MAVLINK_MSG_ID_VFR_HUD: 10.0,
    }
)
"""Default rates of the offboard-API link (PX4 "onboard" mode, capped at a 50 Hz plant)."""

PX4_GCS_RATES_HZ: Mapping[int, float] = MappingProxyType(
    {
        M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
        M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
        M.MAVLINK_MSG_ID_ATTITUDE: 15.0,
        M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 1.0,
        M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
        M.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
        M.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    }
)
"""Default rates of the ground-station link (PX4 "normal" mode)."""

ARDUPILOT_DATA_STREAMS: Mapping[int, tuple[int, ...]] = MappingProxyType(
    {
        M.MAV_DATA_STREAM_EXTENDED_STATUS: (
            M.MAVLINK_MSG_ID_SYS_STATUS,
            M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE,
        ),
        M.MAV_DATA_STREAM_POSITION: (
            M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
            M.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
        ),
        M.MAV_DATA_STREAM_EXTRA1: (M.MAVLINK_MSG_ID_ATTITUDE,),
        M.MAV_DATA_STREAM_EXTRA2: (M.MAVLINK_MSG_ID_VFR_HUD,),
    }
)
"""REQUEST_DATA_STREAM stream id -> the messages it carries (MAV_DATA_STREAM_ALL: all of them)."""

HEARTBEAT_ID = M.MAVLINK_MSG_ID_HEARTBEAT


@dataclass
class StreamSchedule:
    """Per-link message intervals, due times in simulated nanoseconds."""

    defaults_hz: Mapping[int, float] = field(default_factory=dict)
    interval_ns: dict[int, int] = field(default_factory=dict)
    next_due_ns: dict[int, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for msg_id in self.defaults_hz:
            self.set_default(msg_id, 0)

    def set_interval(self, msg_id: int, interval_ns: int | None, now_ns: int) -> None:
        """Stream `msg_id` every `interval_ns` (None stops it); the first one goes out next."""
        if interval_ns is None:
            self.interval_ns.pop(msg_id, None)
            self.next_due_ns.pop(msg_id, None)
            return
        self.interval_ns[msg_id] = max(int(interval_ns), 1)
        self.next_due_ns[msg_id] = -1  # due at once; the schedule is anchored at that send

    def set_default(self, msg_id: int, now_ns: int) -> None:
        """Back to the link's default rate for `msg_id` (which may be off)."""
        rate_hz = self.defaults_hz.get(msg_id, 0.0)
        self.set_interval(msg_id, round(1e9 / rate_hz) if rate_hz > 0 else None, now_ns)

    def due(self, now_ns: int) -> list[int]:
        """Message ids due at `now_ns`; each is rescheduled one interval later (no bursts)."""
        out = []
        for msg_id, due_ns in self.next_due_ns.items():
            if due_ns <= now_ns:
                out.append(msg_id)
                interval = self.interval_ns[msg_id]
                nxt = due_ns + interval
                self.next_due_ns[msg_id] = (
                    nxt if due_ns >= 0 and nxt > now_ns else now_ns + interval
                )
        return out


@dataclass(frozen=True)
class Identity:
    """Who the vehicle is on the wire."""

    system_id: int
    autopilot: Autopilot
    site: Site
    local_origin_m: tuple[float, float] = (0.0, 0.0)
    """Origin of LOCAL_POSITION_NED in the scenario's frame (where the vehicle booted) [m]."""


@dataclass(frozen=True)
class Snapshot:
    """The vehicle as its estimator reports it at one plant tick."""

    time_ns: int
    """Simulated time since boot [ns]."""
    north_m: float
    """Measured position North of home [m]."""
    east_m: float
    """Measured position East of home [m]."""
    yaw_rad: float
    """Measured heading [rad]."""
    vel_north_m_s: float
    """Measured ground velocity North [m/s]."""
    vel_east_m_s: float
    """Measured ground velocity East [m/s]."""
    yaw_rate_rad_s: float
    """Achieved yaw rate [rad/s]."""
    altitude_m: float
    """Altitude above home [m]."""
    climb_rate_m_s: float
    """Vertical speed, positive up [m/s]."""
    armed: bool
    mode: FlightMode
    landed_state: LandedState
    system_status: MavState
    position_ready: bool
    true_north_m: float = math.nan
    """True position North of home [m] (the simulator's ground truth)."""
    true_east_m: float = math.nan
    """True position East of home [m]."""
    true_yaw_rad: float = math.nan
    """True heading [rad]."""
    true_vel_north_m_s: float = math.nan
    """True ground velocity North [m/s]."""
    true_vel_east_m_s: float = math.nan
    """True ground velocity East [m/s]."""
    true_wind_north_m_s: float = math.nan
    """The wind where the vehicle is, North [m/s] (the simulator's truth)."""
    true_wind_east_m_s: float = math.nan
    """The wind where the vehicle is, East [m/s]."""


_SENSORS = (
    M.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | M.MAV_SYS_STATUS_SENSOR_3D_MAG
    | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | M.MAV_SYS_STATUS_SENSOR_GPS
    | M.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | M.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | M.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | M.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | M.MAV_SYS_STATUS_AHRS
    | M.MAV_SYS_STATUS_PREARM_CHECK
)
_NEED_POSITION = M.MAV_SYS_STATUS_SENSOR_GPS | M.MAV_SYS_STATUS_PREARM_CHECK


def _ms(time_ns: int) -> int:
    return (time_ns // 1_000_000) & 0xFFFFFFFF


def _int16(x: float) -> int:
    return max(-32768, min(32767, round(x)))


def _heading_cdeg(yaw_rad: float) -> int:
    return round(math.degrees(yaw_rad) * 100.0) % 36000


def _latlon_e7(ident: Identity, north_m: float, east_m: float) -> tuple[int, int]:
    lat, lon = geodetic_from_ned(
        north_m, east_m, home_lat_deg=ident.site.home_lat_deg, home_lon_deg=ident.site.home_lon_deg
    )
    return round(lat * 1e7), round(lon * 1e7)


def heartbeat(
    mav: mavlink.MAVLink, ident: Identity, *, armed: bool, mode: FlightMode, status: MavState
):
    return mav.heartbeat_encode(
        M.MAV_TYPE_QUADROTOR,
        int(ident.autopilot),
        base_mode(armed=armed, mode=mode),
        custom_mode_of(mode, ident.autopilot),
        int(status),
    )


def statustext(mav: mavlink.MAVLink, severity: int, text: str):
    return mav.statustext_encode(int(severity), text.encode("ascii", "replace")[:50])


def autopilot_version(mav: mavlink.MAVLink, ident: Identity):
    if ident.autopilot == Autopilot.PX4:
        version = (1 << 24) | (15 << 16) | (0 << 8) | M.FIRMWARE_VERSION_TYPE_OFFICIAL
    else:
        version = (4 << 24) | (5 << 16) | (7 << 8) | M.FIRMWARE_VERSION_TYPE_OFFICIAL
    capabilities = (
        M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    )
    custom = [0] * 8
    return mav.autopilot_version_encode(
        capabilities, version, 0, 0, 0, custom, custom, custom, 0, 0, ident.system_id
    )


def build(mav: mavlink.MAVLink, msg_id: int, snap: Snapshot, *, ident: Identity):
    """The message `msg_id` describing `snap`, or None if it is not one this vehicle sends."""
    builder = _BUILDERS.get(msg_id)
    return None if builder is None else builder(mav, snap, ident)


def _heartbeat(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    return heartbeat(mav, ident, armed=snap.armed, mode=snap.mode, status=snap.system_status)


def _attitude(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    t_ms = _ms(snap.time_ns)
    return mav.attitude_encode(t_ms, 0.0, 0.0, snap.yaw_rad, 0.0, 0.0, snap.yaw_rate_rad_s)


def _local_position_ned(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    return mav.local_position_ned_encode(
        _ms(snap.time_ns),
        snap.north_m - ident.local_origin_m[0],
        snap.east_m - ident.local_origin_m[1],
        -snap.altitude_m,
        snap.vel_north_m_s,
        snap.vel_east_m_s,
        -snap.climb_rate_m_s,
    )


def _odometry(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    """As PX4's EKF2 publishes it: position and velocity in the local NED frame, the attitude
    as a quaternion (w, x, y, z), time in microseconds since boot. ArduPilot sends none."""
    if ident.autopilot != Autopilot.PX4:
        return None
    return mav.odometry_encode(
        snap.time_ns // 1000,
        M.MAV_FRAME_LOCAL_NED,
        M.MAV_FRAME_LOCAL_NED,
        snap.north_m - ident.local_origin_m[0],
        snap.east_m - ident.local_origin_m[1],
        -snap.altitude_m,
        yaw_quaternion(snap.yaw_rad),
        snap.vel_north_m_s,
        snap.vel_east_m_s,
        -snap.climb_rate_m_s,
        0.0,
        0.0,
        snap.yaw_rate_rad_s,
        [math.nan] * 21,
        [math.nan] * 21,
        0,
        M.MAV_ESTIMATOR_TYPE_AUTOPILOT,
    )


def _global_position_int(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    lat, lon = _latlon_e7(ident, snap.north_m, snap.east_m)
    return mav.global_position_int_encode(
        _ms(snap.time_ns),
        lat,
        lon,
        round((ident.site.home_alt_m + snap.altitude_m) * 1000.0),
        round(snap.altitude_m * 1000.0),
        _int16(snap.vel_north_m_s * 100.0),
        _int16(snap.vel_east_m_s * 100.0),
        _int16(-snap.climb_rate_m_s * 100.0),
        _heading_cdeg(snap.yaw_rad),
    )


def _hil_state_quaternion(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    """Ground truth, as PX4's SITL sends it, but with time_usec (since boot) set: PX4 leaves it
    0, and a sample without a time cannot be placed on the fleet's clock."""
    lat, lon = _latlon_e7(ident, snap.true_north_m, snap.true_east_m)
    return mav.hil_state_quaternion_encode(
        snap.time_ns // 1000,
        yaw_quaternion(snap.true_yaw_rad),
        0.0,
        0.0,
        snap.yaw_rate_rad_s,
        lat,
        lon,
        round((ident.site.home_alt_m + snap.altitude_m) * 1000.0),
        _int16(snap.true_vel_north_m_s * 100.0),
        _int16(snap.true_vel_east_m_s * 100.0),
        _int16(-snap.climb_rate_m_s * 100.0),
        0,
        0,
        0,
        0,
        0,
    )


def _wind_cov(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    """The true wind (NED, m/s) with its time since boot; no variance: it is the truth."""
    return mav.wind_cov_encode(
        snap.time_ns // 1000,
        snap.true_wind_north_m_s,
        snap.true_wind_east_m_s,
        0.0,
        0.0,
        0.0,
        ident.site.home_alt_m + snap.altitude_m,
        0.0,
        0.0,
    )


def _vfr_hud(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    ground_speed = math.hypot(snap.vel_north_m_s, snap.vel_east_m_s)
    flying = snap.armed and snap.landed_state != LandedState.ON_GROUND
    return mav.vfr_hud_encode(
        ground_speed,
        ground_speed,
        _heading_cdeg(snap.yaw_rad) // 100,
        50 if flying else 0,
        ident.site.home_alt_m + snap.altitude_m,
        snap.climb_rate_m_s,
    )


def _sys_status(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    health = _SENSORS if snap.position_ready else _SENSORS & ~_NEED_POSITION
    return mav.sys_status_encode(_SENSORS, _SENSORS, health, 200, 16200, -1, 100, 0, 0, 0, 0, 0, 0)


def _extended_sys_state(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    return mav.extended_sys_state_encode(M.MAV_VTOL_STATE_UNDEFINED, int(snap.landed_state))


def _home_position(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    lat, lon = _latlon_e7(ident, 0.0, 0.0)
    return mav.home_position_encode(
        lat,
        lon,
        round(ident.site.home_alt_m * 1000.0),
        0.0,
        0.0,
        0.0,
        [1.0, 0.0, 0.0, 0.0],
        0.0,
        0.0,
        0.0,
        snap.time_ns // 1000,
    )


def _autopilot_version(mav: mavlink.MAVLink, snap: Snapshot, ident: Identity):
    return autopilot_version(mav, ident)


_BUILDERS = MappingProxyType(
    {
        M.MAVLINK_MSG_ID_HEARTBEAT: _heartbeat,
        M.MAVLINK_MSG_ID_ATTITUDE: _attitude,
        M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _local_position_ned,
        M.MAVLINK_MSG_ID_ODOMETRY: _odometry,
        M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position_int,
        M.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: _hil_state_quaternion,
        M.MAVLINK_MSG_ID_WIND_COV: _wind_cov,
        M.MAVLINK_MSG_ID_VFR_HUD: _vfr_hud,
        M.MAVLINK_MSG_ID_SYS_STATUS: _sys_status,
        M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _extended_sys_state,
        M.MAVLINK_MSG_ID_HOME_POSITION: _home_position,
        M.MAVLINK_MSG_ID_AUTOPILOT_VERSION: _autopilot_version,
    }
)
"""How each message this vehicle sends is built from a snapshot (`build`)."""
