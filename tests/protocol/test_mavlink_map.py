"""protocol.mavlink_map, mavlink_setpoint and local_frame against pymavlink's own tables, and their
round trips."""

import math
import os

import pytest
from hypothesis import given
from hypothesis import strategies as st

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402

from fleetmpc.protocol.local_frame import (  # noqa: E402
    EARTH_RADIUS_M,
    geodetic_from_ned,
    ned_from_geodetic,
    wrap_pi,
)
from fleetmpc.protocol.mavlink_map import (  # noqa: E402
    COPTER_MODE_OF,
    PX4_CUSTOM_MODE_OF,
    Autopilot,
    CopterMode,
    FlightMode,
    LandedState,
    MavResult,
    MavState,
    ModeFlag,
    Severity,
    base_mode,
    custom_mode_of,
    mode_from_custom,
    px4_custom_mode,
    px4_split_custom_mode,
)
from fleetmpc.protocol.mavlink_setpoint import (  # noqa: E402
    Frame,
    PositionDemand,
    Rejection,
    SetpointFields,
    TypeMask,
    UnicycleDemand,
    decode_setpoint,
    encode_position_setpoint,
    encode_setpoint,
    setpoint_message_args,
)

M = mavutil.mavlink


@pytest.mark.parametrize(
    ("ours", "prefix"),
    [
        (Frame, "MAV_FRAME_"),
        (ModeFlag, "MAV_MODE_FLAG_"),
        (MavResult, "MAV_RESULT_"),
        (MavState, "MAV_STATE_"),
        (LandedState, "MAV_LANDED_STATE_"),
        (Severity, "MAV_SEVERITY_"),
        (Autopilot, "MAV_AUTOPILOT_"),
    ],
)
def test_enums_match_pymavlink(ours, prefix):
    for member in ours:
        assert getattr(M, prefix + member.name) == member.value, member


def test_type_masks_ignore_exactly_what_they_should():
    ignore = {name: getattr(M, f"POSITION_TARGET_TYPEMASK_{name}_IGNORE") for name in
              ("X", "Y", "Z", "VX", "VY", "VZ", "AX", "AY", "AZ", "YAW", "YAW_RATE")}  # fmt: skip
    position_accel = sum(ignore[k] for k in ("X", "Y", "Z", "AX", "AY", "AZ"))
    assert TypeMask.VELOCITY_YAW_RATE == position_accel + ignore["YAW"] == 1479
    assert TypeMask.VELOCITY_YAW == position_accel + ignore["YAW_RATE"] == 2503


@pytest.mark.parametrize(
    ("mode", "px4_name"),
    [
        (FlightMode.POSITION, "POSCTL"),
        (FlightMode.HOLD, "LOITER"),
        (FlightMode.OFFBOARD, "OFFBOARD"),
        (FlightMode.TAKEOFF, "TAKEOFF"),
        (FlightMode.LAND, "LAND"),
    ],
)
def test_px4_custom_modes_match_pymavlink(mode, px4_name):
    _, main, sub = mavutil.px4_map[px4_name]
    assert PX4_CUSTOM_MODE_OF[mode] == (main << 16) | (sub << 24)
    assert mavutil.interpret_px4_mode(0, PX4_CUSTOM_MODE_OF[mode]) == px4_name
    assert mode_from_custom(custom_mode_of(mode, Autopilot.PX4), Autopilot.PX4) == mode


def test_px4_hold_and_offboard_encodings():
    assert PX4_CUSTOM_MODE_OF[FlightMode.OFFBOARD] == 6 << 16
    assert PX4_CUSTOM_MODE_OF[FlightMode.HOLD] == 4 << 16 | 3 << 24


def test_copter_modes_match_pymavlink():
    for member in CopterMode:
        assert mavutil.mode_mapping_acm[member.value] == member.name
    for mode, number in COPTER_MODE_OF.items():
        assert (
            mode_from_custom(custom_mode_of(mode, Autopilot.ARDUPILOTMEGA), Autopilot.ARDUPILOTMEGA)
            == mode
        )
        assert custom_mode_of(mode, Autopilot.ARDUPILOTMEGA) == number
    assert COPTER_MODE_OF[FlightMode.OFFBOARD] == 4 and COPTER_MODE_OF[FlightMode.HOLD] == 5


@given(main=st.integers(0, 255), sub=st.integers(0, 255))
def test_px4_custom_mode_round_trip(main, sub):
    assert px4_split_custom_mode(px4_custom_mode(main, sub)) == (main, sub)


def test_px4_sub_mode_matters_only_under_auto():
    posctl = px4_custom_mode(3, 7)
    assert mode_from_custom(posctl, Autopilot.PX4) == FlightMode.POSITION
    assert mode_from_custom(px4_custom_mode(4, 4), Autopilot.PX4) is None  # AUTO.MISSION
    assert mode_from_custom(12345, Autopilot.ARDUPILOTMEGA) is None


def test_base_mode_flags():
    armed = base_mode(armed=True, mode=FlightMode.OFFBOARD)
    assert armed & ModeFlag.CUSTOM_MODE_ENABLED and armed & ModeFlag.SAFETY_ARMED
    assert not base_mode(armed=False, mode=FlightMode.HOLD) & ModeFlag.SAFETY_ARMED


finite = st.floats(-50.0, 50.0, allow_nan=False)
heading = st.floats(-math.pi, math.pi, allow_nan=False)


@given(speed=finite, yaw_rate=finite, heading_rad=heading, frame=st.sampled_from(list(Frame)))
def test_unicycle_setpoint_round_trip(speed, yaw_rate, heading_rad, frame):
    sp = encode_setpoint(speed, yaw_rate, frame=frame, heading_rad=heading_rad, climb_rate_m_s=0.5)
    assert sp.type_mask == TypeMask.VELOCITY_YAW_RATE
    demand = decode_setpoint(sp, heading_rad=heading_rad, yaw_gain_1_s=1.0)
    assert isinstance(demand, UnicycleDemand)
    assert demand.speed_m_s == pytest.approx(speed, abs=1e-9)
    assert demand.yaw_rate_rad_s == yaw_rate
    assert demand.climb_rate_m_s == 0.5


@given(vx=finite, vy=finite, heading_rad=heading)
def test_lateral_velocity_is_dropped(vx, vy, heading_rad):
    local = SetpointFields(int(Frame.LOCAL_NED), int(TypeMask.VELOCITY_YAW_RATE), vx, vy)
    body = SetpointFields(int(Frame.BODY_NED), int(TypeMask.VELOCITY_YAW_RATE), vx, vy)
    along = vx * math.cos(heading_rad) + vy * math.sin(heading_rad)
    assert decode_setpoint(local, heading_rad=heading_rad, yaw_gain_1_s=1.0).speed_m_s == (
        pytest.approx(along, abs=1e-9)
    )
    assert decode_setpoint(body, heading_rad=heading_rad, yaw_gain_1_s=1.0).speed_m_s == vx


@given(target=heading, heading_rad=heading)
def test_yaw_setpoints_turn_the_short_way(target, heading_rad):
    sp = SetpointFields(int(Frame.LOCAL_NED), int(TypeMask.VELOCITY_YAW), yaw_rad=target)
    rate = decode_setpoint(sp, heading_rad=heading_rad, yaw_gain_1_s=2.0).yaw_rate_rad_s
    assert abs(rate) <= 2.0 * math.pi + 1e-9
    assert rate == pytest.approx(2.0 * wrap_pi(target - heading_rad), abs=1e-9)
    relative = SetpointFields(int(Frame.BODY_NED), int(TypeMask.VELOCITY_YAW), yaw_rad=target)
    rel = decode_setpoint(
        relative, heading_rad=heading_rad, yaw_gain_1_s=2.0, yaw_relative_in_body=True
    )
    assert rel.yaw_rate_rad_s == pytest.approx(2.0 * wrap_pi(target), abs=1e-9)


@pytest.mark.parametrize(
    ("sp", "why"),
    [
        (SetpointFields(7, 1479, 1.0), Rejection.UNSUPPORTED_FRAME),
        (SetpointFields(1, 3527, 1.0), Rejection.UNSUPPORTED_MASK),
        (SetpointFields(8, 1479, math.nan), Rejection.NON_FINITE),
        (SetpointFields(8, 1479, 1.0, yaw_rate_rad_s=math.inf), Rejection.NON_FINITE),
        (SetpointFields(8, 1479, 1e20), Rejection.IMPLAUSIBLE),
        (SetpointFields(8, 2503, 1.0, yaw_rad=100.0), Rejection.IMPLAUSIBLE),
        (SetpointFields(8, 3576, x_m=1.0), Rejection.UNSUPPORTED_FRAME),
        (SetpointFields(1, 3576, z_m=math.nan), Rejection.NON_FINITE),
        (SetpointFields(1, 3576, y_m=2e5), Rejection.IMPLAUSIBLE),
    ],
)
def test_bad_setpoints_are_rejected_with_a_reason(sp, why):
    assert decode_setpoint(sp, heading_rad=0.0, yaw_gain_1_s=1.0) == why


@given(north=finite, east=finite, down=finite)
def test_position_setpoint_round_trip_on_the_wire(north, east, down):
    """Mask 3576 (ArduPilot's and PX4's position-only mask) carries the point in x, y, z."""
    sp = encode_position_setpoint(north, east, down)
    assert sp.type_mask == TypeMask.POSITION == 3576 and sp.frame == Frame.LOCAL_NED
    args = setpoint_message_args(sp, time_boot_ms=7, target_system=1)
    mav = M.MAVLink(None, srcSystem=255)
    msg = mav.decode(bytearray(mav.set_position_target_local_ned_encode(*args).pack(mav)))
    assert (msg.x, msg.y, msg.z, msg.type_mask) == (
        pytest.approx(north, rel=1e-6, abs=1e-5),
        pytest.approx(east, rel=1e-6, abs=1e-5),
        pytest.approx(down, rel=1e-6, abs=1e-5),
        3576,
    )
    # Velocity and yaw are unused: NaN there (as MAVSDK sends) is not checked.
    sp = SetpointFields(1, 3576, vx_m_s=math.nan, yaw_rate_rad_s=math.nan, x_m=north, z_m=down)
    demand = decode_setpoint(sp, heading_rad=1.0, yaw_gain_1_s=1.0)
    assert demand == PositionDemand(north_m=north, east_m=0.0, altitude_m=-down)


def test_unused_fields_are_not_checked():
    # yaw is ignored with mask 1479: NaN there is fine (MAVSDK sends NaN in unused fields).
    sp = SetpointFields(8, 1479, 1.0, yaw_rad=math.nan)
    assert isinstance(decode_setpoint(sp, heading_rad=0.0, yaw_gain_1_s=1.0), UnicycleDemand)


@given(
    north=st.floats(-20_000, 20_000),
    east=st.floats(-20_000, 20_000),
    lat0=st.floats(-80, 80),
    lon0=st.floats(-179, 179),
)
def test_geodetic_round_trip(north, east, lat0, lon0):
    lat, lon = geodetic_from_ned(north, east, home_lat_deg=lat0, home_lon_deg=lon0)
    back = ned_from_geodetic(lat, lon, home_lat_deg=lat0, home_lon_deg=lon0)
    assert back == (pytest.approx(north, abs=1e-6), pytest.approx(east, abs=1e-6))


def test_geodetic_scale():
    lat, lon = geodetic_from_ned(1000.0, 0.0, home_lat_deg=47.0, home_lon_deg=8.0)
    assert (lat - 47.0) == pytest.approx(math.degrees(1000.0 / EARTH_RADIUS_M), rel=1e-9)
    assert lon == pytest.approx(8.0, abs=1e-12)
    _, lon = geodetic_from_ned(0.0, 1000.0, home_lat_deg=60.0, home_lon_deg=8.0)
    assert (lon - 8.0) == pytest.approx(2 * math.degrees(1000.0 / EARTH_RADIUS_M), rel=1e-6)


def test_modes_are_named_as_each_autopilot_names_them():
    from fleetmpc.onboard.autopilot_link import LinkState
    from fleetmpc.protocol.mavlink_map import (
        Autopilot,
        CopterMode,
        FlightMode,
        Px4AutoSubMode,
        Px4MainMode,
        custom_mode_name,
        custom_mode_of,
        flight_mode_name,
        px4_custom_mode,
    )

    ap, px4 = Autopilot.ARDUPILOTMEGA, Autopilot.PX4
    assert flight_mode_name(FlightMode.OFFBOARD, ap) == "GUIDED"
    assert flight_mode_name(FlightMode.HOLD, ap) == "LOITER"
    assert flight_mode_name(FlightMode.POSITION, ap) == "POSHOLD"
    assert flight_mode_name(FlightMode.HOLD, px4) == "HOLD"
    assert custom_mode_name(int(CopterMode.RTL), ap) == "RTL"
    assert custom_mode_name(99, ap) == "mode 99"
    assert custom_mode_name(custom_mode_of(FlightMode.OFFBOARD, px4), px4) == "OFFBOARD"
    rtl = px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.RTL)
    assert custom_mode_name(rtl, px4) == "AUTO.RTL"
    assert custom_mode_name(px4_custom_mode(Px4MainMode.ALTCTL), px4) == "ALTCTL"
    # The agent's state, and so its final report: LOITER, not HOLD, for an ArduCopter.
    loiter = LinkState(autopilot=ap, mode=FlightMode.HOLD, custom_mode=int(CopterMode.LOITER))
    assert loiter.mode_name == "LOITER"
    assert LinkState(autopilot=ap, mode=FlightMode.HOLD).mode_name == "LOITER"  # (the fake)
    assert LinkState(autopilot=ap, custom_mode=int(CopterMode.RTL)).mode_name == "RTL"
    assert LinkState().mode_name is None
