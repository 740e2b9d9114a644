"""FleetRunner on fakes: steps on the autopilot's clock, publishes, streams, never raises."""

import threading
import time

import numpy as np
import pytest

from gcs.lockstep import build_agents
from onboard.autopilot_link import FakeAutopilotLink
from onboard.core.errors import ConfigError
from onboard.planbus import InMemoryPlanBus, MemoryHubs
from onboard.runner import (
    ClockSync,
    FleetClock,
    FleetRunner,
    RunnerSettings,
    SetpointStreamer,
    gap_stats_ms,
)
from protocol.mavlink_map import FlightMode

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
    out = runner.tick(link.state())
    assert out.plan.stamp_ns == 600_000_000
    assert runner.overruns == 2  # the steps at 0.2 s and 0.4 s were skipped
    assert runner.tick(link.state()) is None  # nothing new before 0.8 s


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
    gaps = gap_stats_ms(streamer.send_times_ns)
    assert gaps["count"] > 20
    assert gaps["max"] < 100.0  # the stream never stalls behind the loop


def test_streamer_keeps_its_rate_while_the_loop_is_blocked() -> None:
    link = FakeAutopilotLink()
    streamer = SetpointStreamer(link, period_s=0.01)
    streamer.set_command(speed_m_s=1.0, yaw_rate_rad_s=0.1)
    streamer.start()
    time.sleep(0.5)  # the control loop could be stuck in a long step
    streamer.stop()
    gaps = gap_stats_ms(streamer.send_times_ns)
    assert 35 <= gaps["count"] <= 55
    assert gaps["p99"] < 30.0
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


def test_settings_are_validated() -> None:
    with pytest.raises(ConfigError, match="period_ns"):
        RunnerSettings(period_ns=0)
    with pytest.raises(ConfigError, match="warmup_ns"):
        RunnerSettings(period_ns=1, warmup_ns=-1)
    with pytest.raises(ConfigError, match="speed"):
        FleetClock(speed=0.0)
    with pytest.raises(ConfigError, match="period_s"):
        SetpointStreamer(FakeAutopilotLink(), period_s=1.0)
