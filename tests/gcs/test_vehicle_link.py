"""When the ground station counts a vehicle as engaged (the fleet epoch waits for all)."""

from fleetmpc.gcs.station import VehicleLink
from fleetmpc.protocol.mavlink_map import Autopilot, FlightMode, LandedState


def _link(autopilot: Autopilot, landed: LandedState | None, *, armed=True) -> VehicleLink:
    return VehicleLink(
        autopilot=autopilot, mode=FlightMode.OFFBOARD, armed=armed, landed_state=landed
    )


def test_an_ardupilot_vehicle_is_engaged_once_its_takeoff_is_over():
    ap = Autopilot.ARDUPILOTMEGA
    assert not _link(ap, LandedState.ON_GROUND).engaged  # GUIDED and armed, takeoff not begun
    assert not _link(ap, LandedState.TAKEOFF).engaged  # climbing: flies no guided target
    assert _link(ap, LandedState.IN_AIR).engaged
    assert _link(ap, None).engaged  # reports no landed state: taken at its word
    assert not _link(ap, LandedState.IN_AIR, armed=False).engaged


def test_a_px4_vehicle_flies_offboard_from_the_ground_but_not_through_a_takeoff():
    px4 = Autopilot.PX4
    assert _link(px4, LandedState.ON_GROUND).engaged
    assert _link(px4, LandedState.IN_AIR).engaged
    assert not _link(px4, LandedState.TAKEOFF).engaged
