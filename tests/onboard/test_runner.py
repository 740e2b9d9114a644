"""FleetRunner on fakes: steps on the autopilot's clock, publishes, streams, never raises."""

import dataclasses
import math
import threading
import time

import numpy as np
import pytest

from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHubs
from fleetmpc.clock import ClockSync, EpochMismatchError, FleetClock
from fleetmpc.errors import ConfigError
from fleetmpc.lockstep.flight import build_agents
from fleetmpc.onboard.fake_autopilot_link import FakeAutopilotLink
from fleetmpc.onboard.runner import FleetRunner, RunnerSettings
from fleetmpc.onboard.setpoints import SetpointStreamer, gap_stats_ms, wind_down
from fleetmpc.protocol.mavlink_map import FlightMode
from fleetmpc.protocol.messages import GROUND_STATION_ID

FLEET = "test"
TARGET_ID = 250


def _fleet(paper, hub):
    agents = build_agents(paper)
    links, buses, runners = [], [], []
    for agent, spec in zip(agents, paper.vehicles, strict=True):
        link = FakeAutopilotLink(system_id=spec.id, north_m=spec.initial[0], east_m=spec.initial[1])
        link.connect(timeout_s=0.1)
        link.engage(timeout_s=0.1)
        bus = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=spec.id)
        runners.append(
            FleetRunner(
                agent,
                link=link,
                bus=bus,
                settings=RunnerSettings(period_ns=paper.controller.period_ns, engage=False),
                clock=FleetClock(),
            )
        )
        links.append(link)
        buses.append(bus)
    return links, buses, runners


def test_runner_steps_once_per_period_on_the_autopilot_clock(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    links, buses, runners = _fleet(paper, hub)
    target = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=TARGET_ID)
    listener = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=None)
    period = paper.controller.period_ns
    stamps = []
    for k in range(60):  # telemetry every 50 ms, 3 s
        t_ns = k * 50_000_000
        if t_ns % period == 0:
            pos, _ = paper.target.state_at(t_ns * 1e-9)
            target.publish_target(stamp_ns=t_ns, north_m=float(pos[0]), east_m=float(pos[1]))
        for link, runner in zip(links, runners, strict=True):
            out = runner.tick(link.state())
            if out is not None:
                link.send_setpoint(speed_m_s=out.command[0], yaw_rate_rad_s=out.command[1])
                if runner is runners[0]:
                    stamps.append(out.plan.stamp_ns)
            link.advance(50_000_000, steps=5)
    assert stamps == [k * period for k in range(len(stamps))]
    assert len(stamps) == 15
    assert all(r.steps == 15 and r.overruns == 0 and r.step_errors == 0 for r in runners)
    plans = listener.latest_plans(stamps[-1], period)
    assert sorted(plans) == [1, 2, 3]
    statuses = listener.latest_statuses(stamps[-1], period)
    assert sorted(statuses) == [1, 2, 3]
    # Neighbours' plans reached the agents: every formation term is in use at the end.
    assert runners[0].last_output.formation_terms == 2
    assert np.all(np.isfinite(runners[0].last_output.slot_m))


def test_runner_counts_overruns_and_stays_on_period_boundaries(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    links, _, runners = _fleet(paper, hub)
    link, runner = links[0], runners[0]
    assert runner.tick(link.state()).plan.stamp_ns == 0
    link.advance(730_000_000)  # a stall of more than three periods
    inputs = []
    step = runner.agent.step
    runner.agent.step = lambda inp: (inputs.append(inp), step(inp))[1]
    out = runner.tick(link.state())
    assert out.plan.stamp_ns == 600_000_000
    assert runner.overruns == 2  # the steps at 0.2 s and 0.4 s were skipped
    # ...and the step at 0.6 s runs 0.13 s late: the agent is told, and it is counted.
    assert inputs[-1].late_s == pytest.approx(0.13)
    assert runner.late_steps == 1 and runner.max_late_ns == 130_000_000
    assert runner.summary()["max_late_ms"] == pytest.approx(130.0)
    assert runner.tick(link.state()) is None  # nothing new before 0.8 s


def test_a_step_on_telemetry_read_late_is_as_late_as_the_host_clock_says(paper) -> None:
    """Telemetry handed over 1.5 s of fleet time after it was sent (the link's reader starved of
    CPU) says the step is on time; the host's clock says how late it runs, and the agent is told
    that (at x10, so that 1.5 s of fleet time is 0.15 s of waiting)."""
    spec = paper.vehicles[0]
    link = FakeAutopilotLink(system_id=spec.id, north_m=spec.initial[0], east_m=spec.initial[1])
    link.connect(timeout_s=0.1)
    link.engage(timeout_s=0.1)
    period = paper.controller.period_ns
    runner = FleetRunner(
        build_agents(paper)[0],
        link=link,
        bus=InMemoryPlanBus(MemoryHubs().hub(FLEET), fleet=FLEET, vehicle_id=spec.id),
        settings=RunnerSettings(period_ns=period, engage=False),
        clock=FleetClock(epoch_ns=time.time_ns(), speed=10.0),
    )
    inputs = []
    step = runner.agent.step
    runner.agent.step = lambda inp: (inputs.append(inp), step(inp))[1]
    runner.tick(dataclasses.replace(link.state(), received_ns=time.time_ns()))  # read at once
    assert inputs[-1].stamp_ns == 0 and inputs[-1].late_s < 1.0
    link.advance(period)
    time.sleep(0.17)  # fleet time 1.7 s (or more) when the period's telemetry is read
    runner.tick(dataclasses.replace(link.state(), received_ns=time.time_ns()))
    assert inputs[-1].stamp_ns == period  # (by the telemetry's own time: on time)
    assert inputs[-1].late_s >= 1.5
    assert runner.late_steps >= 1 and runner.max_late_ns >= 1_500_000_000


def test_a_failing_step_never_leaves_the_loop(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    links, _, runners = _fleet(paper, hub)

    def explode(_inp):
        raise RuntimeError("boom")

    runners[0].agent.step = explode
    assert runners[0].tick(links[0].state()) is None
    assert runners[0].step_errors == 1
    assert "boom" in runners[0].last_status


def test_run_streams_engages_and_stops_at_the_requested_time(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    agent = build_agents(paper)[0]
    link = FakeAutopilotLink(system_id=1)
    link.connect(timeout_s=0.1)
    bus = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1)
    listener = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=None)
    settings = RunnerSettings(
        period_ns=paper.controller.period_ns, warmup_ns=1_000_000_000, stop_at_fleet_ns=3 * 10**9
    )
    runner = FleetRunner(agent, link=link, bus=bus, settings=settings, clock=FleetClock())
    streamer = SetpointStreamer(link, period_s=0.005)
    stop = threading.Event()

    def autopilot() -> None:  # the fake's clock runs at 20x real time
        while not stop.is_set():
            link.advance(100_000_000, steps=2)
            time.sleep(0.005)

    flying = threading.Thread(target=autopilot, daemon=True)
    streamer.start()
    flying.start()
    try:
        runner.run(stop, streamer)
    finally:
        stop.set()
        streamer.stop()
        flying.join(timeout=1.0)
    assert runner.engaged and runner.engage_attempted
    assert link.state().mode == FlightMode.OFFBOARD
    assert 14 <= runner.steps <= 16
    assert link.hold_point is None, "the steps' velocities replace the hold"
    gaps = gap_stats_ms(streamer.send_times_ns)
    assert gaps["count"] > 20
    assert gaps["max"] < 100.0  # the stream never stalls behind the loop
    # The status carries the stream's rate (the stream is younger than the 1 s window here, so
    # below its 200 Hz), and the plan the step's time.
    last = runner.next_step_ns - settings.period_ns
    status = listener.latest_statuses(last, 0)[1].status
    assert 0.0 < status.setpoint_rate_hz <= 205.0, status.setpoint_rate_hz
    plan = listener.latest_plan_messages(last, 0)[1]
    assert 0 < plan.status.solve_time_us < 1_000_000


def test_until_the_epoch_the_vehicle_holds_where_the_runner_found_it(paper) -> None:
    """Engaged but waiting for the fleet epoch, the agent streams position setpoints at the
    pose it started from (the autopilot holds it against the wind). Once steps run, velocities
    replace them (`test_run_streams_engages_and_stops_at_the_requested_time`)."""
    hub = MemoryHubs().hub(FLEET)
    link = FakeAutopilotLink(system_id=1, north_m=3.0, east_m=-4.0)
    link.connect(timeout_s=0.1)
    bus = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1)
    clock = FleetClock(awaiting_epoch=True)  # and none is announced
    settings = RunnerSettings(period_ns=paper.controller.period_ns, warmup_ns=500_000_000)
    runner = FleetRunner(build_agents(paper)[0], link=link, bus=bus, settings=settings, clock=clock)
    streamer = SetpointStreamer(link, period_s=0.005)
    stop = threading.Event()

    def autopilot() -> None:
        while not stop.is_set():
            link.advance(50_000_000, steps=2)
            time.sleep(0.005)

    threads = [
        threading.Thread(target=autopilot),
        threading.Thread(target=runner.run, args=(stop, streamer)),
    ]
    streamer.start()
    for thread in threads:
        thread.start()
    try:
        deadline = time.monotonic() + 10.0
        while not runner.engaged and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
        assert runner.engaged and runner.steps == 0
        assert link.hold_point == (3.0, -4.0, 0.0)
        assert link.state().mode == FlightMode.OFFBOARD
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=2.0)
        streamer.stop()


def test_setpoint_rate_counts_the_sends_of_the_last_window() -> None:
    now = [10_000_000_000]
    streamer = SetpointStreamer(FakeAutopilotLink(), period_s=0.01, monotonic_ns=lambda: now[0])
    streamer.send_times_ns.extend(range(8_000_000_000, 10_000_000_001, 10_000_000))  # 100 Hz
    assert streamer.rate_hz(window_ns=1_000_000_000) == 100.0
    assert streamer.rate_hz(window_ns=250_000_000) == 100.0
    now[0] += 500_000_000  # the stream stopped half a second ago
    assert streamer.rate_hz(window_ns=1_000_000_000) == 50.0
    assert streamer.rate_hz(window_ns=250_000_000) == 0.0
    with pytest.raises(ConfigError):
        streamer.rate_hz(window_ns=0)


def test_streamer_keeps_its_rate_while_the_loop_is_blocked() -> None:
    link = FakeAutopilotLink()
    streamer = SetpointStreamer(link, period_s=0.01)
    streamer.set_command(speed_m_s=1.0, yaw_rate_rad_s=0.1)
    streamer.start()
    time.sleep(0.5)  # the control loop could be stuck in a long step
    streamer.stop()
    gaps = gap_stats_ms(streamer.send_times_ns)
    # 50 sends at 100 Hz; a loaded machine may delay the streamer's thread by some periods, but
    # it keeps sending through the whole blocked step (a stalled streamer leaves a gap of it).
    assert 20 <= gaps["count"] <= 55
    assert gaps["p99"] < 100.0
    assert link.command == (1.0, 0.1)


def test_clock_sync_takes_the_minimum_offset() -> None:
    clock = FleetClock(epoch_ns=1_000_000_000_000, speed=4.0)
    sync = ClockSync(clock)
    assert sync.fleet_ns(0) is None
    # The autopilot booted 2 s wall before the epoch: boot time = fleet time + 8 s simulated.
    for latency_ns, boot_ns in ((3_000_000, 9_000_000_000), (500_000, 10_000_000_000)):
        wall = clock.epoch_ns + (boot_ns - 8_000_000_000) // 4 + latency_ns
        sync.update(time_boot_ns=boot_ns, received_wall_ns=wall)
    assert sync.offset_ns == -8_000_000_000 + 4 * 500_000
    assert sync.fleet_ns(12_000_000_000) == 4_000_000_000 + 2_000_000
    assert ClockSync(FleetClock()).fleet_ns(5) == 5  # no epoch: fleet time = autopilot time


def test_clock_sync_follows_an_autopilot_clock_that_runs_slow() -> None:
    """PX4's SIH runs about 1 % slower than the wall clock: over a minute its boot time falls
    0.6 s behind. The offset follows it within the drift over the filter's window, where an
    all-time minimum would stay at the first sample's."""
    clock = FleetClock(epoch_ns=EPOCH_NS, speed=1.0)
    sync = ClockSync(clock)
    rate = 0.99
    for k in range(60 * 30):  # 30 Hz for 60 s; latency 1 ms, and 20 ms on every tenth
        wall_since_ns = k * 1_000_000_000 // 30
        latency_ns = 20_000_000 if k % 10 == 0 else 1_000_000
        boot_ns = round(wall_since_ns * rate)
        sync.update(time_boot_ns=boot_ns, received_wall_ns=EPOCH_NS + wall_since_ns + latency_ns)
    true_offset_ns = wall_since_ns - boot_ns
    drift_over_window_ns = (1 - rate) * ClockSync.WINDOW_NS
    assert true_offset_ns == pytest.approx(600_000_000, rel=0.01)
    assert true_offset_ns - drift_over_window_ns <= sync.offset_ns <= true_offset_ns + 1_000_000


def test_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match="period_ns"):
        RunnerSettings(period_ns=0)
    with pytest.raises(ConfigError, match="warmup_ns"):
        RunnerSettings(period_ns=1, warmup_ns=-1)
    with pytest.raises(ConfigError, match="speed"):
        FleetClock(speed=0.0)
    with pytest.raises(ConfigError, match="period_s"):
        SetpointStreamer(FakeAutopilotLink(), period_s=1.0)


EPOCH_NS = 1_700_000_000_000_000_000


def test_an_awaited_epoch_counts_once_and_only_at_the_clock_speed() -> None:
    clock = FleetClock(speed=4.0, awaiting_epoch=True)
    assert clock.uses_epoch and not clock.ready
    assert clock.epoch_ns is None and clock.fleet_ns(EPOCH_NS) is None
    with pytest.raises(EpochMismatchError) as info:
        clock.set_epoch(EPOCH_NS, speed=2.0)
    assert info.value.field == "speed" and "x2" in str(info.value) and "x4" in str(info.value)
    assert not clock.ready  # a refused announcement changes nothing
    assert clock.set_epoch(EPOCH_NS, speed=4.0) is True
    assert clock.ready and clock.epoch_ns == EPOCH_NS
    assert clock.fleet_ns(EPOCH_NS + 250_000_000) == 1_000_000_000
    # Only the first announcement counts: fleet time never jumps.
    assert clock.set_epoch(EPOCH_NS + 10**9, speed=4.0) is False
    assert clock.epoch_ns == EPOCH_NS
    with pytest.raises(EpochMismatchError):
        clock.set_epoch(EPOCH_NS, speed=4.5)
    with pytest.raises(ConfigError) as info:
        FleetClock(epoch_ns=EPOCH_NS, awaiting_epoch=True)
    assert info.value.field == "epoch_ns"
    with pytest.raises(ConfigError) as info:
        FleetClock(awaiting_epoch=True).set_epoch(1.5e18, speed=1.0)
    assert info.value.field == "epoch_ns"


def test_clock_sync_uses_the_samples_taken_before_a_late_epoch() -> None:
    clock = FleetClock(speed=4.0, awaiting_epoch=True)
    sync = ClockSync(clock)
    # The autopilot booted 3 s wall before the epoch; samples arrive with 1..3 ms latency.
    for k, latency_ns in enumerate((3_000_000, 1_000_000, 2_000_000)):
        boot_ns = 1_000_000_000 + k * 100_000_000
        wall = EPOCH_NS - 3_000_000_000 + boot_ns // 4 + latency_ns
        sync.update(time_boot_ns=boot_ns, received_wall_ns=wall)
    assert sync.samples == 3 and sync.offset_ns is None and sync.fleet_ns(0) is None
    clock.set_epoch(EPOCH_NS, speed=4.0)
    assert sync.offset_ns == -12_000_000_000 + 4 * 1_000_000


def _awaiting_runner(paper, hub):
    agent = build_agents(paper)[0]
    link = FakeAutopilotLink(system_id=1)
    link.connect(timeout_s=0.1)
    logged: list[str] = []
    runner = FleetRunner(
        agent,
        link=link,
        bus=InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=1),
        settings=RunnerSettings(period_ns=paper.controller.period_ns, engage=False),
        clock=FleetClock(speed=4.0, awaiting_epoch=True),
        log=logged.append,
    )
    return runner, link, logged


def test_runner_adopts_the_first_announced_epoch_and_ignores_others(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    runner, link, logged = _awaiting_runner(paper, hub)
    gcs = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=GROUND_STATION_ID)
    runner.poll_epoch()
    assert not runner.sync.clock.ready and runner.failure is None
    assert runner.tick(link.state()) is None  # no fleet time yet: no step
    gcs.publish_epoch(epoch_ns=EPOCH_NS, speed=4.0)
    runner.poll_epoch()
    assert runner.sync.clock.epoch_ns == EPOCH_NS and runner.epoch_received_wall_ns is not None
    gcs.publish_epoch(epoch_ns=EPOCH_NS + 5 * 10**9, speed=4.0)
    runner.poll_epoch()
    runner.poll_epoch()
    assert runner.sync.clock.epoch_ns == EPOCH_NS
    assert sum("ignoring another fleet epoch" in line for line in logged) == 1, logged
    assert runner.failure is None


def test_an_epoch_at_another_speed_stops_the_run(paper) -> None:
    hub = MemoryHubs().hub(FLEET)
    runner, link, logged = _awaiting_runner(paper, hub)
    InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=GROUND_STATION_ID).publish_epoch(
        epoch_ns=EPOCH_NS, speed=2.0
    )
    streamer = SetpointStreamer(link, period_s=0.01)
    stop = threading.Event()
    done = threading.Thread(target=runner.run, args=(stop, streamer), daemon=True)
    done.start()
    done.join(timeout=5.0)
    stop.set()
    assert not done.is_alive()  # the run ended by itself, without telemetry or a stop request
    assert runner.failure is not None and "x2" in runner.failure and "x4" in runner.failure
    assert not runner.sync.clock.ready and runner.steps == 0
    assert any(line.startswith("error: speed") for line in logged), logged
    assert runner.summary()["failure"] == runner.failure


def test_winding_down_leaves_the_vehicle_holding_where_it_is() -> None:
    """The last setpoints are a point where the vehicle was, not its last velocity, and an
    engaged vehicle is asked to HOLD; without a pose the stream falls back to zero velocity."""
    link = FakeAutopilotLink(north_m=3.0, east_m=-4.0)
    link.connect(timeout_s=0.1)
    streamer = SetpointStreamer(link, period_s=0.005)
    streamer.set_command(speed_m_s=1.5, yaw_rate_rad_s=0.2)
    streamer.start()
    wind_down(link, streamer, engaged=True, settle_s=0.05)
    assert link.hold_point == (3.0, -4.0, 0.0) and link.command == (0.0, 0.0)
    assert link.hold_requests == 1
    sent = link.setpoints_sent
    time.sleep(0.03)
    assert link.setpoints_sent == sent  # the stream has stopped

    class NoPose(FakeAutopilotLink):
        def state(self):
            return dataclasses.replace(super().state(), north_m=math.nan)

    link = NoPose()
    link.connect(timeout_s=0.1)
    streamer = SetpointStreamer(link, period_s=0.005)
    streamer.set_command(speed_m_s=1.5, yaw_rate_rad_s=0.2)
    streamer.start()
    wind_down(link, streamer, engaged=False, settle_s=0.05)
    assert link.hold_point is None and link.command == (0.0, 0.0)
    assert link.hold_requests == 0


def test_a_held_vehicle_publishes_where_it_holds(paper) -> None:
    """Once its autopilot holds it (setpoints stopped, so the fake falls back to HOLD as PX4
    does), a vehicle's plan is its pose over the whole horizon: its neighbours plan against
    what it really does, not the motion its agent would have commanded."""
    hub = MemoryHubs().hub(FLEET)
    links, _, runners = _fleet(paper, hub)
    listener = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=None)
    target = InMemoryPlanBus(hub, fleet=FLEET, vehicle_id=TARGET_ID)
    link, runner = links[0], runners[0]
    period = paper.controller.period_ns
    stamp = None
    for k in range(40):  # telemetry every 50 ms; no setpoints reach vehicle 1 after 0.5 s
        t_ns = k * 50_000_000
        if t_ns % period == 0:
            pos, _ = paper.target.state_at(t_ns * 1e-9)
            target.publish_target(stamp_ns=t_ns, north_m=float(pos[0]), east_m=float(pos[1]))
        out = runner.tick(link.state())
        if out is not None:
            stamp = out.plan.stamp_ns
            if t_ns < 500_000_000:
                link.send_setpoint(speed_m_s=out.command[0], yaw_rate_rad_s=out.command[1])
        link.advance(50_000_000, steps=5)
    state = link.state()
    assert state.mode == FlightMode.HOLD
    plan = listener.latest_plans(stamp, period)[1]
    np.testing.assert_array_equal(
        plan.states[:, :2], np.tile([state.north_m, state.east_m], (6, 1))
    )
    assert not plan.inputs.any()
