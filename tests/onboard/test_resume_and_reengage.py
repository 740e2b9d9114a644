"""After a stall of the agent itself (a frozen or late process): the setpoint stream's longest
recent gap, the agent restarting its state filter when periods were missed, and the runner
taking its vehicle back from the autopilot's failsafe only when its own gap caused it.

Every clock here is driven by hand (the streamer's `monotonic_ns`, the fake autopilot's boot
time, the agent's stamps); the runner's loop runs on a link whose `wait_state` plays a script,
so nothing waits for real time.
"""

import threading

import numpy as np
import pytest

from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHubs
from fleetmpc.clock import FleetClock
from fleetmpc.lockstep.flight import build_agents
from fleetmpc.onboard.core.agent import AgentInput
from fleetmpc.onboard.core.unicycle import NOMINAL_BETA, advance
from fleetmpc.onboard.fake_autopilot_link import FakeAutopilotLink
from fleetmpc.onboard.runner import FleetRunner, RunnerSettings
from fleetmpc.onboard.setpoints import SetpointStreamer
from fleetmpc.protocol.mavlink_map import FlightMode

FLEET = "test"
S = 1_000_000_000
MS = 1_000_000


# SetpointStreamer.longest_gap_ns ----------------------------------------------------------


def streamer_at(now: list[int], link: FakeAutopilotLink | None = None) -> SetpointStreamer:
    """A streamer (never started) whose clock reads `now[0]`."""
    return SetpointStreamer(link or FakeAutopilotLink(), period_s=0.01, monotonic_ns=lambda: now[0])


def test_longest_gap_is_zero_before_any_send() -> None:
    now = [50 * S]
    streamer = streamer_at(now)
    assert streamer.longest_gap_ns(window_ns=5 * S) == 0
    now[0] += 100 * S  # however long it has been
    assert streamer.longest_gap_ns(window_ns=5 * S) == 0


def test_longest_gap_of_a_steady_stream_is_its_period() -> None:
    now = [10 * S]
    streamer = streamer_at(now)
    streamer.send_times_ns.extend(range(5 * S, 10 * S + 1, 10 * MS))  # 100 Hz up to now
    assert streamer.longest_gap_ns(window_ns=S) == 10 * MS
    now[0] += 3 * MS  # 3 ms since the last send: shorter than the stream's period
    assert streamer.longest_gap_ns(window_ns=S) == 10 * MS


def test_longest_gap_finds_the_longest_gap_inside_the_window() -> None:
    now = [20 * S]
    streamer = streamer_at(now)
    times = list(range(10 * S, 12 * S, 10 * MS))  # 100 Hz to 12 s...
    times += list(range(14 * S, 16 * S, 10 * MS))  # ...a 2.01 s gap, 100 Hz to 16 s...
    times += list(range(16_700 * MS, 20 * S + 1, 10 * MS))  # ...a 0.71 s gap, 100 Hz to now
    streamer.send_times_ns.extend(times)
    assert streamer.longest_gap_ns(window_ns=5 * S) == 710 * MS  # the 2 s gap ended 6 s ago
    assert streamer.longest_gap_ns(window_ns=10 * S) == 2_010 * MS
    assert streamer.longest_gap_ns(window_ns=2 * S) == 10 * MS  # both gaps are older
    # A gap that started before the window and ended inside it counts whole; one that ended
    # as the window starts does not.
    assert streamer.longest_gap_ns(window_ns=6_500 * MS) == 2_010 * MS
    assert streamer.longest_gap_ns(window_ns=6 * S) == 710 * MS
    assert streamer.longest_gap_ns(window_ns=3_400 * MS) == 710 * MS
    # A window reaching before the first send: every gap of the stream counts.
    assert streamer.longest_gap_ns(window_ns=100 * S) == 2_010 * MS


def test_longest_gap_counts_the_time_since_the_last_send() -> None:
    now = [10 * S]
    streamer = streamer_at(now)
    streamer.send_times_ns.extend(range(8 * S, 10 * S + 1, 10 * MS))
    now[0] += 800 * MS  # the stream stopped 0.8 s ago (its thread is stalled)
    assert streamer.longest_gap_ns(window_ns=5 * S) == 800 * MS
    now[0] += 10 * S  # long after the window has no send at all
    assert streamer.longest_gap_ns(window_ns=5 * S) == 10_800 * MS
    # The stream resumes: the gap is over, and is still the longest of the window.
    streamer.send_times_ns.extend(range(now[0], now[0] + S + 1, 10 * MS))
    now[0] += S
    assert streamer.longest_gap_ns(window_ns=5 * S) == 10_800 * MS
    now[0] += 5 * S  # ... until it ends before the window starts
    assert streamer.longest_gap_ns(window_ns=5 * S) == 5 * S  # (no send since)


def test_longest_gap_of_a_single_send_is_the_time_since_it() -> None:
    now = [3 * S]
    streamer = streamer_at(now)
    streamer.send_times_ns.append(3 * S)
    assert streamer.longest_gap_ns(window_ns=S) == 0
    now[0] += 250 * MS
    assert streamer.longest_gap_ns(window_ns=S) == 250 * MS


# Agent: resuming after missed periods -----------------------------------------------------


def fly(paper, agent, *, pose, stamps, measurements=None):
    """Step `agent` at `stamps`, flying each command for one period on the nominal unicycle
    (noise free), with a target observation every step, as the lockstep simulation hands
    them. Returns the last output and the pose the vehicle is at afterwards."""
    period = paper.controller.period_ns
    out = None
    for k, stamp in enumerate(stamps):
        target, _ = paper.target.state_at(stamp * 1e-9)
        y = np.array(pose) if measurements is None else measurements[k]
        out = agent.step(
            AgentInput(
                stamp_ns=stamp,
                measurement=y,
                target_observation=np.array(target, float),
                target_stamp_ns=stamp,
            )
        )
        pose = advance(*pose, *out.command.tolist(), NOMINAL_BETA, period * 1e-9)
    return out, pose


def spy_incumbent(agent) -> list:
    """Record the `incumbent` the agent's seeder is given at each solved step (None: the
    agent has no plan of its own to continue)."""
    seen = []
    seed = agent.seeder.seed

    def recording(*args, **kwargs):
        seen.append(kwargs.get("incumbent"))
        return seed(*args, **kwargs)

    agent.seeder.seed = recording
    return seen


def test_consecutive_stamps_never_count_as_resumes(paper) -> None:
    agent = build_agents(paper)[0]
    incumbents = spy_incumbent(agent)
    period = paper.controller.period_ns
    out, _ = fly(
        paper, agent, pose=paper.vehicles[0].initial, stamps=[k * period for k in range(25)]
    )
    assert out.status == "solved"
    assert agent.resumes == 0 and agent.steps == 25
    assert incumbents[0] is None and None not in incumbents[1:]  # the plan goes on


JUMPS = {
    "small": (0.3, -0.2, 0.05),  # inside the filter's innovation gate
    "large": (3.0, -2.0, 0.5),  # beyond it
}


@pytest.mark.parametrize("jump", JUMPS)
def test_a_stamp_gap_restarts_the_filter_at_the_measurement(paper, jump) -> None:
    agent = build_agents(paper)[0]
    period = paper.controller.period_ns
    _, pose = fly(
        paper, agent, pose=paper.vehicles[0].initial, stamps=[k * period for k in range(15)]
    )
    assert agent.resumes == 0
    beta, gate_resets = agent.dekf.beta.copy(), agent.dekf.resets
    incumbents = spy_incumbent(agent)
    # 10 periods missed (the agent was frozen); the vehicle is elsewhere meanwhile, and the
    # last command would not have taken it there.
    y = np.array(pose) + JUMPS[jump]
    out, _ = fly(paper, agent, pose=pose, stamps=[25 * period], measurements=[y.copy()])
    assert agent.resumes == 1
    np.testing.assert_array_equal(agent.dekf.z, y)  # the estimate is the measurement
    np.testing.assert_array_equal(out.state_estimate[:2], y[:2])
    np.testing.assert_array_equal(agent.dekf.beta, beta)  # nothing learned from the gap
    np.testing.assert_array_equal(out.beta, beta)
    assert agent.dekf.resets == gate_resets  # a restart, not the filter's gate
    assert incumbents == [None]  # the plan from before the gap is dropped
    assert out.status == "solved"
    assert out.plan.stamp_ns == 25 * period
    np.testing.assert_array_equal(out.plan.states[0, :2], y[:2])
    # Steps go on consecutively from there: no more resumes, the new plan continues.
    fly(paper, agent, pose=tuple(y), stamps=[k * period for k in range(26, 31)])
    assert agent.resumes == 1
    assert len(incumbents) == 6 and None not in incumbents[1:]


def test_the_same_jump_without_a_gap_is_filtered_and_learned_from(paper) -> None:
    """The reference for the test above: one period later, the small jump is filtered (the
    estimate is not the measurement) and learned from (beta moves); the large one trips the
    filter's gate, which also learns from it."""
    period = paper.controller.period_ns
    for jump, gated in (("small", False), ("large", True)):
        agent = build_agents(paper)[0]
        _, pose = fly(
            paper, agent, pose=paper.vehicles[0].initial, stamps=[k * period for k in range(15)]
        )
        beta, gate_resets = agent.dekf.beta.copy(), agent.dekf.resets
        y = np.array(pose) + JUMPS[jump]
        fly(paper, agent, pose=pose, stamps=[15 * period], measurements=[y.copy()])
        assert agent.resumes == 0
        assert agent.dekf.resets == gate_resets + gated
        assert np.array_equal(agent.dekf.z, y) == gated
        assert not np.array_equal(agent.dekf.beta, beta)


@pytest.mark.parametrize(("skipped", "resumes"), [(0, 0), (1, 1), (2, 1), (50, 1)])
def test_a_gap_of_more_than_one_and_a_half_periods_is_a_resume(paper, skipped, resumes) -> None:
    agent = build_agents(paper)[0]
    period = paper.controller.period_ns
    _, pose = fly(
        paper, agent, pose=paper.vehicles[0].initial, stamps=[k * period for k in range(5)]
    )
    fly(paper, agent, pose=pose, stamps=[(5 + skipped) * period])
    assert agent.resumes == resumes


def test_each_gap_counts_once(paper) -> None:
    agent = build_agents(paper)[0]
    period = paper.controller.period_ns
    stamps = [0, 1, 2, 10, 11, 12, 13, 40, 41, 60]
    fly(paper, agent, pose=paper.vehicles[0].initial, stamps=[k * period for k in stamps])
    assert agent.resumes == 3


def test_a_gap_before_the_first_measurement_is_not_a_resume(paper) -> None:
    """Before the filter has started there is nothing to restart: the first measurement after
    a gap starts it as usual."""
    agent = build_agents(paper)[0]
    period = paper.controller.period_ns
    target, _ = paper.target.state_at(0.0)
    out = agent.step(AgentInput(stamp_ns=0, measurement=None, target_observation=np.array(target)))
    assert out.status == "waiting for telemetry"
    y = np.array(paper.vehicles[0].initial, float)
    fly(paper, agent, pose=tuple(y), stamps=[10 * period], measurements=[y])
    assert agent.resumes == 0 and agent.dekf.initialized


# The runner: taking the vehicle back after its own gap ------------------------------------


class ScriptedLink(FakeAutopilotLink):
    """The fake autopilot, whose `wait_state` plays one scripted action per call (then stops
    the run): the runner's loop without threads or real time."""

    def __init__(self, script, stop: threading.Event, *, engage_ok: bool = True, **kw) -> None:
        super().__init__(**kw)
        self.script = list(script)
        self.stop = stop
        self.engage_ok = engage_ok
        self.engage_calls = 0

    def wait_state(self, *, newer_than_ns: int, timeout_s: float):
        if not self.script:
            self.stop.set()
        else:
            self.script.pop(0)(self)
        return self.state()

    def engage(self, *, timeout_s: float) -> bool:
        self.engage_calls += 1
        if not self.engage_ok:
            return False
        return super().engage(timeout_s=timeout_s)


class RecordingStreamer(SetpointStreamer):
    """A streamer that is never started: each command reaches the link at once (as its thread
    would send it), and the position holds it is asked for are recorded."""

    def __init__(self, link, now: list[int]) -> None:
        super().__init__(link, period_s=0.01, monotonic_ns=lambda: now[0])
        self.holds: list[tuple[float, float]] = []

    def hold_position(self, *, north_m: float, east_m: float) -> None:
        super().hold_position(north_m=north_m, east_m=east_m)
        self.holds.append((north_m, east_m))
        self._link.send_position_setpoint(north_m=north_m, east_m=east_m, down_m=0.0)

    def set_command(self, *, speed_m_s: float, yaw_rate_rad_s: float) -> None:
        super().set_command(speed_m_s=speed_m_s, yaw_rate_rad_s=yaw_rate_rad_s)
        self._link.send_setpoint(speed_m_s=speed_m_s, yaw_rate_rad_s=yaw_rate_rad_s)


def failsafe_run(paper, *, wall_gap_ms, reengage_after_gap_s=0.5, speed=1.0, engage_ok=True):
    """Fly an engaged vehicle whose setpoints stop reaching the autopilot for 1.2 s (its
    failsafe leaves offboard), with a streamer whose own stream had a gap of `wall_gap_ms` of
    wall time just before now (None: a steady stream). Returns the runner, link, streamer and
    log after the run."""
    stop = threading.Event()
    script = [
        lambda link: link.advance(200 * MS),  # setpoints flowing: offboard
        lambda link: link.advance(1_200 * MS),  # none for 1.2 s: the autopilot holds
        lambda link: link.advance(200 * MS),
        lambda link: link.advance(200 * MS),
    ]
    link = ScriptedLink(script, stop, engage_ok=engage_ok, north_m=3.0, east_m=-4.0)
    link.connect(timeout_s=0.1)
    FakeAutopilotLink.engage(link, timeout_s=0.1)  # (whatever `engage_ok` says of later ones)
    now = [100 * S]
    streamer = RecordingStreamer(link, now)
    if wall_gap_ms is None:
        streamer.send_times_ns.extend(range(90 * S, now[0] + 1, 10 * MS))
    else:
        streamer.send_times_ns.extend(range(90 * S, now[0] - wall_gap_ms * MS + 1, 10 * MS))
        streamer.send_times_ns.extend(range(now[0], now[0] + 1, 10 * MS))
    logged: list[str] = []
    runner = FleetRunner(
        build_agents(paper)[0],
        link=link,
        bus=InMemoryPlanBus(MemoryHubs().hub(FLEET), fleet=FLEET, vehicle_id=1),
        settings=RunnerSettings(
            period_ns=paper.controller.period_ns,
            engage=False,  # engaged by hand above
            reengage_after_gap_s=reengage_after_gap_s,
        ),
        clock=FleetClock(speed=speed),
        log=logged.append,
    )
    runner.engaged = True
    runner.run(stop, streamer)
    assert not link.script and stop.is_set()  # the whole script ran
    assert runner.step_errors == 0
    return runner, link, streamer, logged


def test_a_vehicle_lost_after_the_agents_own_gap_is_taken_back(paper) -> None:
    runner, link, streamer, logged = failsafe_run(paper, wall_gap_ms=800)
    assert link.engage_calls == 1
    assert runner.reengaged == 1 and runner.engaged
    state = link.state()
    assert state.mode == FlightMode.OFFBOARD and not state.mode_lost
    # The vehicle holds where the autopilot left it while it is taken back (after the hold
    # where the runner found it, before its first step).
    assert streamer.holds == [(3.0, -4.0), (3.0, -4.0)]
    text = "\n".join(logged)
    assert "mode lost (HOLD) after a 0.8 s gap in its own setpoints; taking it back" in text
    assert "vehicle 1: re-engaged" in text
    assert "not re-engaging" not in text
    summary = runner.summary(streamer)
    assert summary["reengaged"] == 1 and summary["engaged"] is True
    # The runner woke 1.2 s late (the script's jump in telemetry, as after a freeze): its
    # agent resumed once, and the summary says so.
    assert summary["resumes"] == runner.agent.resumes == 1


def test_a_mode_change_while_the_stream_was_whole_is_not_undone(paper) -> None:
    """The autopilot left offboard while the agent's own stream had no gap: a pilot's or a
    ground station's doing (here, setpoints lost on the way), reported once, never fought."""
    runner, link, streamer, logged = failsafe_run(paper, wall_gap_ms=None)
    assert link.engage_calls == 0 and runner.reengaged == 0
    assert link.state().mode == FlightMode.HOLD and link.state().mode_lost
    assert streamer.holds == [(3.0, -4.0)]  # only where the runner found it
    assert sum("mode lost (HOLD); not re-engaging" in line for line in logged) == 1, logged
    assert not any("taking it back" in line for line in logged)
    assert runner.summary(streamer)["reengaged"] == 0


def test_a_gap_shorter_than_the_setting_is_not_the_agents_doing(paper) -> None:
    runner, link, _, logged = failsafe_run(paper, wall_gap_ms=400)
    assert link.engage_calls == 0 and runner.reengaged == 0
    assert any("not re-engaging" in line for line in logged)


def test_reengaging_can_be_turned_off(paper) -> None:
    runner, link, _, logged = failsafe_run(paper, wall_gap_ms=3_000, reengage_after_gap_s=None)
    assert link.engage_calls == 0 and runner.reengaged == 0
    assert link.state().mode_lost
    assert any("not re-engaging" in line for line in logged)
    assert not any("taking it back" in line for line in logged)


def test_a_failed_take_back_leaves_the_vehicle_alone(paper) -> None:
    runner, link, _, logged = failsafe_run(paper, wall_gap_ms=800, engage_ok=False)
    assert link.engage_calls == 1  # tried once, not at every wake-up
    assert runner.reengaged == 0 and not runner.engaged
    assert any("could not re-engage; flying nothing" in line for line in logged)
    assert link.state().mode_lost


def test_the_gap_is_measured_in_fleet_time(paper) -> None:
    """At x4, 0.2 s of wall time is 0.8 s of fleet time: a gap to take the vehicle back for."""
    runner, link, _, logged = failsafe_run(paper, wall_gap_ms=200, speed=4.0)
    assert link.engage_calls == 1 and runner.reengaged == 1
    assert any("after a 0.8 s gap" in line for line in logged), logged
    runner, link, _, _ = failsafe_run(paper, wall_gap_ms=100, speed=4.0)  # 0.4 s fleet
    assert link.engage_calls == 0 and runner.reengaged == 0


class FakeStreamer:
    """What `_own_gap_s` and `_take_back` use of a streamer."""

    def __init__(self, gap_ns: int) -> None:
        self.gap_ns = gap_ns
        self.windows: list[int] = []
        self.holds: list[tuple[float, float]] = []

    def longest_gap_ns(self, *, window_ns: int) -> int:
        self.windows.append(window_ns)
        return self.gap_ns

    def hold_position(self, *, north_m: float, east_m: float) -> None:
        self.holds.append((north_m, east_m))

    def rate_hz(self, *, window_ns: int) -> float:
        return 100.0


def bare_runner(paper, *, limit_s=0.5, speed=1.0):
    link = FakeAutopilotLink(north_m=1.0, east_m=2.0)
    link.connect(timeout_s=0.1)
    logged: list[str] = []
    runner = FleetRunner(
        build_agents(paper)[0],
        link=link,
        bus=InMemoryPlanBus(MemoryHubs().hub(FLEET), fleet=FLEET, vehicle_id=1),
        settings=RunnerSettings(period_ns=paper.controller.period_ns, reengage_after_gap_s=limit_s),
        clock=FleetClock(speed=speed),
        log=logged.append,
    )
    return runner, link, logged


def test_own_gap_needs_a_stream_an_engaged_vehicle_and_the_setting(paper) -> None:
    runner, _, _ = bare_runner(paper)
    assert runner._own_gap_s() is None  # no streamer yet
    runner._streamer = FakeStreamer(2 * S)
    assert runner._own_gap_s() is None  # not engaged: nothing to take back
    runner.engaged = True
    assert runner._own_gap_s() == pytest.approx(2.0)
    runner._streamer.gap_ns = 499 * MS
    assert runner._own_gap_s() is None
    runner._streamer.gap_ns = 500 * MS
    assert runner._own_gap_s() == pytest.approx(0.5)
    off, _, _ = bare_runner(paper, limit_s=None)
    off._streamer, off.engaged = FakeStreamer(60 * S), True
    assert off._own_gap_s() is None


@pytest.mark.parametrize("speed", [1.0, 4.0, 0.5])
def test_own_gap_looks_back_five_seconds_of_fleet_time(paper, speed) -> None:
    runner, _, _ = bare_runner(paper, speed=speed)
    runner._streamer, runner.engaged = FakeStreamer(S), True
    gap = runner._own_gap_s()
    assert runner._streamer.windows == [round(5 * S / speed)]  # the streamer's clock is wall
    assert gap == pytest.approx(speed)  # 1 s of wall time is `speed` s of fleet time


def test_take_back_holds_the_vehicle_and_engages_it(paper) -> None:
    runner, link, logged = bare_runner(paper)
    link.engage(timeout_s=0.1)
    link.advance(1_500 * MS)  # no setpoints: the fake autopilot holds
    state = link.state()
    assert state.mode_lost
    streamer = FakeStreamer(S)
    runner._streamer, runner.engaged = streamer, True
    after = runner._take_back(state, streamer)
    assert streamer.holds == [(1.0, 2.0)]
    assert runner.reengaged == 1 and runner.engaged
    assert after.mode == FlightMode.OFFBOARD and not after.mode_lost
    assert after == link.state()
    assert logged == [
        "vehicle 1: mode lost (HOLD) after a 1.0 s gap in its own setpoints; taking it back",
        "vehicle 1: re-engaged",
    ]


def test_take_back_without_an_own_gap_changes_nothing(paper) -> None:
    runner, link, logged = bare_runner(paper)
    link.engage(timeout_s=0.1)
    link.advance(1_500 * MS)
    state = link.state()
    streamer = FakeStreamer(20 * MS)
    runner._streamer, runner.engaged = streamer, True
    assert runner._take_back(state, streamer) is state
    assert streamer.holds == [] and runner.reengaged == 0 and logged == []
    assert link.state().mode_lost


def test_tick_reports_a_lost_mode_only_when_it_is_not_taken_back(paper) -> None:
    runner, link, logged = bare_runner(paper)
    link.engage(timeout_s=0.1)
    link.advance(1_500 * MS)
    runner._streamer, runner.engaged = FakeStreamer(S), True
    runner.tick(link.state())  # an own gap: `run` takes it back, so nothing to report
    assert not any("not re-engaging" in line for line in logged)
    runner._streamer.gap_ns = 10 * MS
    runner.tick(link.state())
    runner.tick(link.state())
    assert sum("mode lost (HOLD); not re-engaging" in line for line in logged) == 1
    assert not any("failed" in line or "error" in line for line in logged), logged


# SetpointStreamer: a command past its lifetime fades to a stop --------------------------------


def test_a_command_older_than_its_lifetime_fades_to_a_stop_and_a_new_one_flies_at_once() -> None:
    now = [0]
    streamer = SetpointStreamer(
        FakeAutopilotLink(), period_s=0.01, command_lifetime_s=0.4, monotonic_ns=lambda: now[0]
    )
    streamer.set_command(speed_m_s=1.5, yaw_rate_rad_s=-0.2)
    now[0] += 400 * MS  # as old as its lifetime: flown as it is
    assert streamer.flown() == (1.5, -0.2) and streamer.faded_sends == 0
    now[0] += 100 * MS  # a quarter of a lifetime past it: a quarter of the way to a stop
    assert streamer.flown() == pytest.approx((1.125, -0.15))
    now[0] += 300 * MS  # two lifetimes: stopped, and stays so
    assert streamer.flown() == (0.0, 0.0)
    now[0] += 10 * S
    assert streamer.flown() == (0.0, 0.0) and streamer.faded_sends == 3
    streamer.set_command(speed_m_s=0.7, yaw_rate_rad_s=0.1)  # the agent is back
    assert streamer.flown() == (0.7, 0.1)
    forever = streamer_at(now)  # no lifetime: the latest command, whatever its age
    forever.set_command(speed_m_s=1.0, yaw_rate_rad_s=0.0)
    now[0] += 100 * S
    assert forever.flown() == (1.0, 0.0)
