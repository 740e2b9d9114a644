"""MavlinkAutopilotLink: the AutopilotLink over pymavlink, for PX4 and ArduPilot.

The link detects the autopilot from its HEARTBEAT and uses its semantics (`engage`):
PX4 — setpoints must already stream (PX4's code needs a recent one, its documentation asks for
> 2 Hz for 1 s: the runner's streamer gives it 1.5 s), then arm (and, on the ground, take off)
and DO_SET_MODE OFFBOARD (COMMAND_LONG 176, param1 CUSTOM_MODE_ENABLED, param2 6); ArduPilot —
GUIDED, arm, takeoff. A refused step is asked again, and a sequence that comes to nothing (a
takeoff that ends on the ground) starts again from where the vehicle is, until the engage
timeout; the autopilot's reason (COMMAND_ACK result, STATUSTEXT) is logged. On connecting,
SET_MESSAGE_INTERVAL for the streams it reads. Everything sent is addressed to the system id of
the autopilot's HEARTBEAT (component 1), never to an assumed one.
Setpoints are SET_POSITION_TARGET_LOCAL_NED with type_mask 1479 (velocity + yaw rate),
frame BODY_NED (8) for PX4 and BODY_OFFSET_NED (9) for ArduPilot, vx = forward speed; a hold is
type_mask 3576 (position only) in LOCAL_NED, which both autopilots fly with their own position
controller (`send_position_setpoint`).

A reader thread decodes everything that arrives; every field acted on is validated (random
payloads often decode as valid messages).
"""

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable

from fleetmpc.bus.faults import LinkFaults
from fleetmpc.onboard.autopilot_link import AutopilotLink, AutopilotLinkError, LinkState
from fleetmpc.onboard.local_origin import OriginShift
from fleetmpc.onboard.telemetry_streams import (
    GLOBAL_FIX_INTERVAL_US,
    MAX_BOOT_MS,
    MAX_POSITION_M,
    ODOMETRY_ID,
    ODOMETRY_INTERVAL_US,
    ODOMETRY_WAIT_S,
    STREAM_INTERVALS_US,
    attitude_yaw,
    finite,
    global_fix,
    landed_state,
    local_position,
    odometry_pose,
)
from fleetmpc.protocol.mavlink_map import (
    Autopilot,
    FlightMode,
    LandedState,
    MavResult,
    ModeFlag,
    Px4MainMode,
    custom_mode_of,
    mode_from_custom,
)
from fleetmpc.protocol.mavlink_setpoint import (
    Frame,
    SetpointFields,
    encode_position_setpoint,
    encode_setpoint,
    setpoint_message_args,
)
from fleetmpc.security.mavlink_signing import SigningGuard, sign_outgoing

__all__ = ["MavlinkAutopilotLink"]

_READ_TIMEOUT_S = 0.5
"""How long the reader waits for a message before it looks at its stop flag [s]. pymavlink
sleeps in select for half of it between messages: a short one wakes the reader many times a
second for nothing (0.05 s: 40 times), which costs an agent as much as its telemetry does."""

AGENT_LINK_ID = 1
"""The agent's signing link id: with its system and component ids it names the agent's stream on
the vehicle, apart from a ground station's (often 255/190 on link 0 as well)."""


class MavlinkAutopilotLink(AutopilotLink):
    """An AutopilotLink over pymavlink (any `mavutil.mavlink_connection` URL)."""

    def __init__(
        self,
        url: str,
        *,
        system_id: int | None = None,
        source_system: int = 255,
        source_component: int = 190,
        log: Callable[[str], None] | None = None,
        now_ns: Callable[[], int] = time.time_ns,
        home_deg: tuple[float, float] | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        super().__init__()
        self._now_ns = now_ns
        self._home_deg = home_deg
        self.faults: LinkFaults | None = None
        """Injected autopilot-link faults (None: none)."""
        self._origin = OriginShift() if home_deg is not None else None
        """Where the autopilot's local origin lies in the scenario's frame (None: taken to be
        the scenario's origin, when no home is given)."""
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self._mavutil = mavutil
        self.url = url
        self._want_system = system_id
        """The autopilot's system id to insist on; None: the first autopilot heard."""
        self._setpoints_paused = False
        """True while an ArduPilot takeoff is under way: setpoints would cancel it."""
        self._heard_systems: set[int] = set()
        """System ids of every autopilot heartbeat heard on the link."""
        self._log = log or (lambda _text: None)
        try:
            self._conn = mavutil.mavlink_connection(
                url,
                source_system=source_system,
                source_component=source_component,
                autoreconnect=True,
            )
        except Exception as e:
            raise AutopilotLinkError(f"cannot open MAVLink connection {url!r}: {e}") from None
        self.signing: SigningGuard | None = None
        """With a key: signs what is sent, and only frames signed with the key are heard."""
        if signing_key is not None:
            self.signing = SigningGuard(signing_key, report=lambda _r, text: self._log(text))
            sign_outgoing(self._conn.mav, signing_key, link_id=AGENT_LINK_ID)
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._acks: dict[int, int] = {}
        self._texts: list[str] = []
        """The autopilot's STATUSTEXTs, the newest last (the last `_KEPT_TEXTS`)."""
        self._texts_seen = 0
        """STATUSTEXTs received so far."""
        self._reason: str | None = None
        """Why the last engage step failed (the autopilot's answer), None: none failed."""
        self._odometry_seen = threading.Event()
        """Set by the first valid ODOMETRY: the autopilot streams the pose in one message."""
        self._reader = threading.Thread(target=self._read_loop, name="mavlink-reader", daemon=True)
        self._reader.start()

    # -- receive --------------------------------------------------------------------------------
    def _read_loop(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._conn.recv_match(blocking=True, timeout=_READ_TIMEOUT_S)
            except Exception:  # a closed socket or a decoder error: keep reading until stopped
                if self._stop.wait(0.01):
                    return
                continue
            if msg is not None:
                try:
                    self._handle(msg)
                except Exception:
                    self._update(rejected=self.state().rejected + 1)

    def _handle(self, msg) -> None:
        if self.faults is not None and self.faults.cut():
            return  # (an injected link fault: the message never came)
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return  # (a frame pymavlink could not decode: nothing to act on)
        if self.signing is not None and not self.signing.admit(msg):
            self._update(rejected=self.state().rejected + 1)
        elif kind == "HEARTBEAT":
            self._on_heartbeat(msg, msg.get_srcSystem())
        elif self._from_autopilot(msg):
            st = self.state()
            if not self._read(kind, msg, st):
                self._update(rejected=st.rejected + 1)

    def _from_autopilot(self, msg) -> bool:
        """Whether `msg` comes from the autopilot the link took from its HEARTBEAT (its system,
        component 1)."""
        system = self.state().system_id
        return system != 0 and msg.get_srcSystem() == system and msg.get_srcComponent() == 1

    def _read(self, kind: str, msg, st: LinkState) -> bool:
        """Take one message of the autopilot's own (`st`: the state before it); False: an
        invalid one (its values are checked by `fleetmpc.onboard.telemetry_streams`' readers;
        a message not read here, or a COMMAND_ACK of a result MAVLink does not define, is
        ignored, not counted)."""
        if kind in ("ODOMETRY", "LOCAL_POSITION_NED"):
            pose = odometry_pose(msg) if kind == "ODOMETRY" else local_position(msg)
            if pose is None:
                return False
            if kind == "ODOMETRY":
                self._odometry_seen.set()
            self._pose(st, *pose)
        elif kind == "ATTITUDE":
            if (yaw := attitude_yaw(msg)) is None:
                return False
            t_ns, yaw_rad = yaw
            boot_ns = max(t_ns, st.time_boot_ns)
            self._update(yaw_rad=yaw_rad, time_boot_ns=boot_ns, received_ns=self._now_ns())
        elif kind == "GLOBAL_POSITION_INT" and self._home_deg is not None:
            if (fix := global_fix(msg, self._home_deg)) is None:
                return False
            self._origin.global_fix(*fix)
        elif kind == "EXTENDED_SYS_STATE":
            if (landed := landed_state(msg)) is None:
                return False
            self._update(landed_state=landed)
        elif kind == "COMMAND_ACK" and msg.result in {int(r) for r in MavResult}:
            with self._cond:
                self._acks[int(msg.command)] = int(msg.result)
                self._cond.notify_all()
        elif kind == "STATUSTEXT":
            self._on_text(str(getattr(msg, "text", ""))[:50])
        return True

    def _on_text(self, text: str) -> None:
        with self._cond:
            self._texts = [*self._texts[-(_KEPT_TEXTS - 1) :], text]
            self._texts_seen += 1
        self._update(last_text=text)
        self._log(f"autopilot: {text}")

    def _pose(
        self,
        st: LinkState,
        t_ns: int,
        x: float,
        y: float,
        z: float,
        vx: float,
        vy: float,
        yaw: float | None = None,
    ) -> None:
        """Take a validated local position (and heading) at boot time `t_ns`."""
        shift = (0.0, 0.0)
        if self._origin is not None:
            self._origin.local(t_ns, x, y, vx, vy)
            shift = self._origin.value
            if shift is None:
                return  # (no pose until the origin is known)
        heading = {} if yaw is None else {"yaw_rad": float(yaw)}
        self._update(
            north_m=float(x) + shift[0],
            east_m=float(y) + shift[1],
            down_m=float(z),
            vel_north_m_s=float(vx),
            vel_east_m_s=float(vy),
            position_boot_ns=t_ns,
            time_boot_ns=max(t_ns, st.time_boot_ns),
            received_ns=self._now_ns(),
            **heading,
        )

    def _on_heartbeat(self, msg, src: int) -> None:
        st = self.state()
        if msg.get_srcComponent() != 1 or msg.type in (6, 18):  # GCS (6), onboard computer (18)
            return
        self._heard_systems.add(src)
        if self._want_system is not None and src != self._want_system:
            return
        if st.system_id not in (0, src):
            return
        try:
            autopilot = Autopilot(msg.autopilot)
        except ValueError:
            self._update(rejected=st.rejected + 1)
            return
        custom = bool(msg.base_mode & ModeFlag.CUSTOM_MODE_ENABLED)
        mode = mode_from_custom(int(msg.custom_mode), autopilot) if custom else None
        armed = bool(msg.base_mode & ModeFlag.SAFETY_ARMED)
        was_lost = st.mode_lost
        self._update(
            autopilot=autopilot,
            system_id=src,
            armed=armed,
            mode=mode,
            custom_mode=int(msg.custom_mode) if custom else None,
            heartbeats=st.heartbeats + 1,
        )
        now = self.state()
        if now.engaged and st.armed and not armed:
            # (the mode may stay GUIDED: ArduCopter's auto-disarm on the ground, a crash)
            self._update(mode_lost=True)
            self._log("mode lost: the autopilot disarmed")
        elif now.mode_lost and not was_lost:
            self._log(f"mode lost: the autopilot switched to {now.mode_name or 'an unknown mode'}")

    # -- send -----------------------------------------------------------------------------------
    def _target(self) -> int | None:
        """The system id of the autopilot flown (its HEARTBEAT's), None before one is heard."""
        return self.state().system_id or None

    def _send(self, fn: Callable[..., None], *args: object) -> bool:
        if self.faults is not None and self.faults.cut():
            return False  # (an injected link fault: the message is lost on the way)
        with self._send_lock:
            if self.signing is not None:
                self.signing.refresh(self._conn.mav)
            try:
                fn(*args)
            except Exception:
                return False
        return True

    def send_setpoint(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        if not (math.isfinite(speed_m_s) and math.isfinite(yaw_rate_rad_s)):
            speed_m_s, yaw_rate_rad_s = 0.0, 0.0
        px4 = self.state().autopilot != Autopilot.ARDUPILOTMEGA
        self._send_fields(
            encode_setpoint(
                speed_m_s, yaw_rate_rad_s, frame=Frame.BODY_NED if px4 else Frame.BODY_OFFSET_NED
            )
        )

    def send_position_setpoint(self, *, north_m: float, east_m: float, down_m: float) -> None:
        if not finite(north_m, east_m, down_m, bound=MAX_POSITION_M):
            self.send_setpoint(speed_m_s=0.0, yaw_rate_rad_s=0.0)
            return
        shift = (0.0, 0.0) if self._origin is None else self._origin.value or (0.0, 0.0)
        self._send_fields(encode_position_setpoint(north_m - shift[0], east_m - shift[1], down_m))

    def _send_fields(self, sp: SetpointFields) -> None:
        target = self._target()
        if self._setpoints_paused or target is None:
            return  # (an ArduPilot takeoff is under way, or no autopilot heard yet)
        boot_ms = max(self.state().time_boot_ns, 0) // 1_000_000 & MAX_BOOT_MS
        mav = self._conn.mav
        sent = self._send(
            lambda: mav.set_position_target_local_ned_send(
                *setpoint_message_args(sp, time_boot_ms=boot_ms, target_system=target)
            )
        )
        if sent:
            self.setpoints_sent += 1

    def _command(self, command: int, params: tuple[float, ...], *, timeout_s: float) -> int | None:
        """COMMAND_LONG to the autopilot's system and wait for its ACK: the MAV_RESULT, or None
        on timeout (or before any autopilot is heard)."""
        p = (*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)[:7]
        with self._cond:
            self._acks.pop(command, None)
        target = self._target()
        if target is None:
            return None
        mav = self._conn.mav
        self._send(lambda: mav.command_long_send(target, 1, command, 0, *p))
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while command not in self._acks:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._acks.pop(command)

    def _retry(self, command: int, params: tuple[float, ...], *, deadline: float) -> bool:
        """Send a command until the autopilot accepts it or the deadline (time.monotonic)
        passes; each refusal's reason (`_refused`) is kept and logged when it changes."""
        while not self._stop.is_set():
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            texts_before = self._texts_seen
            result = self._command(command, params, timeout_s=min(1.0, left))
            if result == MavResult.ACCEPTED:
                return True
            self._stop.wait(_RETRY_PAUSE_S)  # (and the STATUSTEXT saying why may come)
            self._refused(command, result, texts_before=texts_before)
        return False

    def _refused(self, command: int, result: int | None, *, texts_before: int) -> None:
        """Keep (and log, if new) the reason the autopilot gave for refusing `command`: the
        COMMAND_ACK's result and its newest STATUSTEXT since the command was sent."""
        what = _COMMAND_NAMES.get(command, f"command {command}")
        answer = "not acknowledged" if result is None else MavResult(result).name
        self._fail(f"{what}: {answer}", texts_before=texts_before)

    def _fail(self, reason: str, *, texts_before: int) -> None:
        """Keep `reason` (with the autopilot's newest STATUSTEXT since `texts_before` texts had
        come) as the last reason an engage step failed; log it when it changes."""
        with self._cond:
            new = self._texts_seen - texts_before
            text = self._texts[-1] if new > 0 and self._texts else None
        if text is not None:
            reason = f"{reason} ({text})"
        if reason != self._reason:
            self._log(f"engage: {reason}; trying again")
        self._reason = reason

    def _set_mode(self, mode: FlightMode, *, deadline: float) -> bool:
        autopilot = self.state().autopilot or Autopilot.PX4
        if autopilot == Autopilot.PX4:
            params = (float(ModeFlag.CUSTOM_MODE_ENABLED), float(_px4_main(mode)))
            custom = custom_mode_of(mode, autopilot)
            sub = (custom >> 24) & 0xFF
            params = (*params, float(sub))
        else:
            params = (float(ModeFlag.CUSTOM_MODE_ENABLED), float(custom_mode_of(mode, autopilot)))
        return self._retry(176, params, deadline=deadline)

    def connect(self, *, timeout_s: float) -> LinkState:
        deadline = time.monotonic() + timeout_s
        asked_streams = False
        while time.monotonic() < deadline:
            st = self.state()
            if st.autopilot is not None and not asked_streams:
                self._request_streams(st.autopilot)
                asked_streams = True
            if st.autopilot is not None and st.has_pose:
                return st
            # Some links (udpout, tcp) stay silent until the client speaks.
            self._send(self._conn.mav.heartbeat_send, 6, 8, 0, 0, 4)
            self.wait_state(newer_than_ns=st.time_boot_ns, timeout_s=0.25)
        st = self.state()
        if self._want_system is not None and self._heard_systems - {self._want_system}:
            heard = ", ".join(str(i) for i in sorted(self._heard_systems))
            raise AutopilotLinkError(
                f"no HEARTBEAT from system {self._want_system} on {self.url} in {timeout_s} s;"
                f" autopilots heard there: system {heard} (leave out --target-system to fly"
                " the first one heard)"
            )
        what = "pose" if st.autopilot is not None else "HEARTBEAT and pose"
        raise AutopilotLinkError(f"no {what} from {self.url} in {timeout_s} s")

    def _request_streams(self, autopilot: Autopilot) -> None:
        """Ask the autopilot for the streams this link reads (`STREAM_INTERVALS_US`):
        ArduPilot streams nothing until asked, PX4 streams more than the agent reads. The pose
        comes from ODOMETRY where the autopilot streams it (PX4), one message where
        LOCAL_POSITION_NED and ATTITUDE are two: once a valid one has come, those two stop."""
        odometry = self._command(
            511, (float(ODOMETRY_ID), ODOMETRY_INTERVAL_US), timeout_s=1.0
        ) == MavResult.ACCEPTED and self._odometry_seen.wait(ODOMETRY_WAIT_S)
        for msg_id, interval_us in STREAM_INTERVALS_US.items():
            if msg_id == 33 and self._home_deg is not None:
                interval_us = GLOBAL_FIX_INTERVAL_US
            if odometry and msg_id in (32, 30):
                interval_us = -1  # (ODOMETRY carries both)
            if interval_us < 0 and autopilot == Autopilot.ARDUPILOTMEGA:
                continue  # (nothing to stop: it streams only what it is asked for)
            self._command(511, (float(msg_id), float(interval_us)), timeout_s=1.0)

    def engage(self, *, timeout_s: float) -> bool:
        """Put the vehicle under the agent's control within `timeout_s` of wall time. Each step
        is asked again while the autopilot refuses it (an arming refused while its estimator
        settles), and the whole sequence starts again from where the vehicle is when one comes
        to nothing (a takeoff that ends on the ground, disarmed); only when the time is up does
        it give up, logging the last reason."""
        deadline = time.monotonic() + timeout_s
        self._reason = None
        while not self._stop.is_set():
            if self._engage_once(deadline) and self._shows_engaged(deadline):
                self._update(engaged=True, mode_lost=False)
                if self._reason is not None:
                    self._log("engage: done")
                return True
            if time.monotonic() >= deadline:
                break
            self._stop.wait(_RETRY_PAUSE_S)
        self._log(
            f"engage: gave up after {timeout_s:g} s; last reason: {self._reason or 'none given'}"
        )
        return False

    def _shows_engaged(self, deadline: float) -> bool:
        """Wait for a HEARTBEAT showing the vehicle armed in the agent's mode: PX4 and ArduPilot
        send it at 1 Hz (PX4's `mavlink_main.cpp`), up to a second after the COMMAND_ACK, and the
        old one's mode would read as a mode lost."""
        texts_before = self._texts_seen
        timeout = min(deadline - time.monotonic(), _CONFIRM_S)
        with self._cond:
            self._cond.wait_for(
                lambda: self._stop.is_set() or self._armed_in_offboard(), timeout=max(timeout, 0.0)
            )
            if self._armed_in_offboard() and not self._stop.is_set():
                return True
        st = self.state()
        shown = f"{st.mode_name or 'an unknown mode'}, {'armed' if st.armed else 'disarmed'}"
        self._fail(f"mode accepted, the HEARTBEAT shows {shown}", texts_before=texts_before)
        return False

    def _armed_in_offboard(self) -> bool:
        return self._state.armed and self._state.mode == FlightMode.OFFBOARD

    def _engage_once(self, deadline: float) -> bool:
        """One pass of the autopilot's engage sequence from the vehicle's present state."""
        st = self.state()
        arm = (1.0,)
        if st.autopilot == Autopilot.ARDUPILOTMEGA:
            # A GUIDED target sent during ArduCopter's takeoff replaces the takeoff (its guided
            # mode leaves SubMode::TakeOff), and the stream holds the vehicle at the altitude it
            # is at, the ground: setpoints are held back until it is airborne.
            ok = self._set_mode(FlightMode.OFFBOARD, deadline=deadline) and self._retry(
                400, arm, deadline=deadline
            )
            if not ok or self.state().landed_state == LandedState.IN_AIR:
                return ok
            self._setpoints_paused = True
            try:
                return self._take_off(_TAKEOFF_ALT_M, deadline=deadline)
            finally:
                self._setpoints_paused = False
        if st.landed_state == LandedState.ON_GROUND:
            # PX4 flies no offboard setpoint off the ground at a constant altitude: it takes off
            # first (AUTO_TAKEOFF to MIS_TAKEOFF_ALT, param 7 NaN), then holds (AUTO_LOITER).
            return (
                self._retry(400, arm, deadline=deadline)
                and self._take_off(math.nan, deadline=deadline)
                and self._set_mode(FlightMode.OFFBOARD, deadline=deadline)
            )
        return self._retry(400, arm, deadline=deadline) and self._set_mode(
            FlightMode.OFFBOARD, deadline=deadline
        )

    def _take_off(self, altitude: float, *, deadline: float) -> bool:
        """MAV_CMD_NAV_TAKEOFF to `altitude` (param 7; NaN: the autopilot's own), retried until
        accepted, then wait until the vehicle is airborne. Yaw, latitude and longitude (params
        4-6) are NaN, "where it is": PX4 takes finite ones as the takeoff's position (0, 0 is
        the Gulf of Guinea, and its copter never leaves the ground for it)."""
        texts_before = self._texts_seen
        here = (math.nan, math.nan, math.nan)
        accepted = self._retry(22, (0.0, 0.0, 0.0, *here, altitude), deadline=deadline)
        return accepted and self._wait_airborne(deadline=deadline, texts_before=texts_before)

    def _wait_airborne(self, *, deadline: float, texts_before: int) -> bool:
        """Until the takeoff is over (landed state IN_AIR): ArduCopter's landed state is TAKEOFF
        while it climbs (a GUIDED target would end the takeoff), PX4's until its takeoff setpoint
        is reached and it loiters, so the vehicle is not the agent's until then. An autopilot
        that reports no landed state within a second is taken at its word. A takeoff that ends
        first (the vehicle disarmed on the ground: PX4's COM_DISARM_PRFLT, ArduCopter's
        DISARM_DELAY) is a failure whose reason is the autopilot's newest STATUSTEXT since
        `texts_before` texts had come."""
        climbing_modes = (
            (FlightMode.OFFBOARD,)
            if self.state().autopilot == Autopilot.ARDUPILOTMEGA
            else (FlightMode.TAKEOFF, FlightMode.HOLD)
        )
        started = time.monotonic()
        quiet_until = started + 1.0
        # A real ArduPilot sends HEARTBEAT once a second: the state may not show the arming and
        # mode the acknowledged commands set until one comes.
        climbing_seen = False
        with self._cond:
            while not self._stop.is_set():
                st = self._state
                if st.landed_state == LandedState.IN_AIR:
                    return True
                if st.landed_state is None and time.monotonic() >= quiet_until:
                    return True
                climbing = st.armed and (st.mode is None or st.mode in climbing_modes)
                if climbing_seen and not climbing:
                    break
                climbing_seen = climbing_seen or climbing
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(min(left, 0.1))
        if self._stop.wait(_RETRY_PAUSE_S):  # (the STATUSTEXT saying why may come after)
            return False
        st = self.state()
        if climbing_seen and not (st.armed and st.mode in climbing_modes):
            where = "disarmed" if not st.armed else f"in {st.mode_name or 'an unknown mode'}"
            reason = f"the takeoff ended before the vehicle was airborne, {where}"
        else:
            reason = f"not airborne {time.monotonic() - started:.0f} s after the takeoff command"
        self._fail(reason, texts_before=texts_before)
        return False

    def hold(self) -> bool:
        self._update(engaged=False)
        return self._set_mode(FlightMode.HOLD, deadline=time.monotonic() + 1.0)

    def close(self) -> None:
        if self._stop.is_set():
            return
        self._stop.set()
        self._reader.join(timeout=1.0)
        with contextlib.suppress(Exception):
            self._conn.close()


_TAKEOFF_ALT_M = 10.0
"""ArduPilot takeoff altitude [m] (the horizontal plant flies at any altitude)."""
_RETRY_PAUSE_S = 0.25
"""Wall seconds between a refused command and its next try, or between two engage passes."""
_CONFIRM_S = 3.0
"""Wall seconds a HEARTBEAT has to show the mode an accepted command set (three of PX4's)."""
_KEPT_TEXTS = 8
"""The autopilot's newest STATUSTEXTs kept for the reasons of refusals."""
_COMMAND_NAMES = {400: "arm", 176: "mode", 22: "takeoff", 511: "message interval"}
"""Names of the commands the link sends, for its log."""


def _px4_main(mode: FlightMode) -> int:
    return {
        FlightMode.OFFBOARD: Px4MainMode.OFFBOARD,
        FlightMode.HOLD: Px4MainMode.AUTO,
        FlightMode.POSITION: Px4MainMode.POSCTL,
        FlightMode.LAND: Px4MainMode.AUTO,
        FlightMode.TAKEOFF: Px4MainMode.AUTO,
    }[mode]
