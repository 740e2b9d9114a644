"""The simulated autopilot's mode, arming and setpoint logic: a pure state machine, no I/O.

Time comes in as integer nanoseconds since boot; every call that changes state takes `now_ns`.
Events a pilot should see (refusals, failsafes) are queued as `Notice`s for the runner to send as
STATUSTEXT.

Profiles:
- PX4: boots in HOLD. OFFBOARD is available while the last valid setpoint is younger than
  `offboard_loss_timeout_ns` (COM_OF_LOSS_T), as PX4's commander decides it
  (`HealthAndArmingChecks/checks/offboardCheck.cpp`: a recent offboard control mode with a control
  flag set; no warm-up, although PX4's documentation asks for 1 s of setpoints first): one
  setpoint, then OFFBOARD at once, is accepted. Without a valid setpoint for that long the vehicle
  switches to HOLD.
  Offboard may be engaged on the ground, and the horizontal (unicycle) plant then follows the
  setpoints at any altitude, so a client's arm -> setpoint -> offboard flow works without a
  takeoff (a simplification: a real PX4 leaves the ground only on a climb demand or a takeoff,
  which is why the agent takes off first). TAKEOFF (MAV_CMD_NAV_TAKEOFF) climbs to the takeoff
  altitude and then switches to HOLD; the landed state is TAKEOFF during the climb, IN_AIR after.
  Three behaviours of a real PX4 SITL can be switched on (all off by default): arming refused
  (TEMPORARILY_REJECTED, "Preflight Fail: heading estimate not stable") until `heading_ready_ns`
  after boot, as PX4 refuses it while its heading estimate settles (4.5-13 s after a SITL's
  boot); COM_DISARM_PRFLT (`preflight_disarm_ns`): armed and never off the ground for that long,
  the vehicle disarms itself ("Disarmed by auto preflight disarming") and a takeoff under way
  ends in HOLD; and a takeoff commanded before `takeoff_stall_ns` after boot is accepted but
  never climbs, as a real PX4 SITL's first takeoff once did (its cause is not modelled), so a
  client sees a takeoff end on the ground.
- ArduPilot (Copter): boots in STABILIZE. Arming and the modes that need a position are refused
  until the position estimate is ready (`position_ready_ns` after boot). A GUIDED target flies
  only once airborne (the takeoff command comes first), and one sent during the takeoff replaces
  it, as ArduCopter's guided mode does (a client must wait for the takeoff to end); after
  `guided_timeout_ns` without a new one the vehicle holds position (mode stays GUIDED). Armed on
  the ground without a takeoff for `disarm_delay_ns` (DISARM_DELAY), it disarms itself.
Position control. A flying vehicle that is not given a velocity demand holds its position, as a
real autopilot's position controller does against the wind: in HOLD, during a takeoff climb or a
landing, in GUIDED without a fresh target, and in OFFBOARD/GUIDED on a position setpoint (which
names the point to fly to and hold). `step` then reports the point in `holding`, and the runner
moves the plant there (`TruthPlant.fly_to`) instead of flying the unicycle.
Both: LAND descends and disarms at touchdown; disarming in the air needs the force flag; a vehicle
disarmed in the air falls at `fall_rate_m_s`. The vertical axis is a separate 1-D kinematic
channel (altitude above home); the estimator is perfect (noise is added only to what is reported).
"""

import math
from dataclasses import dataclass
from enum import Enum

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.mavlink_map import FlightMode, LandedState, MavResult, MavState, Severity
from fleetmpc.protocol.mavlink_setpoint import (
    PositionDemand,
    Rejection,
    SetpointFields,
    UnicycleDemand,
    check_setpoint,
    decode_setpoint,
)
from fleetmpc.validate import positive

__all__ = ["PROFILE_MODES", "Autopilot", "AutopilotConfig", "Notice", "Profile"]


class Profile(Enum):
    """Which real autopilot the simulated one imitates."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"


PROFILE_MODES: dict[Profile, frozenset[FlightMode]] = {
    Profile.PX4: frozenset(
        {
            FlightMode.POSITION,
            FlightMode.HOLD,
            FlightMode.OFFBOARD,
            FlightMode.TAKEOFF,
            FlightMode.LAND,
        }
    ),
    Profile.ARDUPILOT: frozenset(
        {
            FlightMode.STABILIZE,
            FlightMode.POSITION,
            FlightMode.HOLD,
            FlightMode.OFFBOARD,
            FlightMode.LAND,
        }
    ),
}
"""The flight modes each profile implements."""

_NEEDS_POSITION = frozenset({FlightMode.POSITION, FlightMode.HOLD, FlightMode.OFFBOARD})
_ALTITUDE_EPS_M = 1e-6
_ALTITUDE_TIME_CONSTANT_S = 1.0
"""Time constant of the altitude hold on a position setpoint (clamped to the climb limits) [s]."""


@dataclass(frozen=True)
class AutopilotConfig:
    """Limits and timeouts of the simulated autopilot."""

    profile: Profile = Profile.PX4
    """PX4 or ArduPilot behaviour."""
    speed_limit_m_s: float = 2.0
    """Largest forward speed demanded of the plant [m/s]."""
    yaw_rate_limit_rad_s: float = 0.5
    """Largest yaw rate demanded of the plant [rad/s]."""
    takeoff_altitude_m: float = 10.0
    """Default takeoff altitude above home [m]."""
    max_takeoff_altitude_m: float = 500.0
    """Largest takeoff altitude a command may ask for [m]."""
    climb_rate_m_s: float = 1.5
    """Climb rate of a takeoff, and the largest commanded climb rate [m/s]."""
    descent_rate_m_s: float = 0.7
    """Descent rate of a landing, and the largest commanded descent rate [m/s]."""
    fall_rate_m_s: float = 5.0
    """Descent rate of a vehicle disarmed in the air [m/s]."""
    offboard_loss_timeout_ns: int = 1_000_000_000
    """PX4 COM_OF_LOSS_T: OFFBOARD without a valid setpoint for this long switches to HOLD [ns]."""
    guided_timeout_ns: int = 3_000_000_000
    """ArduPilot: a GUIDED velocity target older than this is replaced by zero velocity [ns]."""
    position_ready_ns: int = 4_000_000_000
    """ArduPilot: time after boot at which the position estimate becomes ready [ns]."""
    disarm_delay_ns: int = 10_000_000_000
    """ArduPilot DISARM_DELAY: armed on the ground without taking off for this long, the vehicle
    disarms itself [ns] (ArduCopter's default 10 s; 0: never)."""
    heading_ready_ns: int = 0
    """PX4: arming is refused until this time after boot, while the heading estimate settles
    [ns] (0: at once; a real PX4 SITL: 4.5-13 s)."""
    preflight_disarm_ns: int = 0
    """PX4 COM_DISARM_PRFLT: armed and never off the ground for this long since arming, the
    vehicle disarms itself [ns] (0: never; PX4's default is 10 s, but this profile flies
    offboard setpoints on the ground, which a real PX4 would not)."""
    takeoff_stall_ns: int = 0
    """PX4: a takeoff commanded before this time after boot is accepted but never climbs [ns]
    (0: none stalls)."""
    local_origin_m: tuple[float, float] = (0.0, 0.0)
    """Where the vehicle's local frame (LOCAL_POSITION_NED, position targets) has its origin in
    the scenario's frame (North, East) [m]: a real autopilot's estimator starts where it boots."""
    yaw_gain_1_s: float = 2.0
    """Yaw rate per radian of heading error when a setpoint carries a yaw [1/s]."""

    def __post_init__(self) -> None:
        if not isinstance(self.profile, Profile):
            raise ConfigError("profile", f"must be a Profile, got {self.profile!r}")
        for name in (
            "speed_limit_m_s",
            "yaw_rate_limit_rad_s",
            "takeoff_altitude_m",
            "max_takeoff_altitude_m",
            "climb_rate_m_s",
            "descent_rate_m_s",
            "fall_rate_m_s",
            "yaw_gain_1_s",
        ):
            positive(name, getattr(self, name))
        if self.takeoff_altitude_m > self.max_takeoff_altitude_m:
            raise ConfigError("takeoff_altitude_m", "must not exceed max_takeoff_altitude_m")
        for name in (
            "offboard_loss_timeout_ns",
            "guided_timeout_ns",
            "position_ready_ns",
            "disarm_delay_ns",
            "heading_ready_ns",
            "preflight_disarm_ns",
            "takeoff_stall_ns",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ConfigError(name, f"must be a non-negative integer [ns], got {value!r}")


@dataclass(frozen=True)
class Notice:
    """A message for the pilot (sent as STATUSTEXT)."""

    severity: Severity
    text: str


@dataclass
class _Stream:
    """The last valid setpoint and when it came."""

    setpoint: SetpointFields | None = None
    last_ns: int = 0


class Autopilot:
    """Mode, arming, setpoint and altitude logic of one simulated vehicle."""

    def __init__(self, config: AutopilotConfig) -> None:
        self.config = config
        self.mode = FlightMode.HOLD if config.profile == Profile.PX4 else FlightMode.STABILIZE
        self.armed = False
        self.altitude_m = 0.0
        self.climb_rate_m_s = 0.0
        self.rejected: dict[Rejection, int] = {}
        self._takeoff_target_m: float | None = None
        self._stream = _Stream()
        self._notices: list[Notice] = []
        self._hold_point: tuple[float, float] | None = None
        self._grounded_since_ns: int | None = None
        """ArduPilot: since when the vehicle is armed on the ground, not taking off."""
        self._armed_ns = 0
        """When the vehicle was last armed [ns]."""
        self._flown_since_arming = False
        """PX4: the vehicle has left the ground since it was last armed."""
        self._takeoff_stalled = False
        """PX4: the takeoff under way never climbs (`AutopilotConfig.takeoff_stall_ns`)."""
        self.holding: tuple[float, float] | None = None
        """The (North, East) point the position controller flies to this tick; None while a
        velocity demand is flown or the vehicle cannot fly horizontally (set by `step`)."""

    # ----------------------------------------------------------------------------- queries
    @property
    def px4(self) -> bool:
        return self.config.profile == Profile.PX4

    @property
    def landed(self) -> bool:
        """On the ground: at zero altitude and not climbing."""
        return self.altitude_m <= _ALTITUDE_EPS_M and self.climb_rate_m_s <= 0.0

    @property
    def landed_state(self) -> LandedState:
        if self.landed:
            return LandedState.ON_GROUND
        if self.climb_rate_m_s > 0.0 and (
            self.mode == FlightMode.TAKEOFF or self._takeoff_target_m is not None
        ):
            return LandedState.TAKEOFF
        if self.mode == FlightMode.LAND:
            return LandedState.LANDING
        return LandedState.IN_AIR

    @property
    def system_status(self) -> MavState:
        return MavState.ACTIVE if self.armed else MavState.STANDBY

    def position_ready(self, now_ns: int) -> bool:
        """Whether the (simulated) position estimate is usable."""
        return self.px4 or now_ns >= self.config.position_ready_ns

    def setpoint_stream_ok(self, now_ns: int) -> bool:
        """PX4's offboard availability: a valid setpoint younger than COM_OF_LOSS_T."""
        s = self._stream
        return s.setpoint is not None and now_ns - s.last_ns < self.config.offboard_loss_timeout_ns

    def take_notices(self) -> list[Notice]:
        """Notices queued since the last call, oldest first."""
        notices, self._notices = self._notices, []
        return notices

    # ----------------------------------------------------------------------------- commands
    def receive_setpoint(self, setpoint: SetpointFields, now_ns: int) -> Rejection | None:
        """Take a SET_POSITION_TARGET_LOCAL_NED; a rejected one changes nothing but a counter."""
        rejection = check_setpoint(setpoint)
        if rejection is not None:
            count = self.rejected.get(rejection, 0)
            self.rejected[rejection] = count + 1
            if count == 0:
                self._notify(Severity.WARNING, f"Setpoint ignored: {rejection.value}")
            return rejection
        if not self.px4 and self.mode != FlightMode.OFFBOARD:
            return None  # ArduPilot reads position targets only in GUIDED
        s = self._stream
        s.setpoint, s.last_ns = setpoint, now_ns
        return None

    def arm(self, now_ns: int) -> MavResult:
        if self.armed:
            return MavResult.ACCEPTED
        if not self.px4 and not self.position_ready(now_ns):
            return self._refuse(Severity.CRITICAL, "PreArm: Need Position Estimate")
        if self.mode == FlightMode.LAND:
            return self._refuse(Severity.CRITICAL, "Arming denied: not in an armable mode")
        if self.px4 and self.mode == FlightMode.OFFBOARD and not self.setpoint_stream_ok(now_ns):
            return self._refuse(Severity.CRITICAL, "Arming denied: no offboard setpoints")
        if self.px4 and now_ns < self.config.heading_ready_ns:
            # (PX4's commander answers a refused arming TEMPORARILY_REJECTED)
            self._refuse(Severity.CRITICAL, "Preflight Fail: heading estimate not stable")
            return MavResult.TEMPORARILY_REJECTED
        self.armed = True
        self._armed_ns = now_ns
        self._flown_since_arming = False
        self._notify(Severity.INFO, "Armed by external command")
        return MavResult.ACCEPTED

    def disarm(self, now_ns: int, *, force: bool = False) -> MavResult:
        if not self.armed:
            return MavResult.ACCEPTED
        if not (self.landed or force):
            return self._refuse(Severity.CRITICAL, "Disarming denied: not landed")
        self._disarm("Disarmed by external command")
        return MavResult.ACCEPTED

    def set_mode(self, mode: FlightMode | None, now_ns: int) -> MavResult:
        """Switch flight mode; None (a mode the profile does not know) is refused."""
        if mode is None or mode not in PROFILE_MODES[self.config.profile]:
            return self._refuse(Severity.WARNING, "Mode change denied: unsupported mode")
        if mode == self.mode:
            return MavResult.ACCEPTED
        if mode in _NEEDS_POSITION and not self.position_ready(now_ns):
            return self._refuse(
                Severity.WARNING, f"Mode change failed: {mode.name} requires position"
            )
        if self.px4 and mode == FlightMode.OFFBOARD and not self.setpoint_stream_ok(now_ns):
            return self._refuse(Severity.WARNING, "Offboard denied: no recent setpoint")
        self._enter(mode)
        return MavResult.ACCEPTED

    def takeoff(
        self, now_ns: int, *, altitude_m: float | None = None, stalled: bool = False
    ) -> MavResult:
        """Climb to `altitude_m` above home (None: the configured takeoff altitude); `stalled`
        (PX4): accept, and never climb."""
        c = self.config
        target = c.takeoff_altitude_m if altitude_m is None else altitude_m
        if not (math.isfinite(target) and 0.5 <= target <= c.max_takeoff_altitude_m):
            return self._refuse(Severity.WARNING, "Takeoff denied: altitude out of range")
        if self.px4:
            if self.mode == FlightMode.LAND and self.armed:
                return self._refuse(Severity.WARNING, "Takeoff denied: landing")
            self._takeoff_target_m = target
            self._enter(FlightMode.TAKEOFF)
            self._takeoff_stalled = stalled or now_ns < c.takeoff_stall_ns
            return MavResult.ACCEPTED
        if self.mode != FlightMode.OFFBOARD or not self.armed or not self.landed:
            return self._refuse(Severity.WARNING, "Takeoff failed: needs GUIDED, armed, landed")
        self._takeoff_target_m = target
        self._stream.setpoint = None
        return MavResult.ACCEPTED

    def land(self, now_ns: int) -> MavResult:
        if self.mode != FlightMode.LAND:
            self._enter(FlightMode.LAND)
        return MavResult.ACCEPTED

    # ----------------------------------------------------------------------------- time
    def step(
        self,
        now_ns: int,
        tick_ns: int,
        *,
        heading_rad: float,
        position_m: tuple[float, float] | None = None,
    ) -> tuple[float, float]:
        """Decide the (speed, yaw-rate) demand for the plant tick starting at `now_ns`.

        With the vehicle's true `position_m`, a flying vehicle without a velocity demand holds
        position: the demand is (0, 0) and `holding` names the point (see the module docstring).
        """
        c = self.config
        fresh = self._fresh_setpoint(now_ns)
        if self.px4 and self.mode == FlightMode.OFFBOARD and fresh is None:
            self._enter(FlightMode.HOLD)
            timeout_s = c.offboard_loss_timeout_ns * 1e-9
            self._notify(
                Severity.CRITICAL, f"Offboard lost: no setpoint for {timeout_s:.1f} s, Hold"
            )
        if not self.px4 and self._takeoff_target_m is not None and fresh is not None:
            # A GUIDED target that comes during the takeoff replaces it (ArduCopter's
            # ModeGuided::set_destination and its kin leave SubMode::TakeOff): on the ground,
            # a position target at the ground's altitude keeps the vehicle there.
            self._takeoff_target_m = None
        self._auto_disarm(now_ns)
        demand = self._decode(fresh, heading_rad)
        self._climb(demand, tick_ns * 1e-9)
        horizontal = self.armed and (self.px4 or not self.landed)
        self.holding = None
        if not horizontal:
            self._hold_point = None
            return 0.0, 0.0
        if isinstance(demand, PositionDemand):
            self._hold_point = None
            on, oe = c.local_origin_m
            self.holding = (demand.north_m + on, demand.east_m + oe)
            return 0.0, 0.0
        if demand is None:
            if self._hold_point is None and position_m is not None:
                self._hold_point = (float(position_m[0]), float(position_m[1]))
            self.holding = self._hold_point
            return 0.0, 0.0
        self._hold_point = None
        speed = min(max(demand.speed_m_s, -c.speed_limit_m_s), c.speed_limit_m_s)
        yaw_rate = min(max(demand.yaw_rate_rad_s, -c.yaw_rate_limit_rad_s), c.yaw_rate_limit_rad_s)
        return speed, yaw_rate

    # ----------------------------------------------------------------------------- internals
    def _fresh_setpoint(self, now_ns: int) -> SetpointFields | None:
        """The setpoint to fly now, or None (never in modes that ignore setpoints)."""
        s, c = self._stream, self.config
        if self.mode != FlightMode.OFFBOARD or s.setpoint is None:
            return None
        timeout_ns = c.offboard_loss_timeout_ns if self.px4 else c.guided_timeout_ns
        return s.setpoint if now_ns - s.last_ns < timeout_ns else None

    def _decode(
        self, setpoint: SetpointFields | None, heading_rad: float
    ) -> UnicycleDemand | PositionDemand | None:
        if setpoint is None:
            return None
        demand = decode_setpoint(
            setpoint,
            heading_rad=heading_rad,
            yaw_gain_1_s=self.config.yaw_gain_1_s,
            yaw_relative_in_body=not self.px4,
        )
        return None if isinstance(demand, Rejection) else demand

    def _climb(self, demand: UnicycleDemand | PositionDemand | None, dt_s: float) -> None:
        """Vertical channel: pick a climb rate for this tick and integrate the altitude."""
        c = self.config
        climbing_modes = (FlightMode.TAKEOFF, FlightMode.OFFBOARD)
        target = self._takeoff_target_m if self.armed and self.mode in climbing_modes else None
        if target is not None and self.altitude_m >= target:
            self._finish_takeoff(target)
            target = None
        if not self.armed:
            rate = -c.fall_rate_m_s if self.altitude_m > 0.0 else 0.0
        elif self.mode == FlightMode.LAND:
            rate = -c.descent_rate_m_s
        elif target is not None and self._takeoff_stalled and self.mode == FlightMode.TAKEOFF:
            rate = 0.0
        elif target is not None:
            rate = c.climb_rate_m_s
        elif self.mode == FlightMode.OFFBOARD and isinstance(demand, PositionDemand):
            wanted = (demand.altitude_m - self.altitude_m) / _ALTITUDE_TIME_CONSTANT_S
            rate = min(max(wanted, -c.descent_rate_m_s), c.climb_rate_m_s)
        elif self.mode == FlightMode.OFFBOARD and demand is not None:
            rate = min(max(demand.climb_rate_m_s, -c.descent_rate_m_s), c.climb_rate_m_s)
        else:
            rate = 0.0
        altitude = max(self.altitude_m + rate * dt_s, 0.0)
        if target is not None and altitude >= target:
            altitude, rate = target, 0.0
            self._finish_takeoff(target)
        self.altitude_m = altitude
        self.climb_rate_m_s = rate if altitude > 0.0 or rate > 0.0 else 0.0
        self._flown_since_arming = self._flown_since_arming or (self.armed and altitude > 0.0)
        if self.armed and self.mode == FlightMode.LAND and self.landed:
            self._notify(Severity.INFO, "Landing detected")
            self._disarm("Disarmed by landing")

    def _finish_takeoff(self, target_m: float) -> None:
        self._takeoff_target_m = None
        if self.mode == FlightMode.TAKEOFF:
            self._enter(FlightMode.HOLD)
        self._notify(Severity.INFO, f"Takeoff complete at {target_m:.1f} m")

    def _enter(self, mode: FlightMode) -> None:
        if mode == FlightMode.TAKEOFF and self._takeoff_target_m is None:
            self._takeoff_target_m = self.config.takeoff_altitude_m
        elif mode != FlightMode.TAKEOFF and (self.px4 or mode == FlightMode.LAND):
            self._takeoff_target_m = None
        if not self.px4 and mode == FlightMode.OFFBOARD:
            self._stream.setpoint = None  # GUIDED starts by holding position
        self.mode = mode

    def _auto_disarm(self, now_ns: int) -> None:
        """Disarm a vehicle left armed on the ground: ArduPilot's DISARM_DELAY, PX4's
        COM_DISARM_PRFLT."""
        if self.px4:
            delay = self.config.preflight_disarm_ns
            grounded = self.armed and not self._flown_since_arming and self.landed
            if delay and grounded and now_ns - self._armed_ns >= delay:
                if self.mode == FlightMode.TAKEOFF:
                    self._enter(FlightMode.HOLD)
                self._disarm("Disarmed by auto preflight disarming")
            return
        delay = self.config.disarm_delay_ns
        waiting = self.armed and self.landed and self._takeoff_target_m is None
        if self.px4 or not delay or not waiting:
            self._grounded_since_ns = None
            return
        if self._grounded_since_ns is None:
            self._grounded_since_ns = now_ns
        elif now_ns - self._grounded_since_ns >= delay:
            self._grounded_since_ns = None
            self._disarm(f"Auto disarmed: on the ground {delay * 1e-9:g} s without a takeoff")

    def _disarm(self, text: str) -> None:
        self.armed = False
        self._takeoff_target_m = None
        self._takeoff_stalled = False
        self._notify(Severity.INFO, text)

    def _refuse(self, severity: Severity, text: str) -> MavResult:
        self._notify(severity, text)
        return MavResult.DENIED if self.px4 else MavResult.FAILED

    def _notify(self, severity: Severity, text: str) -> None:
        self._notices.append(Notice(severity, text[:50]))
