import dataclasses
import math

import numpy as np
import pytest

from fleetmpc.onboard.core.agent import Agent, AgentInput
from fleetmpc.onboard.core.period import safe_fallback
from fleetmpc.protocol.plan import Plan
from fleetmpc.scenario import Scenario

PERIOD_NS = 200_000_000


def _agent(sc: Scenario, vid: int = 1, **learning) -> Agent:
    return Agent(
        vid,
        fleet_ids=sc.vehicle_ids,
        controller=sc.controller,
        learning=dataclasses.replace(sc.learning, **learning),
        formation=sc.formation,
        target_observation_std_m=0.05,
    )


def _slot_state(sc: Scenario, idx: int, t_s: float) -> np.ndarray:
    p, v = sc.target.state_at(t_s)
    u = v / np.linalg.norm(v)
    slot = p - sc.formation.trail_m * u + np.array(sc.formation.slots_m[idx])
    return np.array([*slot, np.arctan2(v[1], v[0])])


def _plan(vid: int, stamp_ns: int, start: np.ndarray, vel: np.ndarray, M: int = 5) -> Plan:
    t = 0.2 * np.arange(M + 1)
    states = np.column_stack(
        [start[0] + vel[0] * t, start[1] + vel[1] * t, np.full(M + 1, np.arctan2(vel[1], vel[0]))]
    )
    return Plan(vid, stamp_ns, PERIOD_NS, states, np.tile([np.hypot(*vel), 0.0], (M, 1)))


def test_at_exact_steady_state_c_is_zero_and_the_command_is_the_steady_input(paper):
    agent = _agent(paper, enabled=False)  # nominal model = truth here: no wind, unit effectiveness
    out = None
    for k in range(30):
        t = k * 0.2
        p, _ = paper.target.state_at(t)
        plans = {
            vid: _plan(
                vid,
                k * PERIOD_NS - PERIOD_NS,
                _slot_state(paper, i, t - 0.2)[:2],
                np.array([1.0, 1.0]),
            )
            for i, vid in enumerate(paper.vehicle_ids)
            if vid != 1
        }
        out = agent.step(
            AgentInput(k * PERIOD_NS, _slot_state(paper, 0, t), p, neighbour_plans=plans)
        )
    assert out.qp_ok and out.formation_terms == 2
    assert np.linalg.norm(out.c) < 1e-3
    np.testing.assert_allclose(out.command, [np.sqrt(2.0), 0.0], atol=1e-3)


def test_waits_for_target_then_flies(paper):
    agent = _agent(paper)
    out = agent.step(AgentInput(0, np.array([0.0, 0.0, 0.0]), None))
    assert out.status == "waiting for target" and np.all(out.command == 0)
    assert out.qp_ok and agent.fallbacks == 0  # waiting is no fallback (no warning at start)
    out = agent.step(AgentInput(PERIOD_NS, np.array([0.0, 0.0, 0.0]), np.array([5.0, 5.0])))
    assert out.qp_ok and np.any(out.command != 0)


def test_stale_plans_drop_the_formation_term_but_keep_separation(paper):
    agent = _agent(paper)
    fresh = _plan(2, 0, np.array([0.0, 10.0]), np.array([1.0, 1.0]))
    z = np.array([0.0, 0.0, np.pi / 4])
    out = agent.step(AgentInput(PERIOD_NS, z, np.array([5.0, 5.0]), neighbour_plans={2: fresh}))
    assert out.formation_terms == 1
    t_ns = int(3e9)  # the plan is now 3 s old: beyond plan_stale_s, within plan_forget_s
    out = agent.step(AgentInput(t_ns, z, np.array([8.0, 8.0]), neighbour_plans={2: fresh}))
    assert out.formation_terms == 0
    assert out.neighbour_ages_s[2] == pytest.approx(3.0)
    assert out.qp_ok


def test_separation_constraint_holds_against_a_neighbour_parked_on_the_path(paper):
    agent = _agent(paper)
    z = np.array([0.0, 0.0, np.pi / 4])
    # Vehicle 2 hovers 2.6 m ahead, on the way to vehicle 1's slot, and says so every period.
    for k in range(1, 8):
        parked = Plan(
            2, (k - 1) * PERIOD_NS, PERIOD_NS, np.tile([1.84, 1.84, 0.0], (6, 1)), np.zeros((5, 2))
        )
        t = np.array([5.0 + 0.2 * k, 5.0 + 0.2 * k])
        out = agent.step(AgentInput(k * PERIOD_NS, z, t, neighbour_plans={2: parked}))
        gaps = np.linalg.norm(out.plan.states[:, :2] - [1.84, 1.84], axis=1)
        assert out.qp_ok, out.status
        assert gaps[1:].min() >= paper.controller.d_safe_m - 1e-6
        z = out.plan.states[1]


def test_a_vehicle_inside_a_neighbours_margin_never_closes_on_it(paper):
    agent = _agent(paper)
    z = np.array([0.0, 0.0, np.pi / 4])
    agent.step(AgentInput(0, z, np.array([5.0, 5.0])))
    # A plan 1.5 s old: its margin is inflated by v_max x (age - one period), and the vehicle,
    # facing it, is already inside it. It holds its distance (the problem stays feasible).
    parked = Plan(2, 0, PERIOD_NS, np.tile([1.84, 1.84, 0.0], (6, 1)), np.zeros((5, 2)))
    out = agent.step(AgentInput(int(1.5e9), z, np.array([6.5, 6.5]), neighbour_plans={2: parked}))
    assert out.qp_ok, out.status
    gaps = np.linalg.norm(out.plan.states[:, :2] - [1.84, 1.84], axis=1)
    assert np.all(np.diff(gaps) >= -1e-3)
    assert out.command[0] < 0.05


def test_the_fallback_never_steers_into_a_neighbour(paper):
    agent = _agent(paper)
    z0 = [0.0, 0.0, np.pi / 4]
    # A neighbour's line 1 m ahead on the way the vehicle faces: flying on breaks it at once.
    n = -np.array([1.0, 1.0]) / np.sqrt(2.0)
    planes = [[(n[0], n[1], -1.0)] * paper.controller.horizon]
    u = safe_fallback(
        z0,
        np.array([2.0, 0.0]),
        (1.0, 1.0, 0.0, 0.0),
        planes,
        box=agent.box,
        horizon=paper.controller.horizon,
        tau=paper.controller.period_s,
    )
    assert u[0] < 2.0
    x, y = z0[0], z0[1]
    for _ in range(paper.controller.horizon):  # held over the horizon, it stays on its side
        x += 0.2 * u[0] * np.cos(z0[2])
        y += 0.2 * u[0] * np.sin(z0[2])
        assert n @ [x, y] >= -1.0 - 1e-9


def test_nan_measurement_never_reaches_the_command(paper):
    agent = _agent(paper)
    agent.step(AgentInput(0, np.array([0.0, 0.0, 0.0]), np.array([5.0, 5.0])))
    out = agent.step(AgentInput(PERIOD_NS, np.array([np.nan, 0.0, 0.0]), np.array([5.2, 5.2])))
    assert np.all(np.isfinite(out.command)) and np.all(np.abs(out.command) <= agent.box.upper)


def test_round_a_corner_the_agents_formation_reference_keeps_with_the_judges():
    """Round a waypoint corner the agent's formation reference (its centre on the estimated
    path and its rate-limited course) stays with the one a run is judged against (the same
    construction on the true path): the sweeps start together, as both read the path."""
    from fleetmpc.onboard.core.agent import reference_course_limit
    from fleetmpc.onboard.core.formation import Formation, FormationReference
    from fleetmpc.scenario import load_scenario

    sc = load_scenario("scenarios/square.toml")
    v = sc.vehicles[0]
    agent = Agent(
        v.id,
        fleet_ids=sc.vehicle_ids,
        controller=sc.controller,
        formation=sc.formation,
        learning=sc.learning,
        target_observation_std_m=sc.target.observation_noise_m,
    )
    truth = FormationReference(
        Formation(sc.formation), reference_course_limit(sc.controller, sc.formation)
    )
    rng = np.random.default_rng(11)
    period_ns = sc.controller.period_ns
    course_lags, centre_gaps = [], []
    for k in range(int(70.0 * 1e9 / period_ns)):
        t = k * period_ns * 1e-9
        position, velocity = sc.target.state_at(t)
        agent.step(AgentInput(k * period_ns, np.array(v.initial), sc.target.observe(t, rng)))
        centre, course = truth.follow(position.tolist(), velocity.tolist(), period_ns * 1e-9)
        if t >= 38.0:  # the corner is at 40 s; the formation goes round it until about 60 s
            mine = agent.reference.path.at(agent.reference.path.length_m - sc.formation.trail_m)
            course_lags.append(abs(agent.reference.course - course))
            centre_gaps.append(math.dist(mine[0], centre))
    rate = reference_course_limit(sc.controller, sc.formation).at(sc.target.speed_m_s)
    assert max(course_lags) < rate * 0.25  # less than a quarter of a second of sweep apart
    # The estimate cuts the corner by a few decimetres for a moment, and its path with it.
    assert max(centre_gaps) < 0.4
    assert math.sqrt(np.mean(np.square(centre_gaps))) < 0.12


def test_an_autopilot_that_responds_late_is_planned_for_from_when_it_will_fly():
    """With a response delay of two periods the agent learns from the command flown over the
    last period (sent three periods ago), plans from the state the two commands still to be
    flown lead to, and stamps its plan at the time its first input will be flown."""
    from fleetmpc.onboard.agent_feed import agent_for
    from fleetmpc.onboard.core.unicycle import advance
    from fleetmpc.scenario import load_scenario

    paper = load_scenario("scenarios/paper.toml")
    late = agent_for(paper, dataclasses.replace(paper.vehicles[0], response_delay_s=0.4))
    fed = []
    late.dekf.step = lambda y, u, _step=late.dekf.step, **kw: (
        fed.append(u.copy()),
        _step(y, u, **kw),
    )[1]
    z = np.array(paper.vehicles[0].initial, float)
    sent = []
    for k in range(8):
        t = k * 0.2
        observation = paper.target.observe(t, np.random.default_rng(k))
        out = late.step(AgentInput(k * PERIOD_NS, z, observation))
        if k >= 1:
            assert out.plan.stamp_ns == k * PERIOD_NS + 2 * PERIOD_NS
            pending = sent[-2:] if len(sent) >= 2 else [np.zeros(2)] * (2 - len(sent)) + sent
            expect = late.dekf.z.tolist()
            for v, w in pending:
                expect = advance(*expect, v, w, late.dekf.beta.tolist(), 0.2)
            assert out.plan.states[0] == pytest.approx(np.array(expect), abs=1e-9)
        sent.append(out.command.copy())
    # The DEKF was given, at step k, the command sent at step k - 3 (zeros before any).
    flown = [np.zeros(2)] * 3 + sent
    assert len(fed) == 8 and any(np.any(u != 0) for u in fed)
    assert all(np.array_equal(u, flown[k]) for k, u in enumerate(fed))


def test_a_late_step_keeps_the_lateness_times_v_max_more_from_every_neighbour(paper):
    """A step that runs L late widens this vehicle's margin to each neighbour by v_max L."""
    seen = []
    for late_s in (0.0, 0.15):
        agent = _agent(paper)
        planes = agent.neighbourhood.planes
        agent.neighbourhood.planes = lambda *a, _p=planes, **k: (
            seen.append(dict(a[-1])),
            _p(*a, **k),
        )[1]
        fresh = _plan(2, PERIOD_NS, np.array([12.0, 5.0, 0.0]), np.array([1.0, 1.0]))
        z = np.array(paper.vehicles[0].initial, float)
        agent.step(AgentInput(0, z, np.array([5.0, 5.0])))
        agent.step(
            AgentInput(
                PERIOD_NS, z, np.array([5.2, 5.2]), neighbour_plans={2: fresh}, late_s=late_s
            )
        )
    assert len(seen) == 4  # (the inflations handed to planes, two steps of each agent)
    on_time, late = seen[1], seen[3]
    assert list(on_time) == list(late) == [2]
    assert late[2] == pytest.approx(on_time[2] + paper.controller.speed_max_m_s * 0.15)
