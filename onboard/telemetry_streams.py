"""What the agent asks its autopilot to stream, and the checked values of each telemetry
message it reads (the pose, heading, global fix and landed state; the link reads HEARTBEAT,
COMMAND_ACK and STATUSTEXT itself).

On connecting, the link sets the intervals of the messages it reads and stops the others it is
sent (`STREAM_INTERVALS_US`): every message costs the agent a wake-up of its reader and the
autopilot a send, four times as many per wall second at x4. The pose comes from ODOMETRY where
the autopilot streams it (PX4), else from LOCAL_POSITION_NED and ATTITUDE (docs/design.md,
"MAVLink").
"""

import math

from fleetmpc.protocol.local_frame import ned_from_geodetic, quaternion_yaw
from fleetmpc.protocol.mavlink_map import LandedState

__all__ = [
    "GLOBAL_FIX_INTERVAL_US",
    "MAX_BOOT_MS",
    "MAX_POSITION_M",
    "ODOMETRY_ID",
    "ODOMETRY_INTERVAL_US",
    "ODOMETRY_WAIT_S",
    "STREAM_INTERVALS_US",
    "attitude_yaw",
    "finite",
    "global_fix",
    "landed_state",
    "local_position",
    "odometry_pose",
]

STREAM_INTERVALS_US = {
    32: 33_333,  # LOCAL_POSITION_NED: the pose, at 30 Hz (PX4's onboard-link rate)
    30: 33_333,  # ATTITUDE: the yaw, with it
    33: -1,  # GLOBAL_POSITION_INT: 5 Hz (GLOBAL_FIX_INTERVAL_US) given a home, else not read
    74: -1,  # VFR_HUD: not read here
    245: 200_000,  # EXTENDED_SYS_STATE: the landed state (a takeoff's end), at 5 Hz
    1: -1,  # SYS_STATUS: not read here
}
"""SET_MESSAGE_INTERVAL requests [us] a link makes when it connects (-1: stop the stream). A
PX4 "onboard" link streams about 150 messages per second of autopilot time by default, half of
them ones the agent does not read; every one costs the agent a parse and the autopilot a send,
four times as many per wall second at x4."""

ODOMETRY_ID = 331
ODOMETRY_INTERVAL_US = 33_333.0
"""ODOMETRY's interval [us]: the pose and the heading in one message at 30 Hz (PX4 streams it at
that rate on an onboard link), half the messages of LOCAL_POSITION_NED and ATTITUDE, each of
which costs the agent a wake-up of its reader and the autopilot a send."""
ODOMETRY_WAIT_S = 1.0
"""Wall seconds to wait for the first ODOMETRY after the autopilot accepted its interval, before
keeping LOCAL_POSITION_NED and ATTITUDE."""
ODOMETRY_FRAMES = {1: False, 12: True}
"""ODOMETRY's velocity frames (child_frame_id) this link reads -> whether it is the body's:
MAV_FRAME_LOCAL_NED (PX4's EKF2 since v1.14) or MAV_FRAME_BODY_FRD (earlier PX4)."""


def odometry_pose(msg) -> tuple[int, float, float, float, float, float, float] | None:
    """(boot time [ns], x, y, z, v_north, v_east, yaw) of a valid ODOMETRY in the local NED
    frame, or None: another frame, a field out of bounds, a quaternion that is not a rotation."""
    body_velocity = ODOMETRY_FRAMES.get(msg.child_frame_id)
    w, qx, qy, qz = (float(q) for q in msg.q)
    if (
        msg.frame_id != 1
        or body_velocity is None
        or not finite(msg.x, msg.y, msg.z, msg.vx, msg.vy, bound=MAX_POSITION_M)
        or not finite(w, qx, qy, qz, bound=1.01)
        or abs(w * w + qx * qx + qy * qy + qz * qz - 1.0) > 0.01
        or not 0 <= msg.time_usec <= MAX_BOOT_MS * 1000
    ):
        return None
    yaw = quaternion_yaw(w, qx, qy, qz)
    vn, ve = float(msg.vx), float(msg.vy)
    if body_velocity:
        c, s = math.cos(yaw), math.sin(yaw)
        vn, ve = c * vn - s * ve, s * vn + c * ve
    return int(msg.time_usec) * 1000, float(msg.x), float(msg.y), float(msg.z), vn, ve, yaw


GLOBAL_FIX_INTERVAL_US = 200_000
"""GLOBAL_POSITION_INT's interval on a link given the scenario's home (5 Hz): it places the
autopilot's local origin."""

MAX_POSITION_M = 1e6
"""Largest local position or velocity component taken as valid [m, m/s]."""
MAX_BOOT_MS = 2**32 - 1
"""Largest boot time a uint32 of milliseconds holds."""


def finite(*values: float, bound: float) -> bool:
    """True if every value is a finite number within +-`bound`."""
    return all(isinstance(v, float | int) and math.isfinite(v) and abs(v) <= bound for v in values)


def local_position(msg) -> tuple[int, float, float, float, float, float] | None:
    """(boot time [ns], x, y, z, v_north, v_east) of a valid LOCAL_POSITION_NED, or None."""
    if not (
        finite(msg.x, msg.y, msg.z, msg.vx, msg.vy, bound=MAX_POSITION_M)
        and 0 <= msg.time_boot_ms <= MAX_BOOT_MS
    ):
        return None
    return int(msg.time_boot_ms) * 1_000_000, msg.x, msg.y, msg.z, msg.vx, msg.vy


def attitude_yaw(msg) -> tuple[int, float] | None:
    """(boot time [ns], yaw [rad]) of a valid ATTITUDE, or None."""
    if not (finite(msg.yaw, bound=2 * math.pi + 1e-3) and 0 <= msg.time_boot_ms <= MAX_BOOT_MS):
        return None
    return int(msg.time_boot_ms) * 1_000_000, float(msg.yaw)


def global_fix(msg, home_deg: tuple[float, float]) -> tuple[int, float, float] | None:
    """(boot time [ns], north, east [m from `home_deg`, (lat, lon)]) of a valid
    GLOBAL_POSITION_INT, or None (latitude 0 is a fix not yet made)."""
    lat, lon = msg.lat * 1e-7, msg.lon * 1e-7
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and msg.lat != 0):
        return None
    north, east = ned_from_geodetic(lat, lon, home_lat_deg=home_deg[0], home_lon_deg=home_deg[1])
    return int(msg.time_boot_ms) * 1_000_000, north, east


def landed_state(msg) -> LandedState | None:
    """The landed state of an EXTENDED_SYS_STATE, or None: a value MAVLink does not define."""
    try:
        return LandedState(msg.landed_state)
    except ValueError:
        return None
