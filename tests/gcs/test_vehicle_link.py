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
    assert not _link(ap, None).engaged  # no landed state yet: it is asked for one
    assert not _link(ap, LandedState.IN_AIR, armed=False).engaged


def test_a_px4_vehicle_flies_offboard_from_the_ground_but_not_through_a_takeoff():
    px4 = Autopilot.PX4
    assert _link(px4, LandedState.ON_GROUND).engaged
    assert _link(px4, LandedState.IN_AIR).engaged
    assert not _link(px4, LandedState.TAKEOFF).engaged


def test_a_vehicle_heard_without_positions_is_asked_for_its_streams():
    from pathlib import Path

    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.station import STREAMS_SILENT_WALL_S, GroundStation
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    gs = GroundStation(load_scenario(root / "scenarios" / "paper.toml"), speed=1.0, duration_s=5.0)
    mav = mavlink.MAVLink(None, srcSystem=2, srcComponent=1)
    beat = mav.heartbeat_encode(2, int(Autopilot.ARDUPILOTMEGA), 0, 0, 4)
    beat.pack(mav)  # (sets its source ids)
    gs.on_mavlink(beat, received_ns=0)
    assert gs.links_to_ask(1.0) == [2]  # heard, no position, no landed state: asked
    assert gs.links_to_ask(1.0 + 0.5 * STREAMS_SILENT_WALL_S) == []  # not again so soon
    state = mav.extended_sys_state_encode(0, int(LandedState.IN_AIR))
    state.pack(mav)
    gs.on_mavlink(state, received_ns=3 * 10**9)
    fix = mav.global_position_int_encode(3000, 473977420, 85455940, 0, 0, 0, 0, 0, 0)
    fix.pack(mav)
    gs.on_mavlink(fix, received_ns=3 * 10**9)
    assert gs.links_to_ask(3.5) == []  # positions and a landed state come: nothing to ask
    assert gs.links_to_ask(3.0 + STREAMS_SILENT_WALL_S + 0.1) == [2]  # they stopped


def test_a_px4_heard_for_the_first_time_is_told_what_to_stream_once():
    """A PX4 ground-station link streams ATTITUDE, VFR_HUD and more that the ground station
    does not read: each vehicle is asked, once, for what it reads and to stop the rest."""
    from pathlib import Path

    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.ground_station import GCS_STREAMS_US
    from fleetmpc.gcs.station import GroundStation
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    gs = GroundStation(load_scenario(root / "scenarios" / "paper.toml"), speed=1.0, duration_s=5.0)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = mav.heartbeat_encode(2, int(Autopilot.PX4), 0, 0, 4)
    beat.pack(mav)
    fix = mav.global_position_int_encode(300, 473977420, 85455940, 0, 0, 0, 0, 0, 0)
    fix.pack(mav)
    gs.on_mavlink(beat, received_ns=0)
    gs.on_mavlink(fix, received_ns=0)
    assert gs.links_to_ask(0.5) == [1]  # heard, streaming: asked all the same
    assert gs.links_to_ask(1.0) == []
    gs.on_mavlink(fix, received_ns=29 * 10**9)
    assert gs.links_to_ask(30.0) == []  # and, while its positions come, never again
    # GLOBAL_POSITION_INT, HIL_STATE_QUATERNION, WIND_COV, EXTENDED_SYS_STATE
    read = {33, 115, 231, 245}
    assert {m for m, us in GCS_STREAMS_US.items() if us > 0} == read
    assert {30, 74, 1, 32} <= {m for m, us in GCS_STREAMS_US.items() if us == -1}


def test_a_vehicle_that_sends_ground_truth_is_recorded_from_it_alone():
    """Once a vehicle sends a timed HIL_STATE_QUATERNION (a simulator's ground truth), its
    GLOBAL_POSITION_INT (its noisy estimate) no longer reaches the record; one that sends none
    is recorded from GLOBAL_POSITION_INT; an untimed one (PX4's own), or one timed beyond any
    boot time (a Unix time, which the message also allows), is not ground truth."""
    import math
    from pathlib import Path

    import numpy as np
    import pytest
    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.station import GroundStation
    from fleetmpc.protocol.local_frame import geodetic_from_ned
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    scenario = load_scenario(root / "scenarios" / "paper.toml")
    site = scenario.site
    gs = GroundStation(scenario, speed=1.0, duration_s=5.0)
    gs.set_epoch(0)

    def e7(north: float, east: float) -> tuple[int, int]:
        lat, lon = geodetic_from_ned(
            north, east, home_lat_deg=site.home_lat_deg, home_lon_deg=site.home_lon_deg
        )
        return round(lat * 1e7), round(lon * 1e7)

    yaw = 0.5
    quaternion = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    for k in range(3):
        t_ns = (k + 1) * 200_000_000  # (a time_usec of 0 is no time: PX4's)
        for vid in scenario.vehicle_ids:
            mav = mavlink.MAVLink(None, srcSystem=vid, srcComponent=1)
            truth_e7 = e7(10.0 * vid + k, 0.0)
            fix_e7 = e7(10.0 * vid + k + 0.05, 0.04)  # (the estimate: off by its noise)
            messages = [mav.global_position_int_encode(t_ns // 10**6, *fix_e7, 0, 0, 0, 0, 0, 0)]
            if vid != 3:  # vehicle 3 sends no ground truth; vehicle 2 one without a boot time
                timed = t_ns // 1000 if vid == 1 else (0, 1_764_800_000_000_000, 0)[k]
                truth = mav.hil_state_quaternion_encode(
                    timed, quaternion, 0, 0, 0, *truth_e7, 0, 0, 0, 0, 0, 0, 0, 0, 0
                )
                messages.insert(0, truth)
            for message in messages:
                message.pack(mav)
                gs.on_mavlink(message, received_ns=t_ns)
    rec = gs.live.record(4, first=1)
    assert rec.truth[:, 0, 0] == pytest.approx([10.0, 11.0, 12.0], abs=0.01)
    assert rec.truth[:, 0, 1] == pytest.approx([0.0, 0.0, 0.0], abs=0.01)
    assert rec.truth[:, 0, 2] == pytest.approx([yaw] * 3, abs=1e-6)
    for i in (1, 2):  # from GLOBAL_POSITION_INT
        assert rec.truth[:, i, 0] == pytest.approx(10.0 * (i + 1) + np.arange(3) + 0.05, abs=0.01)
        assert rec.truth[:, i, 1] == pytest.approx([0.04] * 3, abs=0.01)
    assert gs.metrics()["ground_truth"] == [1]
    metrics = gs.metrics()
    # The learned model is judged against the simulated truth only where there is one.
    assert [b["vehicle"] for b in metrics["beta_error"]] == [1]
    assert metrics["beta_error_without_truth"] == [2, 3]
    import re

    from fleetmpc.gcs.metrics import format_summary

    summary = format_summary(metrics)
    assert re.search(r"beta error UAV 1 +a_V", summary)
    for vid in (2, 3):
        assert re.search(rf"beta error UAV {vid} +unknown: no simulated truth", summary)


def test_each_autopilot_s_modes_are_named_as_it_names_them():
    """The status table and the events call ArduCopter's modes GUIDED and LOITER, PX4's
    OFFBOARD and HOLD, and name modes the profiles do not fly (RTL) rather than hide them."""
    from pathlib import Path

    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.station import GroundStation
    from fleetmpc.protocol.mavlink_map import CopterMode, base_mode, custom_mode_of
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    gs = GroundStation(load_scenario(root / "scenarios" / "paper.toml"), speed=1.0, duration_s=5.0)
    beats = [
        (1, Autopilot.PX4, custom_mode_of(FlightMode.OFFBOARD, Autopilot.PX4)),
        (2, Autopilot.ARDUPILOTMEGA, int(CopterMode.GUIDED)),
        (3, Autopilot.ARDUPILOTMEGA, int(CopterMode.LOITER)),
    ]
    for vid, autopilot, custom in beats:
        mav = mavlink.MAVLink(None, srcSystem=vid, srcComponent=1)
        flags = base_mode(armed=True, mode=FlightMode.OFFBOARD)
        beat = mav.heartbeat_encode(2, int(autopilot), flags, custom, 4)
        beat.pack(mav)
        gs.on_mavlink(beat, received_ns=0)
    modes = {v: s["mode"] for v, s in gs.status_snapshot("waiting")["vehicles"].items()}
    assert modes == {"1": "OFFBOARD", "2": "GUIDED", "3": "LOITER"}
    texts = [text for *_, text in gs._events]
    assert texts == ["UAV 1: OFFBOARD, armed", "UAV 2: GUIDED, armed", "UAV 3: LOITER, armed"]
    mav = mavlink.MAVLink(None, srcSystem=3, srcComponent=1)
    beat = mav.heartbeat_encode(2, int(Autopilot.ARDUPILOTMEGA), 0, int(CopterMode.RTL), 4)
    beat.pack(mav)
    gs.on_mavlink(beat, received_ns=0)
    assert gs.status_snapshot("waiting")["vehicles"]["3"]["mode"] == "RTL"


def test_the_true_wind_of_a_simulator_is_the_records_truth_and_a_real_autopilots_is_not():
    """WIND_COV from a vehicle that sends ground truth (our SITL's true wind) replaces the
    scenario's wind in the record's beta truth from the period it came on; WIND_COV from one
    that sends none (a real autopilot's estimate) is not a truth."""
    from pathlib import Path

    import pytest
    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.station import GroundStation
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    scenario = load_scenario(root / "scenarios" / "paper.toml")
    gs = GroundStation(scenario, speed=1.0, duration_s=5.0)
    gs.set_epoch(0)
    scripted = gs.live.record(4).beta_truth[:, :, 2:]
    for k in range(1, 4):
        t_ns = k * 200_000_000
        for vid in (1, 2):
            mav = mavlink.MAVLink(None, srcSystem=vid, srcComponent=1)
            messages = [mav.wind_cov_encode(t_ns // 1000, 0.1 * k, -0.2, 0, 0, 0, 0, 0, 0)]
            if vid == 1:  # vehicle 1 is a simulator: its ground truth comes first
                quaternion = [1.0, 0.0, 0.0, 0.0]
                messages.insert(
                    0,
                    mav.hil_state_quaternion_encode(
                        t_ns // 1000, quaternion, 0, 0, 0, 473977420, 85455940, 0, *[0] * 8
                    ),
                )
            for message in messages:
                message.pack(mav)
                gs.on_mavlink(message, received_ns=t_ns)
    wind = gs.live.record(4).beta_truth[:, :, 2:]
    assert wind[0, 0] == pytest.approx(scripted[0, 0])  # (before the first sample)
    assert wind[1:, 0, 0] == pytest.approx([0.1, 0.2, 0.3], abs=1e-6)
    assert wind[1:, 0, 1] == pytest.approx([-0.2] * 3, abs=1e-6)
    assert wind[:, 1:] == pytest.approx(scripted[:, 1:])  # vehicles 2 and 3: the scenario's


def test_following_another_target_the_figures_against_the_scenarios_target_are_not_judged():
    """A fleet that follows a MAVLink system (`up --target mavlink:...`) is not judged against
    the scenario's script: the summary says so instead of printing a distance to a target that
    was not there; the separation between the vehicles is still judged."""
    from pathlib import Path

    from pymavlink.dialects.v20 import common as mavlink

    from fleetmpc.gcs.metrics import NOT_JUDGED, TARGET_FIGURES, format_summary
    from fleetmpc.gcs.station import GroundStation
    from fleetmpc.scenario import load_scenario

    root = Path(__file__).resolve().parents[2]
    scenario = load_scenario(root / "scenarios" / "paper.toml")
    summaries = []
    for source in ("script", "mavlink:udpin:127.0.0.1:14590"):
        gs = GroundStation(scenario, speed=1.0, duration_s=1.0, target_source=source)
        gs.set_epoch(0)
        for k in range(1, 7):
            for vid in scenario.vehicle_ids:
                mav = mavlink.MAVLink(None, srcSystem=vid, srcComponent=1)
                fix = mav.global_position_int_encode(
                    k * 200, 473977420 + 1000 * vid, 85455940, 0, 0, 0, 0, 0, 0
                )
                fix.pack(mav)
                gs.on_mavlink(fix, received_ns=k * 200_000_000)
        metrics = gs.metrics()
        summaries.append(format_summary({**metrics, "periods_recorded": 6, "periods_expected": 6}))
        if source == "script":
            assert metrics["formation_rms_m"] > 0 and metrics["centre_distance_error_m"] > 0
        else:
            assert all(metrics[k] is None for k in TARGET_FIGURES)
        assert metrics["separation_error_m"] and metrics["min_separation_m"] > 0
    assert NOT_JUDGED not in summaries[0]
    assert f"formation RMS           {NOT_JUDGED}" in summaries[1]
