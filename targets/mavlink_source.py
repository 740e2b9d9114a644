"""A target that is another MAVLink system: a second autopilot's GLOBAL_POSITION_INT, or a ground
station's follow-me stream (FOLLOW_TARGET), over any pymavlink connection string.

The connection is pymavlink's (`udpin:0.0.0.0:14560` to listen where the system sends,
`udpout:HOST:PORT` or `tcp:HOST:PORT` to reach it); this end asks every system it hears for
GLOBAL_POSITION_INT at `REQUEST_HZ` (a PX4 sends it on its ground-station link anyway, an
ArduPilot only when asked). Every fix heard is handed on, whoever sent it: the screen
(`fleetmpc.targets.screen`) rejects those of other systems, and says so.
"""

from fleetmpc.targets.fix import Fix

__all__ = ["MavlinkSource", "fix_of_message"]

REQUEST_HZ = 5.0
"""GLOBAL_POSITION_INT rate asked of the systems heard [Hz]."""

SOURCE_SYSTEM = 254
"""This end's own MAVLink system id (a ground station's range)."""


def fix_of_message(msg) -> Fix:
    """The fix a GLOBAL_POSITION_INT or FOLLOW_TARGET message carries."""
    if msg.get_type() == "FOLLOW_TARGET":
        vel = tuple(float(v) for v in msg.vel[:2])
        velocity = vel if any(v != 0.0 for v in vel) else None  # (unknown: zeros)
        return Fix(
            msg.get_srcSystem(), msg.timestamp * 1e-3, msg.lat * 1e-7, msg.lon * 1e-7,
            velocity, "FOLLOW_TARGET",
        )  # fmt: skip
    return Fix(
        msg.get_srcSystem(), msg.time_boot_ms * 1e-3, msg.lat * 1e-7, msg.lon * 1e-7,
        (msg.vx * 1e-2, msg.vy * 1e-2), "GLOBAL_POSITION_INT",
    )  # fmt: skip


class MavlinkSource:
    """Fixes from a MAVLink connection."""

    def __init__(self, connection: str) -> None:
        from pymavlink import mavutil

        self._mavutil = mavutil
        self._link = mavutil.mavlink_connection(connection, source_system=SOURCE_SYSTEM)
        self._asked: set[int] = set()

    def poll(self, timeout_s: float) -> list[Fix]:
        """The fixes that arrived, waiting up to `timeout_s` for the first."""
        out = []
        msg = self._link.recv_match(blocking=True, timeout=timeout_s)
        while msg is not None:
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                self._ask(msg.get_srcSystem(), msg.get_srcComponent())
            elif kind in ("GLOBAL_POSITION_INT", "FOLLOW_TARGET"):
                out.append(fix_of_message(msg))
            msg = self._link.recv_match(blocking=False)
        return out

    def _ask(self, system: int, component: int) -> None:
        """Ask a newly heard system for GLOBAL_POSITION_INT at REQUEST_HZ, once."""
        if system in self._asked or system == SOURCE_SYSTEM:
            return
        self._asked.add(system)
        mav = self._mavutil.mavlink
        self._link.mav.command_long_send(
            system, component, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 1e6 / REQUEST_HZ, 0, 0, 0, 0, 0,
        )  # fmt: skip

    def close(self) -> None:
        self._link.close()
