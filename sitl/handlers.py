"""What the simulated autopilot does with each message a client sends.

Every field acted on is validated first: random payloads often decode as valid messages. Every
COMMAND_LONG/COMMAND_INT addressed to this vehicle is answered with one COMMAND_ACK (unknown
commands: UNSUPPORTED); SET_MODE is answered with a COMMAND_ACK whose command is 11, as ArduPilot
does. Messages addressed to other systems, and this vehicle's own echoes, are ignored; a command
addressed to another system is ignored without an ACK and, in the PX4 profile, logged as PX4's
`MavlinkReceiver::handle_message_command_both` logs it ("Ignore command 511 from 255/190 to
1/1"), once for each sender and target (a ground station's one UDP port sends every vehicle's
requests to every vehicle it hears), the rest counted.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

from fleetmpc.protocol.mavlink_map import (
    DISARM_FORCE_MAGIC,
    Autopilot,
    FlightMode,
    MavResult,
    ModeFlag,
    mode_from_custom,
    px4_custom_mode,
)
from fleetmpc.protocol.mavlink_setpoint import SetpointFields
from fleetmpc.sitl.autopilot import Autopilot as AutopilotLogic
from fleetmpc.sitl.mavlink_io import Incoming, mavlink
from fleetmpc.sitl.telemetry import (
    ARDUPILOT_DATA_STREAMS,
    ON_REQUEST,
    PX4_ONLY,
    STREAMABLE,
    Identity,
    Snapshot,
    StreamSchedule,
    build,
)

__all__ = ["MessageHandler", "Reply", "setpoint_fields"]

M = mavlink
_MAX_STREAM_RATE_HZ = 50.0
_MIN_INTERVAL_NS = 1_000_000


@dataclass(frozen=True)
class Reply:
    """A message to send back on the link (and to the peer) a request came from."""

    message: mavlink.MAVLink_message
    to: Incoming


def _integer(value: float, lo: int, hi: int) -> int | None:
    """`value` as an int if it is a finite whole number in [lo, hi], else None."""
    if not isinstance(value, int | float) or not math.isfinite(value) or value != int(value):
        return None
    i = int(value)
    return i if lo <= i <= hi else None


def setpoint_fields(m: mavlink.MAVLink_set_position_target_local_ned_message) -> SetpointFields:
    """The fields of a SET_POSITION_TARGET_LOCAL_NED a setpoint uses (unvalidated)."""
    return SetpointFields(
        frame=m.coordinate_frame,
        type_mask=m.type_mask,
        x_m=m.x,
        y_m=m.y,
        z_m=m.z,
        vx_m_s=m.vx,
        vy_m_s=m.vy,
        vz_m_s=m.vz,
        yaw_rad=m.yaw,
        yaw_rate_rad_s=m.yaw_rate,
    )


@dataclass(frozen=True)
class _Command:
    command: int
    params: tuple[float, float, float, float, float, float, float]


class MessageHandler:
    """Dispatches decoded messages to the autopilot logic and the links' stream schedules."""

    def __init__(
        self,
        autopilot: AutopilotLogic,
        ident: Identity,
        mav: mavlink.MAVLink,
        *,
        schedule_of: Callable[[Incoming], StreamSchedule],
        snapshot: Callable[[], Snapshot],
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.autopilot = autopilot
        self.ident = ident
        self.mav = mav
        self._schedule_of = schedule_of
        self._snapshot = snapshot
        self._log = log or (lambda _text: None)
        self.ignored = 0
        self.commands = 0
        self.commands_to_others = 0
        """Commands addressed to another system, ignored."""
        self._others_logged: set[tuple[int, int, int, int]] = set()

    @property
    def _px4(self) -> bool:
        return self.ident.autopilot == Autopilot.PX4

    def _for_me(self, target_system: int, target_component: int | None = None) -> bool:
        sys_ok = target_system in (0, self.ident.system_id)
        return sys_ok and (target_component is None or target_component in (0, 1))

    def handle(self, inc: Incoming, now_ns: int) -> list[Reply]:
        m = inc.message
        header = m.get_header()
        if header.srcSystem == self.ident.system_id and header.srcComponent == 1:
            return []  # our own message echoed back by a router
        msg_id = m.get_msgId()
        if msg_id == M.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED:
            self._setpoint(m, now_ns)
            return []
        if msg_id == M.MAVLINK_MSG_ID_COMMAND_LONG:
            params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
            return self._command(inc, _Command(m.command, params), now_ns=now_ns)
        if msg_id == M.MAVLINK_MSG_ID_COMMAND_INT:
            params = (m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z)
            return self._command(inc, _Command(m.command, params), now_ns=now_ns)
        if msg_id == M.MAVLINK_MSG_ID_SET_MODE:
            return self._set_mode_message(inc, now_ns)
        if msg_id == M.MAVLINK_MSG_ID_REQUEST_DATA_STREAM:
            self._request_data_stream(inc, now_ns)
            return []
        if msg_id == M.MAVLINK_MSG_ID_PING:
            return self._ping(inc)
        if msg_id == M.MAVLINK_MSG_ID_TIMESYNC:
            if m.tc1 == 0:
                return [Reply(self.mav.timesync_encode(max(now_ns, 1), m.ts1), inc)]
            return []
        if msg_id in (M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, M.MAVLINK_MSG_ID_PARAM_REQUEST_READ):
            return self._params(inc)
        if msg_id == M.MAVLINK_MSG_ID_PARAM_SET:
            return self._params(inc)
        if msg_id != M.MAVLINK_MSG_ID_HEARTBEAT:
            self.ignored += 1
        return []

    # ----------------------------------------------------------------------------- setpoints
    def _setpoint(self, m, now_ns: int) -> None:
        if self._for_me(m.target_system, m.target_component):
            self.autopilot.receive_setpoint(setpoint_fields(m), now_ns)

    # ----------------------------------------------------------------------------- commands
    def _command(self, inc: Incoming, cmd: _Command, *, now_ns: int) -> list[Reply]:
        """Act on a COMMAND_LONG/COMMAND_INT for this vehicle; the ACK comes first."""
        m = inc.message
        if not self._for_me(m.target_system, m.target_component):
            self._ignore_command(m, cmd.command)
            return []
        self.commands += 1
        replies: list[Reply] = []
        result = self._dispatch(inc, cmd, now_ns=now_ns, replies=replies)
        header = m.get_header()
        ack = self.mav.command_ack_encode(
            cmd.command, int(result), 0, 0, header.srcSystem, header.srcComponent
        )
        return [Reply(ack, inc), *replies]

    def _ignore_command(self, m, command: int) -> None:
        self.commands_to_others += 1
        header = m.get_header()
        route = (header.srcSystem, header.srcComponent, m.target_system, m.target_component)
        if not self._px4 or route in self._others_logged:
            return
        self._others_logged.add(route)
        self._log(
            f"Ignore command {command} from {route[0]}/{route[1]} to {route[2]}/{route[3]}"
            " (the same route again: counted)"
        )

    def _dispatch(
        self, inc: Incoming, cmd: _Command, *, now_ns: int, replies: list[Reply]
    ) -> MavResult:
        p = cmd.params
        ap = self.autopilot
        if cmd.command == M.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return ap.arm(now_ns)
            if p[0] == 0.0:
                return ap.disarm(now_ns, force=p[1] == DISARM_FORCE_MAGIC)
            return MavResult.DENIED
        if cmd.command == M.MAV_CMD_DO_SET_MODE:
            return ap.set_mode(self._mode_of_command(p), now_ns)
        if cmd.command == M.MAV_CMD_NAV_TAKEOFF:
            # PX4 takes a finite latitude and longitude (params 5, 6) as the takeoff's position
            # (navigator_main.cpp); given 0, 0 it accepted, never climbed, and disarmed itself.
            # This plant's takeoff is vertical: a PX4 takeoff to a position stalls.
            elsewhere = self._px4 and math.isfinite(p[4]) and math.isfinite(p[5])
            altitude = self._takeoff_altitude(p[6])
            return ap.takeoff(now_ns, altitude_m=altitude, stalled=elsewhere)
        if cmd.command == M.MAV_CMD_NAV_LAND:
            return ap.land(now_ns)
        if cmd.command == M.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(inc, p, now_ns=now_ns)
        if cmd.command == M.MAV_CMD_REQUEST_MESSAGE:
            msg_id = _integer(p[0], 0, 0xFFFFFF)
            if msg_id is None or msg_id not in ON_REQUEST:
                return MavResult.DENIED
            message = build(self.mav, msg_id, self._snapshot(), ident=self.ident)
            replies.append(Reply(message, inc))
            return MavResult.ACCEPTED
        if cmd.command == M.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p[0] != 1.0:
                return MavResult.DENIED
            message = build(
                self.mav, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, self._snapshot(), ident=self.ident
            )
            replies.append(Reply(message, inc))
            return MavResult.ACCEPTED
        return MavResult.UNSUPPORTED

    def _mode_of_command(self, p) -> FlightMode | None:
        base = _integer(p[0], 0, 255)
        if base is None or not base & ModeFlag.CUSTOM_MODE_ENABLED:
            return None
        if self._px4:
            main = _integer(p[1], 0, 255)
            sub = 0 if math.isnan(p[2]) else _integer(p[2], 0, 255)
            if main is None or sub is None:
                return None
            return mode_from_custom(px4_custom_mode(main, sub), self.ident.autopilot)
        number = _integer(p[1], 0, 255)
        return None if number is None else mode_from_custom(number, self.ident.autopilot)

    def _takeoff_altitude(self, param7: float) -> float | None:
        """Takeoff altitude above home from param7 (PX4: AMSL, ArduPilot: above home).

        NaN (and 0 for ArduPilot) asks for the default (None); +-Inf is passed on to be refused.
        """
        if math.isnan(param7) or (not self._px4 and param7 == 0.0):
            return None
        return param7 - self.ident.site.home_alt_m if self._px4 else param7

    def _set_interval(self, inc: Incoming, p, *, now_ns: int) -> MavResult:
        msg_id = _integer(p[0], 0, 0xFFFFFF)
        interval_us = p[1]
        if msg_id is None or msg_id not in STREAMABLE or not math.isfinite(interval_us):
            return MavResult.DENIED
        if msg_id in PX4_ONLY and not self._px4:
            return MavResult.DENIED
        schedule = self._schedule_of(inc)
        if interval_us == -1.0:
            schedule.set_interval(msg_id, None, now_ns)
        elif interval_us == 0.0:
            schedule.set_default(msg_id, now_ns)
        elif interval_us > 0.0:
            schedule.set_interval(
                msg_id, max(round(interval_us * 1000.0), _MIN_INTERVAL_NS), now_ns
            )
        else:
            return MavResult.DENIED
        return MavResult.ACCEPTED

    # ----------------------------------------------------------------------------- other messages
    def _set_mode_message(self, inc: Incoming, now_ns: int) -> list[Reply]:
        m = inc.message
        if not self._for_me(m.target_system) or m.target_system == 0:
            return []
        if m.base_mode & ModeFlag.CUSTOM_MODE_ENABLED:
            mode = mode_from_custom(m.custom_mode, self.ident.autopilot)
        else:
            mode = None
        result = self.autopilot.set_mode(mode, now_ns)
        header = m.get_header()
        ack = self.mav.command_ack_encode(
            M.MAVLINK_MSG_ID_SET_MODE, int(result), 0, 0, header.srcSystem, header.srcComponent
        )
        return [Reply(ack, inc)]

    def _request_data_stream(self, inc: Incoming, now_ns: int) -> None:
        m = inc.message
        if self._px4 or not self._for_me(m.target_system, m.target_component):
            return
        if m.req_stream_id == M.MAV_DATA_STREAM_ALL:
            ids = tuple(i for group in ARDUPILOT_DATA_STREAMS.values() for i in group)
        else:
            ids = ARDUPILOT_DATA_STREAMS.get(m.req_stream_id, ())
        rate_hz = min(float(m.req_message_rate), _MAX_STREAM_RATE_HZ)
        schedule = self._schedule_of(inc)
        for msg_id in ids:
            if m.start_stop and rate_hz > 0:
                schedule.set_interval(msg_id, round(1e9 / rate_hz), now_ns)
            else:
                schedule.set_interval(msg_id, None, now_ns)

    def _ping(self, inc: Incoming) -> list[Reply]:
        m = inc.message
        if m.target_system != 0 or m.target_component != 0:
            return []  # a response to someone's ping, or addressed elsewhere
        header = m.get_header()
        reply = self.mav.ping_encode(m.time_usec, m.seq, header.srcSystem, header.srcComponent)
        return [Reply(reply, inc)]

    def _params(self, inc: Incoming) -> list[Reply]:
        """A small read-only parameter table, so parameter downloads complete."""
        m = inc.message
        if not self._for_me(m.target_system, m.target_component) or m.target_system == 0:
            return []
        table = self._param_table()
        names = list(table)
        if m.get_msgId() == M.MAVLINK_MSG_ID_PARAM_REQUEST_LIST:
            wanted = names
        else:
            name = m.param_id if isinstance(m.param_id, str) else ""
            index = getattr(m, "param_index", -1)
            if name in table:
                wanted = [name]
            elif m.get_msgId() == M.MAVLINK_MSG_ID_PARAM_REQUEST_READ and 0 <= index < len(names):
                wanted = [names[index]]
            else:
                return []
        return [
            Reply(
                self.mav.param_value_encode(
                    n.encode(), table[n], M.MAV_PARAM_TYPE_REAL32, len(names), names.index(n)
                ),
                inc,
            )
            for n in wanted
        ]

    def _param_table(self) -> dict[str, float]:
        c = self.autopilot.config
        if self._px4:
            return {
                "COM_OF_LOSS_T": c.offboard_loss_timeout_ns * 1e-9,
                "MAV_SYS_ID": float(self.ident.system_id),
                "MIS_TAKEOFF_ALT": c.takeoff_altitude_m,
                "MPC_XY_VEL_MAX": c.speed_limit_m_s,
            }
        return {
            "GUID_TIMEOUT": c.guided_timeout_ns * 1e-9,
            "PILOT_TKOFF_ALT": c.takeoff_altitude_m * 100.0,
            "SYSID_THISMAV": float(self.ident.system_id),
            "WPNAV_SPEED": c.speed_limit_m_s * 100.0,
        }
