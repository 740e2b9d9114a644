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


class _Plants:
    """The fleet's truth plants in one wind field per wind (`WindField`), and their closest
    approach so far, checked at every plant tick."""

    def __init__(self, sc: Scenario, seed: int, rngs: Sequence[np.random.Generator]) -> None:
        """`rngs`: each vehicle's measurement noise stream, in the fleet's order."""
        winds = {v.truth.wind: WindField(v.truth.wind, seed=seed) for v in sc.vehicles}
        self.plants = [
            TruthPlant(
                v.truth,
                x_m=v.initial[0],
                y_m=v.initial[1],
                yaw_rad=v.initial[2],
                wind=winds[v.truth.wind],
            )
            for v in sc.vehicles
        ]
        self._rngs = rngs
        self.tick_ns, self.ticks = sc.tick_ns, sc.plant_steps_per_period
        self.min_separation_m = np.inf
        self._upper = np.triu_indices(len(self.plants), 1)

    def measure(self) -> list[np.ndarray]:
        """Each vehicle's noisy measurement now (`TruthPlant.measure`)."""
        return [plant.measure(rng) for plant, rng in zip(self.plants, self._rngs, strict=True)]

    def truths(self) -> np.ndarray:
        """Each vehicle's true beta now (N, 4) (`_truth`)."""
        return np.array([_truth(p) for p in self.plants])

    def poses(self) -> np.ndarray:
        """Each vehicle's true (x, y, yaw) now (N, 3)."""
        return np.array([p.pose for p in self.plants])

    def fly(self, commands: Sequence[np.ndarray]) -> None:
        """Fly each vehicle's command (speed, yaw rate) for one period of plant ticks (the
        plants are independent), keeping the closest approach up to date."""
        tracks: list[list[tuple[float, float]]] = [[] for _ in self.plants]
        for command, plant, track in zip(commands, self.plants, tracks, strict=True):
            plant.command(float(command[0]), float(command[1]))
            plant.advance(self.tick_ns, self.ticks, track=track)
        if len(self.plants) > 1:
            xy = np.array(tracks)  # (vehicle, tick, 2)
            dx = xy[:, None, :, 0] - xy[None, :, :, 0]
            dy = xy[:, None, :, 1] - xy[None, :, :, 1]
            gaps = np.sqrt(dx * dx + dy * dy)[self._upper]
            self.min_separation_m = min(self.min_separation_m, float(gaps.min()))


class _Target:
    """The target's side of a period: its observations (a script's at its rate, a recorded
    track's as recorded) go to the sinks, to the ground side's own track of it (as a live ground
    station keeps one, for the sinks' map) and, on the plan bus, to the agents."""

    def __init__(self, sc: Scenario, rng: np.random.Generator, hub: MemoryHub, sinks) -> None:
        self._feed = sc.target.feed(rng)
        self._noise_m = float(sc.target.observation_noise_m)
        self._bus = InMemoryPlanBus(hub, fleet=sc.name, vehicle_id=TARGET_ID)
        self._hub, self._sinks = hub, sinks
        self._track = TargetEstimator(observation_std_m=self._noise_m) if sinks else None
        self._horizon = sc.controller.horizon

    def observe(self, t_ns: int, pool: AgentPool) -> None:
        """Publish the observations due by `t_ns` and deliver them to the agents."""
        observations = self._feed.due(t_ns)
        _observe(self._sinks, observations)
        for stamp_ns, obs in observations:
            if self._track is not None:
                self._track.observe(stamp_ns, obs)
            north, east = float(obs[0]), float(obs[1])
            self._bus.publish_target(
                stamp_ns=stamp_ns, north_m=north, east_m=east, noise_std_m=self._noise_m
            )
        if observations:
            pool.deliver(t_ns, [(key, payload, None) for key, payload, _ in self._hub.take()])

    def predicted_path(self, t_ns: int, period_ns: int) -> np.ndarray | None:
        """The ground side's prediction of the target over the horizon, None before it has one."""
        if self._track is None or not self._track.ready:
            return None
        return self._track.predict(t_ns, period_ns, self._horizon + 1)[0]

    def close(self) -> None:
        self._bus.close()


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
    period_ns = sc.controller.period_ns
    periods = int(round(duration_s * 1e9 / period_ns)) + 1
    rngs = np.random.default_rng(seed).spawn(len(sc.vehicles) + 1)
    plants = _Plants(sc, seed, rngs[:-1])
    target = _Target(sc, rngs[-1], MemoryHub(sc.name, deliver_immediately=False), sinks)
    judge = _Judge(sc)
    constants = RunConstants.of_scenario(sc, judge.formation.desired_distances())
    for sink in sinks:
        sink.open(constants, run_info or {})
    flush_every = max(1, round(FLUSH_S * 1e9 / period_ns))
    target_states = [TRACKING] * len(sc.vehicles)
    """Each agent's target state (tracking, predicting, ...) as last logged."""
    samples: list[PeriodSample] = []
    for k in range(periods):
        t_ns = k * period_ns
        target.observe(t_ns, pool)
        truths = plants.truths()
        outs, published = pool.step(t_ns, plants.measure(), list(truths) if known_model else None)
        _log_target_states(sinks, t_ns, sc.vehicle_ids, [o for o, _ in outs], target_states)
        sample = judge.sample(t_ns, outs, plants, truths, target.predicted_path(t_ns, period_ns))
        samples.append(sample)
        for sink in sinks:  # (the QP fallbacks become events from the samples)
            sink.log([sample])
            if (k + 1) % flush_every == 0:
                sink.flush()
        pool.deliver(t_ns, published)  # (each plan reaches the others as the period ends)
        if k == periods - 1:
            break
        plants.fly([out.command for out, _ in outs])
        if progress is not None:
            progress((k + 1) * period_ns * 1e-9, duration_s)
    network = _network_report(pool.report(), faults, periods)
    for sink in sinks:
        sink.finish({"network": network})
        sink.close()
    target.close()
    return record_of(constants, samples, network=network)


class _Judge:
    """What the run is judged against, and each period's sample of it: the slots of the
    formation along the true target's path, placed as the agents place them along their
    estimates'."""

    def __init__(self, sc: Scenario) -> None:
        self.formation = Formation(sc.formation)
        limit = reference_course_limit(sc.controller, sc.formation)
        self._reference = FormationReference(self.formation, limit)
        self._target = sc.target
        self._period_s = sc.controller.period_ns * 1e-9
        self._ids = sc.vehicle_ids
        n = len(self._ids)
        self._others = [[j for j in range(n) if j != i] for i in range(n)]
        self._setpoint_rate = np.full(n, 1.0 / self._period_s)  # one command per period

    def sample(
        self,
        t_ns: int,
        outs: list,
        plants: _Plants,
        truths: np.ndarray,
        target_path: np.ndarray | None,
    ) -> PeriodSample:
        """The period's sample: the truth against the slots, and what each agent decided."""
        tgt_pos, tgt_vel = self._target.state_at(t_ns * 1e-9)
        centre, course = self._reference.follow(tgt_pos.tolist(), tgt_vel.tolist(), self._period_s)
        slots = self.formation.slots(np.array([centre]), np.array([course]))[0]
        decided = [o for o, _ in outs]
        return PeriodSample(
            t_ns=t_ns,
            truth=plants.poses(),
            target=tgt_pos,
            target_velocity=tgt_vel,
            slots=slots,
            slot_offsets_world=slots - np.array(centre),
            command=np.array([o.command for o in decided]),
            c=np.array([o.c[0] for o in decided]),
            beta=np.array([o.beta for o in decided]),
            beta_truth=truths,
            qp_ok=np.array([o.qp_ok for o in decided]),
            step_time_ms=np.array([ms for _, ms in outs]),
            min_separation_m=float(plants.min_separation_m),
            plans=np.array([o.plan.states[:, :2] for o in decided]),
            plan_age_s=self._plan_ages(decided),
            setpoint_rate_hz=self._setpoint_rate,
            target_prediction=decided[0].target_prediction_m,
            target_path=target_path,
        )

    def _plan_ages(self, decided: list) -> np.ndarray:
        """Each agent's age of each other vehicle's plan (N, N - 1) [s], nan where it has none."""
        n, ids = len(decided), self._ids
        ages = [o.neighbour_ages_s for o in decided]
        rows = [[ages[i].get(ids[j], np.nan) for j in self._others[i]] for i in range(n)]
        return np.array(rows).reshape(n, n - 1)


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
