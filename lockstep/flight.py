"""In-process lockstep simulation: every agent and truth plant advance together on integer ticks.

Each period every agent steps on its own noisy measurement, the latest target observation and the
neighbours' plans as its plan bus has them (Dunbar & Murray's assumed trajectories), then
publishes its plan, and the plants fly the commands for one period of plant ticks. The plans
travel through the in-memory plan bus (`fleetmpc.bus.memory`), encoded and decoded as
on the wire, each bus behind its vehicle's `fleetmpc.bus.faults.FaultLayer` when the run has
faults: without faults every plan arrives at the next period, as a perfect network would deliver
it. Deterministic for a seed.

Each period becomes a `PeriodSample` (`fleetmpc.gcs.telemetry`), as a live ground station makes
them; the run's FlightRecord stacks them, and any telemetry sinks given (a Rerun recording, a
viewer) are handed them as the ground station hands its own, each with its own time, and
flushed every `FLUSH_S` of flight; at the end they are told what the plan bus did.
"""

from collections.abc import Callable, Sequence

import numpy as np

from fleetmpc.bus.faults import FaultSchedule
from fleetmpc.bus.memory import InMemoryPlanBus, MemoryHub
from fleetmpc.gcs.record import FlightRecord, RunConstants
from fleetmpc.gcs.telemetry import (
    FLUSH_S,
    PeriodSample,
    TargetFix,
    TelemetrySink,
    record_of,
    target_state_event,
)
from fleetmpc.lockstep.agent_pool import COUNTED, AgentPool, build_agents
from fleetmpc.onboard.core.agent import reference_course_limit
from fleetmpc.onboard.core.formation import Formation, FormationReference
from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.target_watch import TRACKING
from fleetmpc.protocol.messages import TARGET_ID
from fleetmpc.scenario import Scenario
from fleetmpc.sitl.plant import TruthPlant
from fleetmpc.sitl.wind import WindField

__all__ = ["build_agents", "run_lockstep"]


def run_lockstep(
    scenario: Scenario,
    *,
    learning: bool = True,
    duration_s: float | None = None,
    seed: int | None = None,
    progress: Callable[[float, float], None] | None = None,
    sinks: Sequence[TelemetrySink] = (),
    run_info: dict | None = None,
    faults: FaultSchedule | None = None,
    jobs: int = 1,
    known_model: bool = False,
) -> FlightRecord:
    """Fly the scenario in lockstep and return its record; the sinks (opened with `run_info`,
    closed at the end) get every period's sample; `faults` are injected into the plan bus; the
    agents step in `jobs` processes (`fleetmpc.lockstep.agent_pool`: the same figures for any).
    `known_model`: every agent is told its vehicle's true effectiveness and the wind where it
    is, each period, instead of learning them (docs/design.md, "The known-model run")."""
    seed = scenario.seed if seed is None else seed
    learning = learning or known_model
    with AgentPool(scenario, learning=learning, jobs=jobs, faults=faults, seed=seed) as pool:
        return _fly(
            scenario, pool, duration_s, seed, progress, sinks, run_info, faults, known_model
        )


def _truth(plant: TruthPlant) -> np.ndarray:
    """What the vehicle's beta would be if learned perfectly: (a_V, a_w, wind N, wind E)."""
    p = plant.params
    return np.array([p.speed_effectiveness, p.yaw_rate_effectiveness, *plant.wind_m_s])


def _fly(
    sc: Scenario,
    pool: AgentPool,
    duration_s: float | None,
    seed: int,
    progress: Callable[[float, float], None] | None,
    sinks: Sequence[TelemetrySink],
    run_info: dict | None,
    faults: FaultSchedule | None,
    known_model: bool,
) -> FlightRecord:
    duration_s = sc.duration_s if duration_s is None else duration_s
    period_ns, tick_ns, ticks = sc.controller.period_ns, sc.tick_ns, sc.plant_steps_per_period
    periods = int(round(duration_s * 1e9 / period_ns)) + 1
    root = np.random.default_rng(seed)
    rngs = root.spawn(len(sc.vehicles) + 1)
    target_rng = rngs[-1]
    winds = {v.truth.wind: WindField(v.truth.wind, seed=seed) for v in sc.vehicles}
    plants = [
        TruthPlant(
            v.truth,
            x_m=v.initial[0],
            y_m=v.initial[1],
            yaw_rad=v.initial[2],
            wind=winds[v.truth.wind],
        )
        for v in sc.vehicles
    ]
    truth_formation = Formation(sc.formation)
    truth_reference = FormationReference(
        truth_formation, reference_course_limit(sc.controller, sc.formation)
    )
    """The slots the run is judged against: the formation along the true target's path, as the
    agents place it along their estimates'."""
    n = len(plants)
    ids = sc.vehicle_ids
    feed = sc.target.feed(target_rng)
    """The target's observations: a script's at its rate, a recorded track's as recorded."""
    constants = RunConstants.of_scenario(sc, truth_formation.desired_distances())
    for sink in sinks:
        sink.open(constants, run_info or {})
    flush_every = max(1, round(FLUSH_S * 1e9 / period_ns))
    ground_target = None
    """The ground side's own target track for the sinks' map (as a live ground station's)."""
    if sinks:
        ground_target = TargetEstimator(observation_std_m=sc.target.observation_noise_m)
    others = [[j for j in range(n) if j != i] for i in range(n)]
    hub = MemoryHub(sc.name, deliver_immediately=False)
    target_bus = InMemoryPlanBus(hub, fleet=sc.name, vehicle_id=TARGET_ID)
    """The target's observations reach the agents on the plan bus too, as in a live fleet."""
    setpoint_rate = np.full(n, 1e9 / period_ns)  # one command per period
    target_states = [TRACKING] * n
    """Each agent's target state (tracking, predicting, ...) as last logged."""
    samples: list[PeriodSample] = []
    min_sep = np.inf
    upper = np.triu_indices(n, 1)
    for k in range(periods):
        t_ns = k * period_ns
        t_s = t_ns * 1e-9
        tgt_pos, tgt_vel = sc.target.state_at(t_s)
        observations = feed.due(t_ns)
        _observe(sinks, observations)
        for stamp_ns, obs in observations:
            if ground_target is not None:
                ground_target.observe(stamp_ns, obs)
            target_bus.publish_target(
                stamp_ns=stamp_ns,
                north_m=float(obs[0]),
                east_m=float(obs[1]),
                noise_std_m=float(sc.target.observation_noise_m),
            )
        if observations:
            pool.deliver(t_ns, [(key, payload, None) for key, payload, _ in hub.take()])
        measurements = [plant.measure(rngs[i]) for i, plant in enumerate(plants)]
        truths = np.array([_truth(p) for p in plants])
        outs, published = pool.step(t_ns, measurements, list(truths) if known_model else None)
        _log_target_states(sinks, t_ns, ids, [o for o, _ in outs], target_states)
        centre, course = truth_reference.follow(
            tgt_pos.tolist(), tgt_vel.tolist(), period_ns * 1e-9
        )
        slots = truth_formation.slots(np.array([centre]), np.array([course]))[0]
        target_path = None
        if ground_target is not None and ground_target.ready:
            target_path, _ = ground_target.predict(t_ns, period_ns, sc.controller.horizon + 1)
        ages = [o.neighbour_ages_s for o, _ in outs]
        sample = PeriodSample(
            t_ns=t_ns,
            truth=np.array([p.pose for p in plants]),
            target=tgt_pos,
            target_velocity=tgt_vel,
            slots=slots,
            slot_offsets_world=slots - np.array(centre),
            command=np.array([o.command for o, _ in outs]),
            c=np.array([o.c[0] for o, _ in outs]),
            beta=np.array([o.beta for o, _ in outs]),
            beta_truth=truths,
            qp_ok=np.array([o.qp_ok for o, _ in outs]),
            step_time_ms=np.array([ms for _, ms in outs]),
            min_separation_m=float(min_sep),
            plans=np.array([o.plan.states[:, :2] for o, _ in outs]),
            plan_age_s=np.array(
                [[ages[i].get(ids[j], np.nan) for j in others[i]] for i in range(n)]
            ).reshape(n, n - 1),
            setpoint_rate_hz=setpoint_rate,
            target_prediction=outs[0][0].target_prediction_m,
            target_path=target_path,
        )
        samples.append(sample)
        for sink in sinks:  # (the QP fallbacks become events from the samples)
            sink.log([sample])
            if (k + 1) % flush_every == 0:
                sink.flush()
        pool.deliver(t_ns, published)  # (each plan reaches the others as the period ends)
        if k == periods - 1:
            break
        for (out, _), plant in zip(outs, plants, strict=True):
            plant.command(float(out.command[0]), float(out.command[1]))
        tracks: list[list[tuple[float, float]]] = [[] for _ in plants]
        for plant, track in zip(plants, tracks, strict=True):  # the plants are independent
            plant.advance(tick_ns, ticks, track=track)
        if n > 1:  # the closest approach, checked at every plant tick
            xy = np.array(tracks)  # (vehicle, tick, 2)
            dx = xy[:, None, :, 0] - xy[None, :, :, 0]
            dy = xy[:, None, :, 1] - xy[None, :, :, 1]
            gaps = np.sqrt(dx * dx + dy * dy)[upper]
            min_sep = min(min_sep, float(gaps.min()))
        if progress is not None:
            progress((k + 1) * period_ns * 1e-9, duration_s)
    network = _network_report(pool.report(), faults, periods)
    for sink in sinks:
        sink.finish({"network": network})
        sink.close()
    target_bus.close()
    return record_of(constants, samples, network=network)


def _observe(sinks: Sequence[TelemetrySink], observations: list) -> None:
    """The target's observations (fleet time [ns], North and East [m]) as the agents get them."""
    if sinks and observations:
        fixes = [TargetFix(t_ns, float(obs[0]), float(obs[1])) for t_ns, obs in observations]
        for sink in sinks:
            sink.observe(fixes)


def _log_target_states(
    sinks: Sequence[TelemetrySink], t_ns: int, ids: tuple[int, ...], outs: list, states: list[str]
) -> None:
    """An event for each agent whose target state changed this period (`states`: each one's
    state before it, updated), as a live ground station logs it from the agents' statuses."""
    for i, out in enumerate(outs):
        if out.target_state != states[i]:
            states[i] = out.target_state
            for sink in sinks:
                sink.event(t_ns, *target_state_event(ids[i], out.target_state))


def _network_report(
    buses: list[tuple[dict[str, int], dict[str, int] | None]],
    faults: FaultSchedule | None,
    periods: int,
) -> dict:
    """What the plan bus did: the faults injected and what the receivers counted (and, per agent
    and period, what each kept and what it dropped as beyond its neighbourhood); `buses` holds
    each vehicle's counters and fault counts (`fleetmpc.lockstep.agent_pool.Share.report`)."""
    agent_periods = max(1, len(buses) * periods)
    received = {name: sum(counters[name] for counters, _ in buses) for name in COUNTED}
    report = {
        "faults": [] if faults is None else [f.describe() for f in faults.faults],
        "received": received,
        "per_agent_period": {
            name: received[name] / agent_periods for name in ("accepted", "filtered")
        },
    }
    if faults is not None:
        injected: dict[str, int] = {}
        for _, counts in buses:
            for name, count in (counts or {}).items():
                injected[name] = injected.get(name, 0) + count
        report["injected"] = injected
    return report
