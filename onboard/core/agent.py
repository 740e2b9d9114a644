"""One vehicle's controller: `Agent.step` is the same in every runner (lockstep, fleet, real).

A period is a short sequence of named stages (`Agent.STAGES`; docs/design.md, "The control
period"), each an `Agent` method with explicit inputs and a frozen output
(`fleetmpc.onboard.core.period`):
- learn: fuse the telemetry into the DEKF (state and learned beta) -> `Estimate`;
- observe_target: fuse any target observation -> whether the target is known;
- reference: predict the target over the horizon, place the formation along its path (centre d_s
  of path behind it, reference course rate-limited toward the path's course) and this vehicle's
  slot, with the steady inputs u_s under the learned model -> `Reference`;
- gather: the neighbours' assumed trajectories, the formation pull, the separation half-planes
  and the goal -> `Surroundings` (`fleetmpc.onboard.core.neighbourhood`);
- build_qp: the linearization seed (`fleetmpc.onboard.core.seeding`) and this period's QP data
  -> `QpData`;
- solve: the tube LBMPC QP (`fleetmpc.onboard.core.lbmpc`), or on failure the clipped tube
  feedback law, or, if held over the horizon it would leave a half-plane, the stop or turn that
  leaves them least -> `Decision`;
- emit: the setpoint to send and the plan to broadcast -> `AgentOutput`.
Each stage changes only the components it names (the DEKF; the target filter; the formation
reference; the neighbourhood's crowded count; the seeder's turn; the QP's warm start and the
fallback count; the commands sent and the last plan).
No I/O, no clocks: time arrives as integer nanoseconds. docs/design.md has the maths.
"""

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.onboard.core.condensed_qp import QpData
from fleetmpc.onboard.core.config import ControllerSettings, FormationSettings, LearningSettings
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.onboard.core.fleet_wind import PooledWind, WindPool
from fleetmpc.onboard.core.formation import (
    CourseRateLimit,
    Formation,
    FormationReference,
    course_rate_limit,
)
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.neighbourhood import Neighbourhood
from fleetmpc.onboard.core.period import (
    Decision,
    Estimate,
    Reference,
    Surroundings,
    plan_ages,
    safe_fallback,
)
from fleetmpc.onboard.core.seeding import Seeder
from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.target_watch import TRACKING, TargetWatch
from fleetmpc.onboard.core.tube import InputBox, vehicle_tube
from fleetmpc.onboard.core.unicycle import advance, rollout, wrap
from fleetmpc.protocol.plan import Plan

__all__ = ["Agent", "AgentInput", "AgentOutput", "reference_course_limit", "vehicle_mpc"]


def reference_course_limit(
    controller: ControllerSettings, formation: FormationSettings
) -> CourseRateLimit:
    """How fast the formation's reference course may turn at a target speed, as every agent of
    the fleet computes it (from its tube-tightened input bounds and the formation's lever arms)."""
    shape = Formation(formation)
    return _course_limit(vehicle_tube(controller, formation_terms=shape.max_degree).box, shape)


def vehicle_mpc(controller: ControllerSettings, formation: Formation) -> TubeLbmpc:
    """The tube LBMPC every agent of the fleet builds: separation rows for K = min(
    neighbours_max, N - 1) neighbours, its tube computed with the formation graph's largest
    number of formation terms."""
    return TubeLbmpc(
        controller,
        n_neighbours=min(controller.neighbours_max, formation.size - 1),
        formation_terms=formation.max_degree,
    )


def _course_limit(box: InputBox, formation: Formation) -> CourseRateLimit:
    speed_bound, yaw_rate_bound = box.last
    return course_rate_limit(
        formation, speed_bound_m_s=speed_bound, yaw_rate_bound_rad_s=yaw_rate_bound
    )


@dataclass(frozen=True, eq=False)
class AgentInput:
    """What a runner hands the agent each period."""

    stamp_ns: int
    """Current time on the autopilot's clock [ns]."""
    measurement: np.ndarray | None
    """Latest measured (x_m, y_m, yaw_rad), or None when no new telemetry arrived."""
    target_observation: np.ndarray | None = None
    """A new noisy target position (North, East) [m], or None."""
    target_stamp_ns: int | None = None
    """When the target observation was taken [ns] (defaults to stamp_ns)."""
    neighbour_plans: Mapping[int, Plan] = field(default_factory=dict)
    """Latest assumed trajectory of each neighbour, by vehicle id."""
    applied_input: np.ndarray | None = None
    """Input the vehicle actually flew over the last period (defaults to the last command)."""
    late_s: float = 0.0
    """How long after its period boundary this step runs [s] (a starved or stalled process):
    the vehicle flies its previous command that much longer than the plan assumes."""
    known_beta: np.ndarray | None = None
    """A known-model run's truth: the vehicle's (a_V, a_w) and the wind (North, East) where it
    is now. The agent predicts and plans with it instead of learning (docs/design.md, "The
    known-model run"); None: it learns, as always outside that run."""


@dataclass(frozen=True, eq=False)
class AgentOutput:
    """What the agent decided this period, with diagnostics for telemetry."""

    command: np.ndarray
    """(speed_m_s, yaw_rate_rad_s) to send now, inside U."""
    plan: Plan
    """This vehicle's new assumed trajectory, to broadcast."""
    c: np.ndarray
    """The QP's decision variables (M, 2) (zeros on fallback)."""
    qp_ok: bool
    """False when this period flew the fallback law (its QP failed or did not pass its checks);
    a waiting period solves no QP and falls back from none, so it is True too."""
    status: str
    """"solved", the failure behind a fallback, or why the agent is waiting."""
    state_estimate: np.ndarray
    """DEKF state estimate (3,)."""
    beta: np.ndarray
    """Learned (a_V, a_w, d_x, d_y)."""
    slot_m: np.ndarray
    """This vehicle's current slot position (2,), nan while the target is unknown."""
    neighbour_ages_s: dict[int, float]
    """Age of each neighbour's plan [s]."""
    neighbours: tuple[int, ...]
    """The vehicles this step kept its separation from (its neighbourhood), nearest first."""
    formation_terms: int
    """Neighbours whose formation term entered the cost."""
    target_prediction_m: np.ndarray
    """Where the target is predicted at the end of the horizon (2,) [m], nan while unknown."""
    target_state: str = TRACKING
    """What the formation follows: "tracking", "predicting", "holding" or "reacquiring"
    (`fleetmpc.onboard.core.target_watch`)."""


class Agent:
    """The LBMPC agent of one vehicle."""

    STAGES = ("learn", "observe_target", "place_formation", "gather", "build_qp", "solve", "emit")
    """The period's stages, in order: the methods `step` calls (a benchmark may wrap them)."""

    def __init__(
        self,
        vehicle_id: int,
        *,
        fleet_ids: tuple[int, ...],
        controller: ControllerSettings,
        learning: LearningSettings,
        formation: FormationSettings,
        target_observation_std_m: float,
        response_delay_s: float = 0.0,
    ) -> None:
        if vehicle_id not in fleet_ids:
            raise ValueError(f"vehicle_id {vehicle_id} is not in fleet_ids {fleet_ids}")
        if len(formation.slots_m) != len(fleet_ids):
            raise ValueError("formation.slots_m must have one slot per vehicle in fleet_ids")
        self.vehicle_id = vehicle_id
        self.fleet_ids = fleet_ids
        self.index = fleet_ids.index(vehicle_id)
        self.neighbour_ids = frozenset(fleet_ids) - {vehicle_id}
        self.settings = controller
        self.learning = learning
        self.dekf = DualEkf(learning, tau=controller.period_s)
        self.wind_pool = WindPool(learning, tau=controller.period_s)
        self.target = TargetEstimator(observation_std_m=target_observation_std_m)
        self.target_watch = TargetWatch(
            lost_s=controller.target_lost_s,
            predict_s=controller.target_predict_s,
            reacquire_s=controller.target_reacquire_s,
            glide_speed_m_s=0.5 * controller.speed_max_m_s,
            brake_m_s2=0.25 * controller.speed_rate_max_m_s2,
        )
        self.formation = Formation(formation)
        self.mpc = vehicle_mpc(controller, self.formation)
        self.box = self.mpc.box
        """U and its tube-tightened boxes."""
        self.reference = FormationReference(self.formation, _course_limit(self.box, self.formation))
        """The formation's centre and reference course, along the estimated target path."""
        self._reference_stamp_ns: int | None = None
        self.neighbourhood = Neighbourhood(
            fleet_ids=fleet_ids,
            formation_links=self.formation.links[self.index],
            controller=controller,
            tube_radius_m=float(self.mpc.tube_radius_m[-1]),
        )
        self.seeder = Seeder(controller, self.box)
        self._set_up_weights()
        self._set_up_commands(response_delay_s)
        self._last_plan: Plan | None = None
        self.fallbacks = 0
        self.steps = 0
        self.resumes = 0
        """Steps that came after missed periods (the state filter restarted)."""
        self._last_stamp_ns: int | None = None
        self._resuming = False
        """Periods were missed and no measurement has come since."""

    def _set_up_weights(self) -> None:
        s, terms = self.settings, self.formation.max_degree
        self._position_weights = [
            np.full(s.horizon, s.q_position + n * s.q_formation) for n in range(terms + 1)
        ]
        """Stage position weights by number of formation terms (read-only arrays)."""
        self._full_weight = s.q_position + terms * s.q_formation
        """Stage position weight with every formation term the tube assumes (the terminal
        P's)."""

    def _set_up_commands(self, response_delay_s: float) -> None:
        self._delay_periods = max(0, round(response_delay_s / self.settings.period_s))
        """Periods between a command and the autopilot flying it (the vehicle's
        `response_delay_s`; docs/design.md, "Response delay")."""
        self._sent: deque[np.ndarray] = deque(
            [np.zeros(2)] * (self._delay_periods + 1), maxlen=self._delay_periods + 1
        )
        """The last commands sent, oldest first: the oldest is the one flown over the last
        period, the others are still to be flown; the newest is `_last_command`."""

    def interest(self) -> tuple[tuple[float, float], float, frozenset[int]] | None:
        """What this agent needs to hear, for its plan bus (`PlanBus.listen_near`): the plans
        of vehicles within twice its safety radius of where it is, and always its formation
        neighbours'; None before its state is known (it needs everything)."""
        if not self.dekf.initialized:
            return None
        x, y = self.dekf.z[:2].tolist()
        hood = self.neighbourhood
        return (x, y), 2.0 * hood.radius_m, frozenset(hood.formation_ids)

    @property
    def _last_command(self) -> np.ndarray:
        """The command sent last (zero before any)."""
        return self._sent[-1]

    # -- the period -----------------------------------------------------------------------------
    def step(self, inp: AgentInput) -> AgentOutput:
        """Run one control period: the stages of `STAGES`, in order."""
        self.steps += 1
        estimate = self.learn(inp)
        target_known = self.observe_target(inp)
        if estimate is None or not target_known:
            why = "waiting for telemetry" if estimate is None else "waiting for target"
            return self._wait(inp, estimate, why)
        reference = self.place_formation(estimate)
        surroundings = self.gather(inp, estimate, reference)
        data = self.build_qp(estimate, reference, surroundings)
        decision = self.solve(data, estimate, reference, surroundings)
        return self.emit(decision, estimate, reference, surroundings)

    def _wait(self, inp: AgentInput, estimate: Estimate | None, why: str) -> AgentOutput:
        """Zero command and a standing plan while the agent lacks telemetry or a target."""
        M = self.settings.horizon
        z = np.full(3, np.nan) if estimate is None else np.array(estimate.z_now)
        beta = self.learning.beta_initial if estimate is None else estimate.beta
        decision = Decision(
            inputs=np.zeros((M, 2)),
            states=np.repeat(z[None, :], M + 1, 0),
            c=np.zeros((M, 2)),
            ok=True,
            status=why,
            standing=True,
        )
        z_now = tuple(z.tolist())
        waiting = Estimate(z_now=z_now, z0=z_now, beta=beta, start_ns=inp.stamp_ns)
        ages = plan_ages(inp.stamp_ns, inp.neighbour_plans, self.neighbour_ids)
        return self.emit(decision, waiting, None, Surroundings(ages=ages))

    # -- the stages -----------------------------------------------------------------------------
    def learn(self, inp: AgentInput) -> Estimate | None:
        """The DEKF's update by this period's measurement (or its prediction without one), and
        where the plan starts; None while no measurement has come. Periods missed since the
        last step restart the state filter at the next measurement and drop the last plan."""
        s = self.settings
        applied = (
            self._sent[0] if inp.applied_input is None else np.asarray(inp.applied_input, float)
        )
        y = None if inp.measurement is None else np.asarray(inp.measurement, float)
        if (
            self._last_stamp_ns is not None
            and inp.stamp_ns - self._last_stamp_ns > 1.5 * s.period_ns
        ):
            self._resuming = True  # (until a measurement comes)
        self._last_stamp_ns = inp.stamp_ns
        if y is not None and np.isfinite(y).all():
            if self._resuming and self.dekf.initialized:
                # What the vehicle did meanwhile is not one period of the last command: the
                # filter restarts at the measurement, learning nothing from the gap.
                self.dekf.reset(y)
                self._last_plan = None
                self.resumes += 1
            else:
                shared = self._fleet_wind(inp, y)
                self.dekf.step(y, applied, known_beta=inp.known_beta, shared=shared)
            self._resuming = False
        elif self.dekf.initialized:
            self.dekf.propagate(applied)
        if not self.dekf.initialized:
            return None
        z_now, beta = tuple(self.dekf.z.tolist()), tuple(self.dekf.beta.tolist())
        # The plan starts when its first input will be flown: after the commands already sent
        # and not flown yet, from the state they lead to.
        z0 = z_now
        for v, w in list(self._sent)[1:]:
            z0 = advance(*z0, v, w, beta, s.period_s)
        start_ns = inp.stamp_ns + self._delay_periods * s.period_ns
        wind = self.dekf.wind_sample
        return Estimate(z_now=z_now, z0=z0, beta=beta, start_ns=start_ns, wind=wind)

    def _fleet_wind(self, inp: AgentInput, y: np.ndarray) -> PooledWind | None:
        """The neighbours' wind samples pooled where this vehicle is measured (`fleet_wind`);
        None when it does not listen to them or none came."""
        if not self.learning.fleet_wind:
            return None
        pose = (y.item(0), y.item(1), y.item(2))
        drift = tuple(self.dekf.beta[2:].tolist())
        return self.wind_pool.pool(inp.neighbour_plans.values(), pose, drift, inp.stamp_ns)

    def observe_target(self, inp: AgentInput) -> bool:
        """Fuse a target observation, if one came; True once the target is known."""
        if inp.target_observation is not None:
            t_obs = inp.stamp_ns if inp.target_stamp_ns is None else inp.target_stamp_ns
            self.target_watch.observe(self.target, t_obs, inp.target_observation)
        return self.target.ready

    def place_formation(self, estimate: Estimate) -> Reference:
        """The target predicted over j = 0..M+1 from the plan's start, the formation's centre
        and reference course along its path (the reference follows the estimate now and looks
        ahead along the rest of the track), this vehicle's slot (centre + its offset turned to
        the reference course) and the steady inputs that keep it there. Changes the target
        watch's state (lost, held, reacquired: `TargetWatch.track`) and the formation
        reference, which follows the estimate now (the look-ahead follows a copy)."""
        s, start_ns = self.settings, estimate.start_ns
        track, velocities = self.target_watch.track(
            self.target, start_ns, s.period_ns, s.horizon + 2
        )
        dt_s = s.period_s
        if self._reference_stamp_ns is not None:
            dt_s = (start_ns - self._reference_stamp_ns) * 1e-9
        self._reference_stamp_ns = start_ns
        ref, std = self.reference, self.target.velocity_std_m_s()
        now = ref.follow(track[0], velocities[0], dt_s, velocity_std_m_s=std)
        ahead = ref.ahead(track[1:], velocities[1:], s.period_s, velocity_std_m_s=std)
        centres = [centre for centre, _ in (now, *ahead)]
        offsets = [self.formation.offsets(course) for _, course in (now, *ahead)]
        slots = [
            (cx + o[self.index][0], cy + o[self.index][1])
            for (cx, cy), o in zip(centres, offsets, strict=True)
        ]
        u_s, headings = self.seeder.steady_inputs(slots, list(estimate.beta), estimate.z0[2])
        return Reference(track, centres, offsets, slots, u_s, headings)

    def gather(self, inp: AgentInput, estimate: Estimate, reference: Reference) -> Surroundings:
        """The neighbourhood: the formation pull, the nearest neighbours, the separation
        half-planes between this vehicle's previous plan and theirs, and the goal. Changes
        only the neighbourhood's count of crowded periods."""
        hood, plans, start_ns = self.neighbourhood, inp.neighbour_plans, estimate.start_ns
        s, (x, y, _), beta = self.settings, estimate.z0, estimate.beta
        centres, offsets = reference.centres, reference.offsets
        ages = plan_ages(inp.stamp_ns, plans, self.neighbour_ids)
        pull, n_terms = hood.pull(start_ns, plans, ages, centres, offsets)
        # A late step's plan starts later than its stamp says: the vehicle may be up to
        # v_max x the lateness from where the plan puts it, so it keeps that much more from
        # every neighbour (its half of each line; docs/design.md, "Safety").
        inflations = hood.inflations(ages, inp.late_s)
        here, drift = (x, y), (beta[2], beta[3])
        neighbours = hood.nearest(start_ns, plans, here, inflations, ages, centres[0], offsets[0])
        planes, lines = hood.planes(
            start_ns, neighbours, plans, self._last_plan, here, drift, ages, inflations
        )
        weight = s.q_position + n_terms * s.q_formation
        goal = hood.goal(reference.slots[1 : s.horizon + 1], pull, n_terms, weight)
        goal = hood.give_way(goal, planes, here, self._last_command[0])
        goal = hood.draw_out(goal, lines)
        return Surroundings(ages, tuple(neighbours), n_terms, planes, goal)

    def build_qp(
        self, estimate: Estimate, reference: Reference, surroundings: Surroundings
    ) -> QpData:
        """This period's QP data: the linearization trajectory (the best of the steady inputs,
        a pursuit of the slot and the shifted previous plan, with hysteresis) and the cost
        targets, headings unwrapped near the linearization's. Changes only the seeder's memory
        of the way its pursuit turned."""
        s, M, tau = self.settings, self.settings.horizon, self.settings.period_s
        z0, beta, slots = list(estimate.z0), list(estimate.beta), reference.slots
        (sx0, sy0), (sx1, sy1) = slots[0], slots[-1]
        slot_vel = ((sx1 - sx0) / ((M + 1) * tau), (sy1 - sy0) / ((M + 1) * tau))
        candidates = [reference.u_s, self.seeder.pursuit_inputs(z0, slots, slot_vel, beta)]
        incumbent = None
        if self._last_plan is not None:
            shifted = self._last_plan.inputs.tolist()
            candidates.append(shifted[1:] + shifted[-1:])
            incumbent = len(candidates) - 1
        goal = surroundings.goal
        lin_states, lin_inputs = self.seeder.seed(z0, candidates, beta, goal, incumbent=incumbent)
        targets = [
            (gx, gy, ref + wrap(h - ref))
            for (gx, gy), h, (_, _, ref) in zip(
                goal, reference.headings[1 : M + 1], lin_states[1:], strict=True
            )
        ]
        n_terms = surroundings.formation_terms
        return QpData(
            z0=z0,
            lin_states=lin_states,
            lin_inputs=lin_inputs,
            beta=beta,
            u_s=reference.u_s,
            targets=targets,
            position_weights=self._position_weights[n_terms],
            terminal_scale=(s.q_position + n_terms * s.q_formation) / self._full_weight,
            speed_now_m_s=float(self._last_command[0]),
            yaw_rate_now_rad_s=float(self._last_command[1]),
            separation_planes=surroundings.planes,
        )

    def solve(
        self, data: QpData, estimate: Estimate, reference: Reference, surroundings: Surroundings
    ) -> Decision:
        """The QP's plan, its inputs clipped to U; on failure, the fallback input held over the
        horizon (`_fallback`). Headings wrapped."""
        M = self.settings.horizon
        sol = self.mpc.solve(data)
        if sol.ok:
            inputs, states, c, status = (
                self.box.clip(sol.inputs),
                sol.learned.copy(),
                sol.c,
                "solved",
            )
        else:
            self.fallbacks += 1
            u = self._fallback(estimate, reference, surroundings)
            inputs = np.repeat(u[None, :], M, axis=0)
            states = rollout(estimate.z0, inputs, estimate.beta, self.settings.period_s)
            c, status = np.zeros((M, 2)), f"fallback: {sol.status}"
        states[:, 2] = wrap(states[:, 2])
        return Decision(inputs=inputs, states=states, c=c, ok=sol.ok, status=status)

    def _fallback(
        self, estimate: Estimate, reference: Reference, surroundings: Surroundings
    ) -> np.ndarray:
        """The tube feedback law toward the slot, or, if held over the horizon it would leave
        a separation half-plane, the stop or turn that leaves them least (`safe_fallback`)."""
        (x, y), heading = reference.slots[0], reference.headings[0]
        slot = np.array([x, y, heading])
        u = self.mpc.fallback_input(estimate.z0, slot, np.array(reference.u_s[0]))
        s, z0, beta = self.settings, estimate.z0, estimate.beta
        planes = surroundings.planes
        return safe_fallback(z0, u, beta, planes, box=self.box, horizon=s.horizon, tau=s.period_s)

    def emit(
        self,
        decision: Decision,
        estimate: Estimate,
        reference: Reference | None,
        surroundings: Surroundings,
    ) -> AgentOutput:
        """Send the decision's first input and broadcast its plan, which starts at the estimate's
        start and is the next period's incumbent unless it is a standing one; `reference` None:
        the agent is waiting (no slot, no target prediction)."""
        s = self.settings
        plan = Plan(
            self.vehicle_id,
            estimate.start_ns,
            s.period_ns,
            decision.states,
            decision.inputs,
            estimate.wind,
        )
        self._last_plan = None if decision.standing else plan
        self._sent.append(decision.inputs[0].copy())
        waiting = reference is None
        nowhere = np.full(2, np.nan)
        return AgentOutput(
            command=decision.inputs[0].copy(),
            plan=plan,
            c=decision.c,
            qp_ok=decision.ok,
            status=decision.status,
            state_estimate=np.array(estimate.z0),
            beta=np.array(estimate.beta),
            slot_m=nowhere if waiting else np.array(reference.slots[0]),
            neighbour_ages_s=surroundings.ages,
            neighbours=surroundings.neighbours,
            formation_terms=surroundings.formation_terms,
            target_prediction_m=nowhere.copy() if waiting else np.array(reference.track[s.horizon]),
            target_state=TRACKING if waiting else self.target_watch.state,
        )
