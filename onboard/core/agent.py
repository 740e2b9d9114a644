"""One vehicle's controller: `Agent.step` is the same in every runner (lockstep, fleet, real).

Per period: fuse the telemetry into the DEKF (state and learned beta); fuse any target observation
and predict the target over the horizon (positions and velocities along a possibly curved path);
grow the target's path by the estimate and place the formation at every step along it (its
centre d_s of path behind the predicted target, its reference course rate-limited toward the
path's course there) and the slots around it; compute the steady-state
inputs u_s under the *learned* model from consecutive slots; gather the neighbours' assumed
trajectories (extrapolated while stale, formation term dropped when too old); place the
separation half-planes between this vehicle's previous plan and each neighbour's; pick a
linearization trajectory (the shifted previous plan, kept unless the steady inputs or a pursuit
path toward the slot score clearly better: hysteresis); solve the tube LBMPC QP; on failure apply
the clipped tube feedback law, or, if held over the horizon it would leave a half-plane, the stop
or turn that leaves them least. The neighbours' part is `fleetmpc.onboard.core.neighbourhood`'s,
the linearization seed `fleetmpc.onboard.core.seeding`'s, the QP `fleetmpc.onboard.core.lbmpc`'s.
No I/O, no clocks: time arrives as integer nanoseconds. docs/design.md has the maths.
"""

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.onboard.core.condensed_qp import QpData
from fleetmpc.onboard.core.config import ControllerSettings, FormationSettings, LearningSettings
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.onboard.core.formation import (
    CourseRateLimit,
    Formation,
    FormationReference,
    course_rate_limit,
)
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.neighbourhood import Neighbourhood
from fleetmpc.onboard.core.seeding import Seeder
from fleetmpc.onboard.core.separation import Plane, plane_slack
from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.target_watch import TRACKING, TargetWatch
from fleetmpc.onboard.core.unicycle import advance, rollout, wrap
from fleetmpc.protocol.plan import Plan

__all__ = ["Agent", "AgentInput", "AgentOutput", "reference_course_limit", "vehicle_mpc"]


def reference_course_limit(
    controller: ControllerSettings, formation: FormationSettings
) -> CourseRateLimit:
    """How fast the formation's reference course may turn at a target speed, as every agent of
    the fleet computes it (from its tube-tightened input bounds and the formation's lever arms)."""
    shape = Formation(formation)
    return _course_limit(vehicle_mpc(controller, shape), shape)


def vehicle_mpc(controller: ControllerSettings, formation: Formation) -> TubeLbmpc:
    """The tube LBMPC every agent of the fleet builds: separation rows for K = min(
    neighbours_max, N - 1) neighbours, its tube computed with the formation graph's largest
    number of formation terms."""
    return TubeLbmpc(
        controller,
        n_neighbours=min(controller.neighbours_max, formation.size - 1),
        formation_terms=formation.max_degree,
    )


def _course_limit(mpc: TubeLbmpc, formation: Formation) -> CourseRateLimit:
    speed_bound, yaw_rate_bound = (mpc.u_max - mpc.tightening[-1]).tolist()
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
    """True when the QP solved and passed its checks."""
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
        self.reference = FormationReference(self.formation, _course_limit(self.mpc, self.formation))
        """The formation's centre and reference course, along the estimated target path."""
        self._reference_stamp_ns: int | None = None
        self.u_max = self.mpc.u_max
        M = controller.horizon
        self._input_box = (np.tile(self.mpc.u_min, (M, 1)), np.tile(self.u_max, (M, 1)))
        """U's bounds for the M planned inputs (full shape: broadcasting costs a ufunc more)."""
        self.neighbourhood = Neighbourhood(
            fleet_ids=fleet_ids,
            formation_links=self.formation.links[self.index],
            controller=controller,
            tube_radius_m=float(self.mpc.tube_radius_m[-1]),
        )
        self.seeder = Seeder(controller, self.mpc.input_box)
        terms = self.formation.max_degree
        self._position_weights = [
            np.full(M, controller.q_position + n * controller.q_formation) for n in range(terms + 1)
        ]
        """Stage position weights by number of formation terms (read-only arrays)."""
        self._full_weight = controller.q_position + terms * controller.q_formation
        """Stage position weight with every formation term the tube assumes (the terminal
        P's)."""
        self._delay_periods = max(0, round(response_delay_s / controller.period_s))
        """Periods between a command and the autopilot flying it (the vehicle's
        `response_delay_s`; docs/design.md, "Response delay")."""
        self._sent: deque[np.ndarray] = deque(
            [np.zeros(2)] * (self._delay_periods + 1), maxlen=self._delay_periods + 1
        )
        """The last commands sent, oldest first: the oldest is the one flown over the last
        period, the others are still to be flown; the newest is `_last_command`."""
        self._last_plan: Plan | None = None
        self.fallbacks = 0
        self.steps = 0
        self.resumes = 0
        """Steps that came after missed periods (the state filter restarted)."""
        self._last_stamp_ns: int | None = None
        self._resuming = False
        """Periods were missed and no measurement has come since."""

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

    # -- pieces of a period ---------------------------------------------------------------------
    # Per-horizon quantities (M + 2 points at most) are plain-float lists, and reach the QP as
    # such (it reads them as floats): for a handful of points a float loop is cheaper than numpy
    # calls.
    def _placement(
        self,
        stamp_ns: int,
        track: list[tuple[float, float]],
        velocities: list[tuple[float, float]],
    ) -> list[tuple[tuple[float, float], float]]:
        """The formation's centre and reference course at j = 0..M+1 along the predicted target
        track: the reference follows the estimate now (its path grows by it) and looks ahead
        along the rest of the track, which it leaves as it is."""
        ref, period_s = self.reference, self.settings.period_s
        dt_s = period_s
        if self._reference_stamp_ns is not None:
            dt_s = (stamp_ns - self._reference_stamp_ns) * 1e-9
        self._reference_stamp_ns = stamp_ns
        std = self.target.velocity_std_m_s()
        now = ref.follow(track[0], velocities[0], dt_s, velocity_std_m_s=std)
        return [now, *ref.ahead(track[1:], velocities[1:], period_s, velocity_std_m_s=std)]

    def _safe_fallback(
        self, z0: list[float], u: np.ndarray, beta: list[float], planes: list[list[Plane]]
    ) -> np.ndarray:
        """The fallback input: the tube law `u` if, held over the horizon, it keeps every
        separation half-plane; otherwise, of `u` and the corners and mid-points of U (stop,
        half and full speed, turning either way or not), the input whose rollout leaves the
        half-planes least (the largest smallest slack over steps and neighbours)."""
        s = self.settings
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        candidates = [tuple(u.tolist())] + [
            (v, w) for v in (0.0, 0.5 * v_max, v_max) for w in (-w_max, 0.0, w_max)
        ]
        best, best_slack = candidates[0], -math.inf
        for v, w in candidates:
            z, slack = tuple(z0), math.inf
            for j in range(s.horizon):
                z = advance(*z, v, w, beta, s.period_s)
                slack = min(
                    slack, min((plane_slack(z[0], z[1], p[j]) for p in planes), default=slack)
                )
            if slack >= 0.0 and (v, w) == candidates[0]:
                return u
            if slack > best_slack:
                best, best_slack = (v, w), slack
        return np.array(best)

    # -- the period -----------------------------------------------------------------------------
    def step(self, inp: AgentInput) -> AgentOutput:
        """Run one control period."""
        s = self.settings
        M, tau = s.horizon, s.period_s
        self.steps += 1
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
        if y is not None and all(map(math.isfinite, y.tolist())):
            if self._resuming and self.dekf.initialized:
                # Periods were missed (the agent was late or frozen): what the vehicle did
                # meanwhile is not one period of the last command, so the filter restarts at
                # the measurement, learning nothing from the gap, and the old plan is dropped.
                self.dekf.reset(y)
                self._last_plan = None
                self.resumes += 1
            else:
                self.dekf.step(y, applied, known_beta=inp.known_beta)
            self._resuming = False
        elif self.dekf.initialized:
            self.dekf.propagate(applied)
        if inp.target_observation is not None:
            t_obs = inp.stamp_ns if inp.target_stamp_ns is None else inp.target_stamp_ns
            self.target_watch.observe(self.target, t_obs, inp.target_observation)
        ages = {
            k: (inp.stamp_ns - p.stamp_ns) * 1e-9
            for k, p in inp.neighbour_plans.items()
            if k in self.neighbour_ids
        }
        if not self.dekf.initialized or not self.target.ready:
            return self._hold(
                inp,
                "waiting for telemetry" if not self.dekf.initialized else "waiting for target",
                ages,
            )
        z0, beta = self.dekf.z.copy(), self.dekf.beta.copy()
        # The plan starts when its first input will be flown: after the commands already sent
        # and not flown yet (none unless the autopilot responds late), from the state they lead
        # to; everything below is placed at that time, `start_ns`.
        for v, w in list(self._sent)[1:]:
            z0 = np.array(advance(*z0.tolist(), v, w, beta.tolist(), tau))
        start_ns = inp.stamp_ns + self._delay_periods * s.period_ns
        z0_f, beta_f = z0.tolist(), beta.tolist()
        # The target, the formation's centre and reference course, and the slots over
        # j = 0..M+1: at each step, slot i = centre + offset i turned to the reference course.
        track, velocities = self.target_watch.track(self.target, start_ns, s.period_ns, M + 2)
        placed = self._placement(start_ns, track, velocities)
        centres = [centre for centre, _ in placed]
        offsets = [self.formation.offsets(course) for _, course in placed]
        mine = [
            (cx + o[self.index][0], cy + o[self.index][1])
            for (cx, cy), o in zip(centres, offsets, strict=True)
        ]
        u_s, heading_s = self.seeder.steady_inputs(mine, beta_f, z0_f[2])
        neighbourhood, plans = self.neighbourhood, inp.neighbour_plans
        pull, n_terms = neighbourhood.pull(start_ns, plans, ages, centres, offsets)
        weight = s.q_position + n_terms * s.q_formation
        # A late step's plan starts later than its stamp says: the vehicle may be up to
        # v_max x the lateness from where the plan puts it, so it keeps that much more from
        # every neighbour (its half of each line; docs/design.md, "Safety").
        inflations = neighbourhood.inflations(ages, inp.late_s)
        here, drift = (z0_f[0], z0_f[1]), (beta_f[2], beta_f[3])
        neighbours = neighbourhood.nearest(
            start_ns, plans, here, inflations, ages, centres[0], offsets[0]
        )
        held = neighbourhood.held(neighbours, plans)
        planes, lines = neighbourhood.planes(
            start_ns, neighbours, self._last_plan, here, drift, ages, inflations, held=held
        )
        goal = neighbourhood.goal(mine[1 : M + 1], pull, n_terms, weight)
        goal = neighbourhood.give_way(goal, planes, here, self._last_command[0])
        goal = neighbourhood.draw_out(goal, lines)
        # Linearization trajectory.
        (sx0, sy0), (sx1, sy1) = mine[0], mine[-1]
        slot_vel = ((sx1 - sx0) / ((M + 1) * tau), (sy1 - sy0) / ((M + 1) * tau))
        candidates = [u_s, self.seeder.pursuit_inputs(z0_f, mine, slot_vel, beta_f)]
        incumbent = None
        if self._last_plan is not None:
            shifted = self._last_plan.inputs.tolist()
            candidates.append(shifted[1:] + shifted[-1:])
            incumbent = len(candidates) - 1
        lin_states, lin_inputs = self.seeder.seed(
            z0_f, candidates, beta_f, goal, incumbent=incumbent
        )
        # Target headings: the steady headings, unwrapped near the linearization's (whose
        # rollout headings are continuous from z0's).
        targets = [
            (gx, gy, ref + wrap(h - ref))
            for (gx, gy), h, (_, _, ref) in zip(
                goal, heading_s[1 : M + 1], lin_states[1:], strict=True
            )
        ]
        # The QP reads its data as plain floats: hand them over as they are.
        data = QpData(
            z0=z0_f,
            lin_states=lin_states,
            lin_inputs=lin_inputs,
            beta=beta_f,
            u_s=u_s,
            targets=targets,
            position_weights=self._position_weights[n_terms],
            terminal_scale=weight / self._full_weight,
            speed_now_m_s=float(self._last_command[0]),
            yaw_rate_now_rad_s=float(self._last_command[1]),
            separation_planes=planes,
        )
        sol = self.mpc.solve(data)
        if sol.ok:
            lower, upper = self._input_box
            inputs = np.minimum(np.maximum(sol.inputs, lower), upper)
            states, c, status = sol.learned.copy(), sol.c, "solved"
        else:
            self.fallbacks += 1
            ref = np.array([mine[0][0], mine[0][1], heading_s[0]])
            u = self.mpc.fallback_input(z0, ref, np.array(u_s[0]))
            u = self._safe_fallback(z0_f, u, beta_f, planes)
            inputs = np.repeat(u[None, :], M, axis=0)
            states, c, status = (
                rollout(z0, inputs, beta, tau),
                np.zeros((M, 2)),
                f"fallback: {sol.status}",
            )
        states[:, 2] = [wrap(h) for h in states[:, 2].tolist()]
        plan = Plan(self.vehicle_id, start_ns, s.period_ns, states, inputs)
        self._last_plan = plan
        self._sent.append(inputs[0].copy())
        return AgentOutput(
            command=inputs[0].copy(),
            plan=plan,
            c=c,
            qp_ok=sol.ok,
            status=status,
            state_estimate=z0,
            beta=beta,
            slot_m=np.array(mine[0]),
            neighbour_ages_s=ages,
            neighbours=tuple(neighbours),
            formation_terms=n_terms,
            target_prediction_m=np.array(track[M]),
            target_state=self.target_watch.state,
        )

    def _hold(self, inp: AgentInput, why: str, ages: dict[int, float]) -> AgentOutput:
        """Zero command and a standing plan while the agent lacks telemetry or a target."""
        s = self.settings
        z = self.dekf.z.copy() if self.dekf.initialized else np.full(3, np.nan)
        self._sent.append(np.zeros(2))
        plan = Plan(
            self.vehicle_id,
            inp.stamp_ns,
            s.period_ns,
            np.repeat(z[None, :], s.horizon + 1, 0),
            np.zeros((s.horizon, 2)),
        )
        self._last_plan = None
        return AgentOutput(
            command=np.zeros(2),
            plan=plan,
            c=np.zeros((s.horizon, 2)),
            qp_ok=False,
            status=why,
            state_estimate=z,
            beta=self.dekf.beta.copy()
            if self.dekf.initialized
            else np.array(self.learning.beta_initial),
            slot_m=np.full(2, np.nan),
            neighbour_ages_s=ages,
            neighbours=(),
            formation_terms=0,
            target_prediction_m=np.full(2, np.nan),
        )
