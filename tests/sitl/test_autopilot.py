"""The pure autopilot state machine, driven tick by tick by a manual clock."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fleetmpc.clock import ManualClock
from fleetmpc.errors import ConfigError
from fleetmpc.protocol.mavlink_map import FlightMode, LandedState, MavResult
from fleetmpc.protocol.mavlink_setpoint import (
    Frame,
    Rejection,
    SetpointFields,
    TypeMask,
    encode_position_setpoint,
    encode_setpoint,
)
from fleetmpc.sitl.autopilot import Autopilot, AutopilotConfig, Profile

TICK_NS = 20_000_000
MS = 1_000_000
S = 1_000_000_000
FORWARD = encode_setpoint(1.0, 0.2, frame=Frame.BODY_NED)


class Sim:
    """An autopilot, a manual clock and a heading integrated from the demands (a toy plant)."""

    def __init__(self, **config) -> None:
        self.ap = Autopilot(AutopilotConfig(**config))
        self.clock = ManualClock()
        self.heading_rad = 0.0
        self.demand = (0.0, 0.0)

    @property
    def now(self) -> int:
        return self.clock.now_ns()

    def tick(self) -> tuple[float, float]:
        self.demand = self.ap.step(self.now, TICK_NS, heading_rad=self.heading_rad)
        self.heading_rad += self.demand[1] * TICK_NS * 1e-9
        self.clock.advance(TICK_NS)
        return self.demand

    def run(self, duration_ns: int, *, setpoint=None, every_ns: int = 100 * MS) -> None:
        """Tick for `duration_ns`, sending `setpoint` every `every_ns` (on tick boundaries)."""
        end = self.now + duration_ns
        next_sp = self.now
        while self.now < end:
            if setpoint is not None and self.now >= next_sp:
                self.ap.receive_setpoint(setpoint, self.now)
                next_sp += every_ns
            self.tick()

    def texts(self) -> list[str]:
        return [n.text for n in self.ap.take_notices()]


def engaged_px4(**config) -> Sim:
    sim = Sim(**config)
    sim.run(1100 * MS, setpoint=FORWARD)
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.ACCEPTED
    assert sim.ap.arm(sim.now) == MavResult.ACCEPTED
    return sim


def test_px4_boots_disarmed_in_hold():
    ap = Autopilot(AutopilotConfig())
    assert (ap.mode, ap.armed, ap.landed_state) == (FlightMode.HOLD, False, LandedState.ON_GROUND)
    assert ap.step(0, TICK_NS, heading_rad=0.0) == (0.0, 0.0)


def test_offboard_is_available_while_the_last_setpoint_is_recent():
    """As PX4's commander decides it (offboardCheck.cpp): a setpoint younger than COM_OF_LOSS_T
    makes OFFBOARD available at once, with no warm-up; an older one does not."""
    sim = Sim()
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.DENIED
    assert any("Offboard denied" in t for t in sim.texts())
    sim.run(1 * MS, setpoint=FORWARD)  # one setpoint
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.ACCEPTED
    assert sim.ap.mode == FlightMode.OFFBOARD


def test_a_setpoint_older_than_com_of_loss_t_does_not_enable_offboard():
    sim = Sim(offboard_loss_timeout_ns=500 * MS)
    sim.run(1 * MS, setpoint=FORWARD)
    sim.run(600 * MS)  # silence: the setpoint is 600 ms old
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.DENIED
    sim.run(1 * MS, setpoint=FORWARD)
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.ACCEPTED


@pytest.mark.parametrize("loss_s", [1.0, 0.5, 2.5])
def test_setpoint_loss_switches_to_hold_after_com_of_loss_t(loss_s):
    loss_ns = round(loss_s * S)
    sim = engaged_px4(offboard_loss_timeout_ns=loss_ns)
    sim.run(1 * S, setpoint=FORWARD)
    t_last = sim.now - 100 * MS  # the last setpoint went out one stream period ago
    sim.texts()
    while sim.ap.mode == FlightMode.OFFBOARD:
        sim.tick()
        assert sim.now < t_last + 10 * S
    switched_at = sim.now - TICK_NS  # the tick that started at this time made the switch
    assert t_last + loss_ns <= switched_at < t_last + loss_ns + TICK_NS
    assert sim.demand == (0.0, 0.0)
    assert sim.ap.armed
    assert [t for t in sim.texts() if "Offboard lost" in t]


def test_offboard_follows_body_local_and_yaw_setpoints():
    sim = engaged_px4()
    heading = math.radians(30)
    ap = sim.ap
    ap.receive_setpoint(encode_setpoint(1.5, -0.3, frame=Frame.BODY_OFFSET_NED), sim.now)
    assert ap.step(sim.now, TICK_NS, heading_rad=heading) == pytest.approx((1.5, -0.3))
    local = SetpointFields(int(Frame.LOCAL_NED), int(TypeMask.VELOCITY_YAW_RATE), vx_m_s=1.0)
    ap.receive_setpoint(local, sim.now)
    speed, _ = ap.step(sim.now, TICK_NS, heading_rad=heading)
    assert speed == pytest.approx(math.cos(heading))  # the lateral part cannot be flown
    yaw = SetpointFields(int(Frame.LOCAL_NED), int(TypeMask.VELOCITY_YAW), yaw_rad=0.4)
    ap.receive_setpoint(yaw, sim.now)
    _, yaw_rate = ap.step(sim.now, TICK_NS, heading_rad=0.5)
    assert yaw_rate == pytest.approx(-0.1 * ap.config.yaw_gain_1_s)


def test_demands_are_clamped_to_the_vehicle_limits():
    sim = engaged_px4(speed_limit_m_s=2.0, yaw_rate_limit_rad_s=0.5)
    sim.ap.receive_setpoint(encode_setpoint(9.0, -3.0), sim.now)
    assert sim.tick() == (2.0, -0.5)
    sim.ap.receive_setpoint(encode_setpoint(-9.0, 3.0), sim.now)
    assert sim.tick() == (-2.0, 0.5)


def test_invalid_setpoints_keep_the_last_valid_command_and_are_reported_once():
    sim = engaged_px4()
    sim.texts()
    bad = SetpointFields(int(Frame.BODY_NED), int(TypeMask.VELOCITY_YAW_RATE), vx_m_s=math.nan)
    for _ in range(5):
        assert sim.ap.receive_setpoint(bad, sim.now) == Rejection.NON_FINITE
        assert sim.tick() == pytest.approx((1.0, 0.2))
    huge = encode_setpoint(1e9, 0.0)
    assert sim.ap.receive_setpoint(huge, sim.now) == Rejection.IMPLAUSIBLE
    assert sim.ap.rejected == {Rejection.NON_FINITE: 5, Rejection.IMPLAUSIBLE: 1}
    assert sim.texts() == [
        "Setpoint ignored: NaN or Inf field",
        "Setpoint ignored: implausibly large value",
    ]


def test_px4_takeoff_climbs_to_the_altitude_then_holds_and_land_disarms():
    sim = Sim(takeoff_altitude_m=5.0, climb_rate_m_s=1.5, descent_rate_m_s=0.7)
    assert sim.ap.arm(sim.now) == MavResult.ACCEPTED
    assert sim.ap.takeoff(sim.now) == MavResult.ACCEPTED
    assert sim.ap.mode == FlightMode.TAKEOFF
    sim.tick()
    assert sim.ap.landed_state == LandedState.TAKEOFF
    sim.run(round(5.0 / 1.5 * S))
    assert sim.ap.mode == FlightMode.HOLD
    assert sim.ap.altitude_m == pytest.approx(5.0)
    assert sim.ap.landed_state == LandedState.IN_AIR
    assert sim.ap.disarm(sim.now) == MavResult.DENIED  # not landed
    assert sim.ap.land(sim.now) == MavResult.ACCEPTED
    sim.tick()
    assert sim.ap.landed_state == LandedState.LANDING
    sim.run(round(5.0 / 0.7 * S) + TICK_NS)
    assert sim.ap.altitude_m == 0.0 and not sim.ap.armed
    assert "Disarmed by landing" in sim.texts()


def test_disarm_in_the_air_needs_the_force_flag():
    sim = Sim(takeoff_altitude_m=2.0)
    sim.ap.arm(sim.now)
    sim.ap.takeoff(sim.now)
    sim.run(2 * S)
    assert sim.ap.disarm(sim.now) == MavResult.DENIED and sim.ap.armed
    assert sim.ap.disarm(sim.now, force=True) == MavResult.ACCEPTED and not sim.ap.armed
    sim.run(1 * S)
    assert sim.ap.altitude_m == 0.0  # a disarmed vehicle falls


def test_modes_a_profile_lacks_are_refused():
    px4 = Autopilot(AutopilotConfig())
    assert px4.set_mode(FlightMode.STABILIZE, 0) == MavResult.DENIED
    assert px4.set_mode(None, 0) == MavResult.DENIED
    ardupilot = Autopilot(AutopilotConfig(profile=Profile.ARDUPILOT, position_ready_ns=0))
    assert ardupilot.set_mode(FlightMode.TAKEOFF, 0) == MavResult.FAILED
    assert ardupilot.mode == FlightMode.STABILIZE


def test_ardupilot_refuses_arming_and_guided_until_the_position_is_ready():
    sim = Sim(profile=Profile.ARDUPILOT, position_ready_ns=3 * S)
    assert sim.ap.arm(sim.now) == MavResult.FAILED
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.FAILED
    assert sim.texts()[0] == "PreArm: Need Position Estimate"
    sim.run(3 * S - TICK_NS)
    assert sim.ap.arm(sim.now) == MavResult.FAILED
    sim.tick()
    assert sim.ap.arm(sim.now) == MavResult.ACCEPTED
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.ACCEPTED


def test_ardupilot_guided_flies_only_in_the_air_and_stops_after_3_s():
    sim = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0, takeoff_altitude_m=3.0)
    assert sim.ap.takeoff(sim.now) == MavResult.FAILED  # needs GUIDED and armed
    sim.ap.set_mode(FlightMode.OFFBOARD, sim.now)
    sim.ap.arm(sim.now)
    sim.run(1 * S, setpoint=FORWARD)
    assert sim.demand == (0.0, 0.0), "GUIDED velocity is not flown on the ground"
    assert sim.ap.takeoff(sim.now) == MavResult.ACCEPTED
    sim.run(3 * S)
    assert sim.ap.altitude_m == pytest.approx(3.0)
    sim.run(1 * S, setpoint=FORWARD)
    assert sim.demand == pytest.approx((1.0, 0.2))
    t_last = sim.now - 100 * MS
    while sim.demand != (0.0, 0.0):
        sim.tick()
    stopped_at = sim.now - TICK_NS
    assert t_last + 3 * S <= stopped_at < t_last + 3 * S + TICK_NS
    assert sim.ap.mode == FlightMode.OFFBOARD and sim.ap.armed


def test_a_flying_vehicle_without_a_velocity_holds_a_point():
    """HOLD, an ArduPilot takeoff climb, a GUIDED timeout and a position setpoint all hand the
    plant to the position controller (`holding`); a velocity demand takes it back."""
    sim = Sim(position_ready_ns=0)
    sim.ap.arm(sim.now)
    sim.demand = sim.ap.step(sim.now, TICK_NS, heading_rad=0.0, position_m=(1.0, 2.0))
    assert sim.demand == (0.0, 0.0) and sim.ap.holding == (1.0, 2.0)  # PX4 HOLD, armed
    sim.ap.step(sim.now, TICK_NS, heading_rad=0.0, position_m=(9.0, 9.0))
    assert sim.ap.holding == (1.0, 2.0), "the point is latched, not the current position"
    point = encode_position_setpoint(5.0, -3.0, -2.0)
    sim.run(1100 * MS, setpoint=point)
    assert sim.ap.set_mode(FlightMode.OFFBOARD, sim.now) == MavResult.ACCEPTED
    sim.run(3 * S, setpoint=point)
    assert sim.ap.holding == (5.0, -3.0) and sim.ap.altitude_m == pytest.approx(2.0, abs=0.2)
    sim.run(200 * MS, setpoint=FORWARD)
    assert sim.demand == pytest.approx((1.0, 0.2)) and sim.ap.holding is None

    ardu = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0, takeoff_altitude_m=3.0)
    ardu.ap.set_mode(FlightMode.OFFBOARD, ardu.now)
    ardu.ap.arm(ardu.now)
    ardu.ap.takeoff(ardu.now)
    for _ in range(10):
        ardu.demand = ardu.ap.step(ardu.now, TICK_NS, heading_rad=0.0, position_m=(0.0, 12.0))
        ardu.clock.advance(TICK_NS)
    assert ardu.ap.altitude_m > 0.0 and ardu.demand == (0.0, 0.0)
    assert ardu.ap.holding == (0.0, 12.0), "the takeoff climb holds the point"


def test_an_ardupilot_guided_target_during_the_takeoff_replaces_it():
    """As ArduCopter's guided mode: a target sent during the takeoff leaves SubMode::TakeOff. A
    position target at the ground's altitude keeps the vehicle on the ground, where it disarms
    itself after DISARM_DELAY."""
    ardu = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0, takeoff_altitude_m=3.0)
    ardu.ap.set_mode(FlightMode.OFFBOARD, ardu.now)
    ardu.ap.arm(ardu.now)
    assert ardu.ap.takeoff(ardu.now) == MavResult.ACCEPTED
    ground = encode_position_setpoint(0.0, 0.0, 0.0)
    ardu.run(12 * S, setpoint=ground)
    assert ardu.ap.altitude_m == 0.0 and ardu.ap.landed_state == LandedState.ON_GROUND
    assert not ardu.ap.armed


def test_ardupilot_ignores_setpoints_outside_guided():
    sim = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0)
    sim.run(1 * S, setpoint=FORWARD)
    sim.ap.set_mode(FlightMode.OFFBOARD, sim.now)
    sim.ap.arm(sim.now)
    sim.ap.takeoff(sim.now, altitude_m=1.0)
    sim.run(1 * S)
    assert sim.demand == (0.0, 0.0), "a setpoint sent before GUIDED must not be flown"


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match="speed_limit_m_s"):
        AutopilotConfig(speed_limit_m_s=-1.0)
    with pytest.raises(ConfigError, match="offboard_loss_timeout_ns"):
        AutopilotConfig(offboard_loss_timeout_ns=1.5)
    with pytest.raises(ConfigError, match="takeoff_altitude_m"):
        AutopilotConfig(takeoff_altitude_m=900.0)


floats = st.floats(allow_nan=True, allow_infinity=True, width=32)
setpoints = st.builds(
    SetpointFields,
    frame=st.sampled_from([1, 7, 8, 9, 21]),
    type_mask=st.sampled_from([1479, 2503, 0, 3527]),
    vx_m_s=floats,
    vy_m_s=floats,
    vz_m_s=floats,
    yaw_rad=floats,
    yaw_rate_rad_s=floats,
)
actions = st.one_of(
    st.tuples(st.just("setpoint"), setpoints),
    st.tuples(st.sampled_from(["arm", "disarm", "force", "land", "takeoff", "tick"]), st.none()),
    st.tuples(st.just("mode"), st.sampled_from([*FlightMode, None])),
)


@settings(max_examples=150, deadline=None)
@given(profile=st.sampled_from(list(Profile)), script=st.lists(actions, max_size=60))
def test_no_command_sequence_exceeds_the_limits(profile, script):
    sim = Sim(profile=profile, position_ready_ns=0, speed_limit_m_s=2.0, yaw_rate_limit_rad_s=0.5)
    ap = sim.ap
    for kind, arg in script:
        if kind == "setpoint":
            ap.receive_setpoint(arg, sim.now)
        elif kind == "mode":
            ap.set_mode(arg, sim.now)
        elif kind in ("arm", "land", "takeoff"):
            getattr(ap, kind)(sim.now)
        elif kind in ("disarm", "force"):
            ap.disarm(sim.now, force=kind == "force")
        for _ in range(5):
            speed, yaw_rate = sim.tick()
            assert abs(speed) <= 2.0 and abs(yaw_rate) <= 0.5
            assert math.isfinite(speed) and math.isfinite(yaw_rate)
            assert ap.altitude_m >= 0.0 and math.isfinite(ap.altitude_m)
            assert all(len(n.text) <= 50 for n in ap.take_notices())


def test_ardupilot_disarms_itself_left_armed_on_the_ground():
    """DISARM_DELAY: 10 s armed on the ground without a takeoff, and the vehicle disarms."""
    sim = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0)
    sim.ap.set_mode(FlightMode.OFFBOARD, sim.now)
    sim.ap.arm(sim.now)
    sim.texts()
    sim.run(9900 * MS, setpoint=FORWARD)
    assert sim.ap.armed
    sim.run(200 * MS)
    assert not sim.ap.armed and sim.ap.mode == FlightMode.OFFBOARD  # the mode stays GUIDED
    assert any("Auto disarmed" in t for t in sim.texts())


def test_ardupilot_does_not_disarm_once_it_takes_off_and_px4_never_does():
    ardu = Sim(profile=Profile.ARDUPILOT, position_ready_ns=0, takeoff_altitude_m=3.0)
    ardu.ap.set_mode(FlightMode.OFFBOARD, ardu.now)
    ardu.ap.arm(ardu.now)
    ardu.run(5 * S)
    assert ardu.ap.takeoff(ardu.now) == MavResult.ACCEPTED
    ardu.run(20 * S)
    assert ardu.ap.armed and ardu.ap.landed_state == LandedState.IN_AIR
    px4 = Sim(position_ready_ns=0)
    px4.ap.arm(px4.now)
    px4.run(20 * S)
    assert px4.ap.armed
