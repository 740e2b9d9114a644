"""One vehicle's controller: `Agent.step` is the same in every runner (lockstep, fleet, real).

Per period: fuse the telemetry into the DEKF (state and learned beta); fuse any target observation
and predict the target over the horizon (positions and velocities along a possibly curved path);
advance the formation's reference course, rate-limited, along that path and place the slots of
every step at the predicted target and reference course of that step; compute the steady-state
inputs u_s under the *learned* model from consecutive slots; gather the neighbours' assumed
trajectories (extrapolated while stale, formation term dropped when too old); place the
separation half-planes between this vehicle's previous plan and each neighbour's; pick a
linearization trajectory (the shifted previous plan, kept unless the steady inputs or a pursuit
path toward the slot score clearly better: hysteresis); solve the tube LBMPC QP; on failure apply
the clipped tube feedback law, or, if held over the horizon it would leave a half-plane, the stop
or turn that leaves them least.
No I/O, no clocks: time arrives as integer nanoseconds. docs/design.md has the maths.
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.onboard.core.config import ControllerSettings, FormationSettings, LearningSettings
from fleetmpc.onboard.core.dekf import DualEkf
from fleetmpc.onboard.core.formation import Formation, ReferenceCourse, course_rate_limit
from fleetmpc.onboard.core.lbmpc import QpData, TubeLbmpc
from fleetmpc.onboard.core.separation import (
    NO_PLANE,
    Plane,
    intersample_allowance,
    plane_slack,
    separation_planes,
)
from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.unicycle import advance, rollout, wrap
from fleetmpc.protocol.plan import Plan

__all__ = ["Agent", "AgentInput", "AgentOutput", "reference_course_rate"]

_TWO_PI = 2.0 * math.pi

_BEHIND_RAD = 2.0
"""A pursuit whose goal lies more than this far off the nose keeps turning the way it turned the
period before (a goal right behind is as near turning left as right)."""


def reference_course_rate(controller: ControllerSettings, formation: FormationSettings) -> float:
    """How fast the formation's reference course may turn [rad/s], as every agent of the fleet
    computes it (from its tube-tightened input bounds and the formation's lever arms)."""
    mpc = TubeLbmpc(controller, n_neighbours=len(formation.slots_m) - 1)
    return _course_rate(mpc, Formation(formation), controller)


def _course_rate(mpc: TubeLbmpc, formation: Formation, controller: ControllerSettings) -> float:
    speed_bound, yaw_rate_bound = (mpc.u_max - mpc.tightening[-1]).tolist()
    return course_rate_limit(
        formation,
        speed_bound_m_s=speed_bound,
        yaw_rate_bound_rad_s=yaw_rate_bound,
        cruise_speed_m_s=controller.reference_speed_m_s,
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
    formation_terms: int
    """Neighbours whose formation term entered the cost."""
    target_prediction_m: np.ndarray
    """Where the target is predicted at the end of the horizon (2,) [m], nan while unknown."""


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
    ) -> None:
        if vehicle_id not in fleet_ids:
            raise ValueError(f"vehicle_id {vehicle_id} is not in fleet_ids {fleet_ids}")
        if len(formation.slots_m) != len(fleet_ids):
            raise ValueError("formation.slots_m must have one slot per vehicle in fleet_ids")
        self.vehicle_id = vehicle_id
        self.fleet_ids = fleet_ids
        self.index = fleet_ids.index(vehicle_id)
        self.neighbour_ids = tuple(i for i in fleet_ids if i != vehicle_id)
        self.settings = controller
        self.learning = learning
        self.dekf = DualEkf(learning, tau=controller.period_s)
        self.target = TargetEstimator(
            observation_std_m=target_observation_std_m,
            accel_std_m_s2=controller.target_accel_std_m_s2,
            turn_accel_std_rad_s2=controller.target_turn_accel_std_rad_s2,
        )
        self.formation = Formation(formation)
        self.mpc = TubeLbmpc(controller, n_neighbours=len(self.neighbour_ids))
        self.reference = ReferenceCourse(_course_rate(self.mpc, self.formation, controller))
        self._reference_stamp_ns = 0
        self._course_locked = False
        """True once the target's course was known well enough to rate-limit the reference."""
        self.u_max = self.mpc.u_max
        M = controller.horizon
        self._input_box = (np.tile(self.mpc.u_min, (M, 1)), np.tile(self.u_max, (M, 1)))
        """U's bounds for the M planned inputs (full shape: broadcasting costs a ufunc more)."""
        self._no_planes = [NO_PLANE] * M
        between = intersample_allowance(
            speed_max_m_s=controller.speed_max_m_s,
            period_s=controller.period_s,
            d_safe_m=controller.d_safe_m,
        )
        tube_m = float(self.mpc.tube_radius_m[-1])
        self._margin_m = 0.5 * (controller.d_safe_m + between) + tube_m
        """Distance kept from a shared separation line before the plan-age inflation
        (`fleetmpc.onboard.core.separation`) [m]."""
        self._alone_margin_m = controller.d_safe_m + between + tube_m
        """Distance kept from a stale neighbour's position before the plan-age inflation [m]."""
        self._position_weights = [
            np.full(M, controller.q_position + n * controller.q_formation)
            for n in range(len(self.neighbour_ids) + 1)
        ]
        """Stage position weights by number of formation terms (read-only arrays)."""
        self._fleet_index = {vid: i for i, vid in enumerate(fleet_ids)}
        N = len(self.neighbour_ids)
        self._full_weight = controller.q_position + N * controller.q_formation
        """Stage position weight with every formation term (the terminal P's)."""
        self._last_command = np.zeros(2)
        self._last_plan: Plan | None = None
        self._turn_sign = 0
        """The way the pursuit seed turned toward a goal behind (+1, -1), 0 when it was not."""
        self.fallbacks = 0
        self.steps = 0

    # -- pieces of a period ---------------------------------------------------------------------
    # Per-horizon quantities (M + 2 points at most) are plain-float lists, and reach the QP as
    # such (it reads them as floats): for a handful of points a float loop is cheaper than numpy
    # calls.
    def _reference_courses(
        self, stamp_ns: int, velocities: list[tuple[float, float]]
    ) -> list[float]:
        """The formation's reference course at j = 0..M+1 along the predicted target path.

        Until the target's course is known (its speed at least three standard deviations of its
        estimate), the reference takes the estimated course as it is; from then on it turns at
        most at its rate limit, now and along the prediction. A target that never moved leaves
        the course at 0 (North).
        """
        ref, v0, turn_rate = self.reference, velocities[0], self.target.turn_rate_rad_s
        if self._course_locked:
            dt_s = (stamp_ns - self._reference_stamp_ns) * 1e-9
            ref.follow(v0, dt_s, turn_rate_rad_s=turn_rate)
        else:
            ref.reset(v0)
            speed = math.hypot(*v0)
            self._course_locked = (
                ref.value is not None and speed >= 3.0 * self.target.velocity_std_m_s()
            )
        self._reference_stamp_ns = stamp_ns
        if ref.value is None:
            return [0.0] * len(velocities)
        ahead = ref.ahead(velocities[1:], self.settings.period_s, turn_rate_rad_s=turn_rate)
        return [ref.value, *ahead]

    def _steady_inputs(
        self, slots: list[tuple[float, float]], beta: list[float], yaw: float
    ) -> tuple[list[tuple[float, float]], list[float]]:
        """u_s (M pairs) and steady headings (M + 1) keeping the learned model on slots (M + 2).

        The ground velocity between consecutive slots, less the learned drift, gives the speed and
        the course of each chord (a (nearly) still slot keeps the vehicle's heading). The model
        flies a step along its midpoint heading (`fleetmpc.onboard.core.unicycle`), so the heading
        at a slot is the mean of the courses of the chords either side of it, and a step along a
        chord then keeps to it (exactly, when the slots turn steadily). Headings are unwrapped.
        """
        tau = self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        speeds, courses = [], []
        (x0, y0), raw_last = slots[0], None
        for x1, y1 in slots[1:]:
            gx, gy = (x1 - x0) / tau - d_x, (y1 - y0) / tau - d_y
            speed = math.hypot(gx, gy)
            raw = math.atan2(gy, gx) if speed >= 1e-3 else yaw
            courses.append(raw if raw_last is None else courses[-1] + wrap(raw - raw_last))
            raw_last, x0, y0 = raw, x1, y1
            speeds.append(speed)
        c0, c1 = courses[0], courses[1]
        ahead = zip(courses, courses[1:], strict=False)
        headings = [c0 - 0.5 * (c1 - c0)] + [0.5 * (a + b) for a, b in ahead]
        tw = tau * a_w
        steps = zip(speeds, headings, headings[1:], strict=False)
        u_s = [(v / a_v, (h1 - h0) / tw) for v, h0, h1 in steps]  # (M pairs)
        return u_s, headings

    def _pursuit_inputs(
        self,
        z0: list[float],
        slots: list[tuple[float, float]],
        slot_vel: tuple[float, float],
        beta: list[float],
    ) -> list[tuple[float, float]]:
        """Inputs of a simple pursuit of the slot, to seed the linearization from far away.

        A goal (nearly) behind the vehicle is turned toward the way it was the period before,
        so that the seed does not flip between a left and a right turn.
        """
        s, tau = self.settings, self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        x, y, th = z0
        vx, vy = slot_vel
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        out = []
        turn = self._turn_sign
        for j, (sx, sy) in enumerate(slots[1 : s.horizon + 1]):
            gx, gy = vx + 0.5 * (sx - x) - d_x, vy + 0.5 * (sy - y) - d_y
            err = wrap(math.atan2(gy, gx) - th)
            if abs(err) > _BEHIND_RAD:
                if turn and err * turn < 0:
                    err += _TWO_PI * turn
                turn = 1 if err > 0 else -1
            elif j == 0:
                turn = 0
            if j == 0:
                self._turn_sign = turn
            v = math.hypot(gx, gy) / a_v * max(math.cos(err), 0.0)
            w = max(-w_max, min(w_max, err / (tau * a_w)))
            out.append((min(v, v_max), w))
            x, y, th = advance(x, y, th, out[-1][0], w, beta, tau)
        return out

    def _seed(
        self,
        z0: list[float],
        candidates: list[list[tuple[float, float]]],
        beta: list[float],
        goal: list[tuple[float, float]],
        *,
        incumbent: int | None,
    ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float]]]:
        """The linearization trajectory: (states, inputs) of one candidate input sequence.

        Each candidate is clipped to the tube-tightened U with its speed kept at least
        min_linearization_speed_m_s, rolled out with the learned model and scored by the
        squared distance of its positions to the goal (M points). The incumbent (the previous
        plan, shifted) is kept unless another candidate scores at most seed_switch_ratio of it.
        """
        s = self.settings
        v_min = s.min_linearization_speed_m_s
        scored = []
        for candidate in candidates:
            z = tuple(z0)
            states, inputs, cost = [z], [], 0.0
            steps = zip(candidate, goal, self.mpc.input_box, strict=True)
            for (v, w), (gx, gy), (_, w_lo, v_hi, w_hi) in steps:
                v = max(v_min, min(v_hi, v))
                w = max(w_lo, min(w_hi, w))
                z = advance(*z, v, w, beta, s.period_s)
                states.append(z)
                inputs.append((v, w))
                cost += (z[0] - gx) ** 2 + (z[1] - gy) ** 2
            scored.append((cost, states, inputs))
        best = min(range(len(scored)), key=lambda i: scored[i][0])
        if incumbent is not None and scored[best][0] > s.seed_switch_ratio * scored[incumbent][0]:
            best = incumbent
        return scored[best][1], scored[best][2]

    def _neighbours(
        self,
        inp: AgentInput,
        ages: dict[int, float],
        centres: list[tuple[float, float]],
        offsets: list[list[tuple[float, float]]],
    ) -> tuple[list[float], list[tuple[float, float]] | None, int]:
        """The neighbours' plan-age inflations and their pull on this vehicle's goal.

        Returns the margin inflation v_max x (age beyond one period) of each neighbour [m]
        (infinite for an absent or forgotten one), the pull sum_k (p_kj - slot_kj) at
        j = 1..M over the neighbours whose plan is fresh (None if there is none) and their
        count. `centres` and `offsets` are the formation's centre and every vehicle's
        offset at j = 0..M+1.
        """
        s, M = self.settings, self.settings.horizon
        when_ns = inp.stamp_ns + s.period_ns
        inflations: list[float] = []
        pull: list[tuple[float, float]] | None = None
        n_terms = 0
        steps = list(zip(centres[1 : M + 1], offsets[1 : M + 1], strict=True))
        for nid in self.neighbour_ids:
            plan = inp.neighbour_plans.get(nid)
            age = ages.get(nid, math.inf)
            if plan is None or age > s.plan_forget_s or age < -s.period_s:
                inflations.append(math.inf)
                continue
            inflations.append(s.speed_max_m_s * max(0.0, age - s.period_s))
            if age <= s.plan_stale_s:
                reach = s.plan_extrapolation_s
                positions = plan.position_list(when_ns, M, max_extrapolation_s=reach)
                k = self._fleet_index[nid]
                terms = [
                    (px - (cx + o[k][0]), py - (cy + o[k][1]))
                    for (px, py), ((cx, cy), o) in zip(positions, steps, strict=True)
                ]
                pull = (
                    terms
                    if pull is None
                    else [(a + b, c + d) for (a, c), (b, d) in zip(pull, terms, strict=True)]
                )
                n_terms += 1
        return inflations, pull, n_terms

    def _planes(
        self,
        inp: AgentInput,
        here: tuple[float, float],
        drift: tuple[float, float],
        ages: dict[int, float],
        inflations: list[float],
    ) -> list[list[Plane]]:
        """Separation half-planes against each neighbour at j = 1..M (`separation_planes`),
        between where this vehicle's previous plan (or, without one, the vehicle) and the
        neighbour's plan are now; the distance is shared while the neighbour's plan is at most
        two periods old."""
        s, M = self.settings, self.settings.horizon
        own = here if self._last_plan is None else self._last_plan.position_at(inp.stamp_ns)
        drift_steps = [
            (drift[0] * j * s.period_s, drift[1] * j * s.period_s) for j in range(1, M + 1)
        ]
        planes = []
        for nid, inflation in zip(self.neighbour_ids, inflations, strict=True):
            plan = inp.neighbour_plans.get(nid)
            if plan is None or not math.isfinite(inflation):
                planes.append(self._no_planes)
                continue
            shared = ages[nid] <= 2.0 * s.period_s + 1e-9
            margin = (self._margin_m if shared else self._alone_margin_m) + inflation
            theirs = plan.position_at(inp.stamp_ns)
            planes.append(separation_planes(own, theirs, margin, here, drift_steps, shared=shared))
        return planes

    def _goal(
        self,
        slots: list[tuple[float, float]],
        pull: list[tuple[float, float]] | None,
        n_terms: int,
        weight: float,
    ) -> list[tuple[float, float]]:
        """Position targets at j = 1..M: the slot pulled toward where the neighbours' plans put
        it, (q_p slot + q_f (n slot + pull)) / (q_p + n q_f)."""
        q_p, q_f = self.settings.q_position, self.settings.q_formation
        if pull is None:
            return [(q_p * x / weight, q_p * y / weight) for x, y in slots]
        return [
            (
                (q_p * x + q_f * (n_terms * x + px)) / weight,
                (q_p * y + q_f * (n_terms * y + py)) / weight,
            )
            for (x, y), (px, py) in zip(slots, pull, strict=True)
        ]

    def _give_way(
        self,
        goal: list[tuple[float, float]],
        planes: list[list[Plane]],
        here: tuple[float, float],
    ) -> list[tuple[float, float]]:
        """The goal moved to the right of every neighbour it lies behind: the rule of the road
        that breaks a deadlock.

        Two vehicles whose goals lie beyond each other's separation lines would stop nose to
        nose, each holding its side. When the vehicle has (nearly) stopped (flying slower than
        min_linearization_speed_m_s), its goal's last point lies beyond a neighbour's line and
        it is within its margin of that line, every goal point moves along the line, to the
        right of the way toward the neighbour, by twice the margin; both vehicles do so, each to
        its own right, and they slide past each other as two ships keep to starboard.
        """
        if self._last_command[0] >= self.settings.min_linearization_speed_m_s:
            return goal  # (still under way: not stuck)
        shift_x = shift_y = 0.0
        (gx, gy), (hx, hy) = goal[-1], here
        for plane in planes:
            nx, ny, b = plane[-1]
            if not math.isfinite(b):
                continue
            beyond = nx * gx + ny * gy < b
            pressed = nx * hx + ny * hy - b < self._margin_m
            if beyond and pressed:
                # Toward the neighbour is -n; its right (NED: a positive rotation) is (n_y, -n_x).
                shift_x += 2.0 * self._margin_m * ny
                shift_y -= 2.0 * self._margin_m * nx
        if shift_x == shift_y == 0.0:
            return goal
        return [(x + shift_x, y + shift_y) for x, y in goal]

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
            self._last_command
            if inp.applied_input is None
            else np.asarray(inp.applied_input, float)
        )
        y = None if inp.measurement is None else np.asarray(inp.measurement, float)
        if y is not None and all(map(math.isfinite, y.tolist())):
            self.dekf.step(y, applied)
        elif self.dekf.initialized:
            self.dekf.propagate(applied)
        if inp.target_observation is not None:
            t_obs = inp.stamp_ns if inp.target_stamp_ns is None else inp.target_stamp_ns
            self.target.observe(t_obs, inp.target_observation)
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
        z0_f, beta_f = z0.tolist(), beta.tolist()
        # The target, the reference course and the slots over j = 0..M+1: at each step, slot
        # i = target - trail + offset i, both turned to that step's reference course.
        track, velocities = self.target.predicted_track(inp.stamp_ns, s.period_ns, M + 2)
        centres, offsets = [], []
        for (tx, ty), course in zip(
            track, self._reference_courses(inp.stamp_ns, velocities), strict=True
        ):
            trail_x, trail_y, step_offsets = self.formation.placement(course)
            centres.append((tx - trail_x, ty - trail_y))
            offsets.append(step_offsets)
        mine = [
            (cx + o[self.index][0], cy + o[self.index][1])
            for (cx, cy), o in zip(centres, offsets, strict=True)
        ]
        u_s, heading_s = self._steady_inputs(mine, beta_f, z0_f[2])
        inflations, pull, n_terms = self._neighbours(inp, ages, centres, offsets)
        weight = s.q_position + n_terms * s.q_formation
        planes = self._planes(inp, (z0_f[0], z0_f[1]), (beta_f[2], beta_f[3]), ages, inflations)
        goal = self._goal(mine[1 : M + 1], pull, n_terms, weight)
        goal = self._give_way(goal, planes, (z0_f[0], z0_f[1]))
        # Linearization trajectory.
        (sx0, sy0), (sx1, sy1) = mine[0], mine[-1]
        slot_vel = ((sx1 - sx0) / ((M + 1) * tau), (sy1 - sy0) / ((M + 1) * tau))
        candidates = [u_s, self._pursuit_inputs(z0_f, mine, slot_vel, beta_f)]
        incumbent = None
        if self._last_plan is not None:
            shifted = self._last_plan.inputs.tolist()
            candidates.append(shifted[1:] + shifted[-1:])
            incumbent = len(candidates) - 1
        lin_states, lin_inputs = self._seed(z0_f, candidates, beta_f, goal, incumbent=incumbent)
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
        plan = Plan(self.vehicle_id, inp.stamp_ns, s.period_ns, states, inputs)
        self._last_plan = plan
        self._last_command = inputs[0].copy()
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
            formation_terms=n_terms,
            target_prediction_m=np.array(track[M]),
        )

    def _hold(self, inp: AgentInput, why: str, ages: dict[int, float]) -> AgentOutput:
        """Zero command and a standing plan while the agent lacks telemetry or a target."""
        s = self.settings
        z = self.dekf.z.copy() if self.dekf.initialized else np.full(3, np.nan)
        self._last_command = np.zeros(2)
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
            formation_terms=0,
            target_prediction_m=np.full(2, np.nan),
        )
