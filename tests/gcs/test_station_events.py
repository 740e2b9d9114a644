"""The ground station's events carry their own time: before the fleet clock starts, negative."""

from pymavlink.dialects.v20 import common as mavlink

from fleetmpc.gcs.station import GroundStation
from fleetmpc.gcs.telemetry import MemorySink, TargetFix
from fleetmpc.protocol.mavlink_map import Autopilot
from fleetmpc.protocol.messages import (
    TARGET_ID,
    StatusMessage,
    TargetObservation,
    TargetState,
    VehicleStatus,
)


def test_events_before_the_fleet_clock_carry_their_own_time(paper):
    """A mode change heard 3 wall seconds before the epoch of a x4 run is at -12 s of fleet
    time, not at 0; nothing goes out before the epoch is known."""
    gs = GroundStation(paper, speed=4.0, duration_s=5.0)
    sink = MemorySink()
    gs.open_sinks([sink])
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = mav.heartbeat_encode(2, int(Autopilot.PX4), 128 | 1, 0, 4)  # armed
    beat.pack(mav)
    wall_ns = 1_000_000_000_000
    gs.on_mavlink(beat, received_ns=wall_ns)
    gs.flush()
    assert sink.events == []  # no fleet clock yet: kept
    gs.set_epoch(wall_ns + 3_000_000_000)
    gs.flush()
    ((t_ns, level, text),) = sink.events
    assert t_ns == -12_000_000_000 and level == "INFO" and text.startswith("UAV 1:")
    gs.close_sinks()
    assert sink.run_end == {"periods_recorded": 0, "periods_expected": 26, "ground_truth": []}


def test_events_of_a_fleet_that_never_started_are_not_lost(paper):
    gs = GroundStation(paper, speed=1.0, duration_s=5.0)
    sink = MemorySink()
    gs.open_sinks([sink])
    gs.links[2].last_wall_s = 1.0
    gs.check_links(10.0)  # (silent for 9 s: lost)
    gs.close_sinks()
    ((t_ns, level, text),) = sink.events
    assert level == "WARN" and text == "UAV 2: no MAVLink for 3 s" and t_ns < 0


def test_target_observations_reach_the_recording_as_received(paper):
    """Each observation heard on the bus goes to the sinks once, at its own time and where it
    was, with or without periods to log; a state change of a vehicle's target is an event."""
    gs = GroundStation(paper, speed=1.0, duration_s=5.0)
    sink = MemorySink()
    gs.open_sinks([sink])
    gs.set_epoch(1_000_000_000_000)
    for seq, stamp_ns in enumerate((200_000_000, 400_000_000)):
        obs = TargetObservation(
            sender_id=TARGET_ID, seq=seq, stamp_ns=stamp_ns, north_m=5.0 + seq, east_m=-2.0
        )
        gs.inbox.put(obs)
    gs.flush()
    gs.flush()
    want = [TargetFix(200_000_000, 5.0, -2.0), TargetFix(400_000_000, 6.0, -2.0)]
    assert sink.observations == want
    status = VehicleStatus(target_state=TargetState.PREDICTING)
    gs.inbox.put(StatusMessage(sender_id=2, seq=0, stamp_ns=600_000_000, status=status))
    gs.flush()
    assert sink.events == [(600_000_000, "WARN", "UAV 2: target predicting")]
