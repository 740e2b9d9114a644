"""One vehicle's controller: `Agent.step` is the same in every runner (lockstep, fleet, real).

Per period: fuse the telemetry into the DEKF (state and learned beta); fuse any target observation
and predict the target over the horizon; place the formation slots; compute the steady-state
inputs u_s under the *learned* model; gather the neighbours' assumed trajectories (extrapolated
while stale, formation term dropped when too old, separation kept and inflated by v_max x age);
pick a linearization trajectory (shifted previous plan, the steady inputs, or a pursuit path toward
the slot — whichever the learned model says ends closer); solve the tube LBMPC QP; on failure apply
the clipped tube feedback law. No I/O, no clocks: time arrives as integer nanoseconds.
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from onboard.core.config import ControllerSettings, FormationSettings, LearningSettings
from onboard.core.dekf import DualEkf
from onboard.core.formation import Formation
from onboard.core.lbmpc import QpData, TubeLbmpc
from onboard.core.plan import Plan
from onboard.core.target_estimator import TargetEstimator
from onboard.core.unicycle import rollout

__all__ = ["Agent", "AgentInput", "AgentOutput"]

_TWO_PI = 2.0 * math.pi


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
        )
        self.formation = Formation(formation)
        self.mpc = TubeLbmpc(controller, n_neighbours=len(self.neighbour_ids))
        self.u_max = self.mpc.u_max
        M = controller.horizon
        self._input_box = (np.tile(-self.u_max, (M, 1)), np.tile(self.u_max, (M, 1)))
        """U's bounds for the M planned inputs (full shape: broadcasting costs a ufunc more)."""
        self._no_positions = [(0.0, 0.0)] * M
        """An absent neighbour's positions (ignored: its margins are infinite)."""
        self._no_margins = [math.inf] * M
        self._margin_m = (controller.d_safe_m + 2.0 * self.mpc.tube_radius_m[1:]).tolist()
        """Separation margin at j = 1..M before the plan-age inflation [m]."""
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
        self.fallbacks = 0
        self.steps = 0

    # -- pieces of a period ---------------------------------------------------------------------
    # Per-horizon quantities (M + 2 points at most) are plain-float lists, and reach the QP as
    # such (it reads them as floats): for a handful of points a float loop is cheaper than numpy
    # calls.
    def _steady_inputs(
        self, slots: list[list[float]], beta: tuple[float, ...], yaw: float
    ) -> tuple[list[tuple[float, float]], list[float]]:
        """u_s (M pairs) and steady headings (M + 1) keeping the learned model on slots (M + 2).

        The ground velocity between consecutive slots, less the learned drift, gives the speed
        and heading; a (nearly) still slot keeps the vehicle's heading; headings are unwrapped.
        """
        tau = self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        hypot, atan2, pi = math.hypot, math.atan2, math.pi
        speeds, headings = [], []
        last = raw_last = None
        x0, y0 = slots[0]
        for x1, y1 in slots[1:]:
            gx, gy = (x1 - x0) / tau - d_x, (y1 - y0) / tau - d_y
            speed = hypot(gx, gy)
            raw = atan2(gy, gx) if speed >= 1e-3 else yaw
            last = raw if raw_last is None else last + (raw - raw_last + pi) % _TWO_PI - pi
            raw_last, x0, y0 = raw, x1, y1
            speeds.append(speed)
            headings.append(last)
        tw = tau * a_w
        steps = zip(speeds[: self.settings.horizon], headings, headings[1:], strict=False)
        u_s = [(v / a_v, (h1 - h0) / tw) for v, h0, h1 in steps]  # (M pairs)
        return u_s, headings

    def _pursuit_inputs(
        self,
        z0: tuple[float, float, float],
        slots: list[list[float]],
        slot_vel: tuple[float, float],
        beta: tuple[float, ...],
    ) -> list[tuple[float, float]]:
        """Inputs of a simple pursuit of the slot, to seed the linearization from far away."""
        s, tau = self.settings, self.settings.period_s
        a_v, a_w, d_x, d_y = beta
        hw, tw = 0.5 * tau * a_w, tau * a_w
        cos, sin, atan2, remainder = math.cos, math.sin, math.atan2, math.remainder
        x, y, th = z0
        vx, vy = slot_vel
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        out = []
        for sx, sy in slots[1 : s.horizon + 1]:
            gx, gy = vx + 0.5 * (sx - x) - d_x, vy + 0.5 * (sy - y) - d_y
            err = remainder(atan2(gy, gx) - th, _TWO_PI)
            toward = cos(err)
            v = math.hypot(gx, gy) / a_v * (0.0 if toward < 0.0 else toward)
            v = v_max if v > v_max else v
            w = err / tw
            w = -w_max if w < -w_max else w_max if w > w_max else w
            out.append((v, w))
            phi = th + hw * w
            x += tau * (a_v * v * cos(phi) + d_x)
            y += tau * (a_v * v * sin(phi) + d_y)
            th += tw * w
        return out

    def _seed(
        self,
        z0: tuple[float, float, float],
        candidates: list[list[tuple[float, float]]],
        beta: tuple[float, ...],
        goal: list[list[float]],
    ) -> tuple[list[tuple[float, float, float]], list[tuple[float, float]]]:
        """The candidate input sequence whose learned rollout ends closest to the goal.

        Each candidate is clipped to U with its speed kept at least min_linearization_speed_m_s
        from 0 (in its own direction), rolled out with the learned model and scored by the
        squared distance of its positions to the goal (M points); returns (states, inputs).
        A rollout stops once its partial score reaches the best so far (the score only grows).
        """
        s = self.settings
        tau = s.period_s
        a_v, a_w, d_x, d_y = beta
        hw, tw = 0.5 * tau * a_w, tau * a_w
        cos, sin = math.cos, math.sin
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        v_min = s.min_linearization_speed_m_s
        best, best_cost = None, math.inf
        for candidate in candidates:
            x, y, th = z0
            states, inputs, cost = [z0], [], 0.0
            for (v, w), (gx, gy) in zip(candidate, goal, strict=True):
                # Clip to U (nan passes through), then keep |v| >= v_min in v's direction.
                v = -v_max if v < -v_max else v_max if v > v_max else v
                w = -w_max if w < -w_max else w_max if w > w_max else w
                if v < 0:
                    v = -v_min if -v_min < v else v
                else:
                    v = v_min if v_min > v else v
                phi = th + hw * w
                x += tau * (a_v * v * cos(phi) + d_x)
                y += tau * (a_v * v * sin(phi) + d_y)
                th += tw * w
                states.append((x, y, th))
                inputs.append((v, w))
                cost += (x - gx) ** 2 + (y - gy) ** 2
                if cost >= best_cost:
                    break
            if cost < best_cost:
                best, best_cost = (states, inputs), cost
        assert best is not None
        return best

    def _neighbours(
        self,
        inp: AgentInput,
        ages: dict[int, float],
        centres: list[tuple[float, float]],
        offsets: list[tuple[float, float]],
    ) -> tuple[
        list[list[tuple[float, float]]], list[list[float]], list[tuple[float, float]] | None, int
    ]:
        """Neighbours' predicted positions and separation margins at j = 1..M, and the pull.

        Returns the positions (N, M, 2; zeros for an absent neighbour), the margins (N, M;
        infinite for an absent neighbour, inflated by v_max x age otherwise), the pull
        sum_k (p_kj - slot_kj) over the neighbours whose plan is fresh (None if there is none)
        and their count. `centres` are the formation centres at j = 0..M+1.
        """
        s, M = self.settings, self.settings.horizon
        when_ns, reach_s = inp.stamp_ns + s.period_ns, s.plan_extrapolation_s
        forget_s, stale_s, ahead_s, v_max = (
            s.plan_forget_s,
            s.plan_stale_s,
            -s.period_s,
            s.speed_max_m_s,
        )
        slot_centres = centres[1 : M + 1]
        nb_pos: list[list[tuple[float, float]]] = []
        nb_margin: list[list[float]] = []
        pull: list[tuple[float, float]] | None = None
        n_terms = 0
        for nid in self.neighbour_ids:
            plan = inp.neighbour_plans.get(nid)
            if plan is None or ages[nid] > forget_s or ages[nid] < ahead_s:
                nb_pos.append(self._no_positions)
                nb_margin.append(self._no_margins)
                continue
            age = ages[nid]
            age = 0.0 if age < 0.0 else age
            positions = plan.position_list(when_ns, M, max_extrapolation_s=reach_s)
            nb_pos.append(positions)
            inflation = v_max * age
            nb_margin.append([m + inflation for m in self._margin_m])
            if age <= stale_s:
                kx, ky = offsets[self._fleet_index[nid]]
                if pull is None:
                    pull = [
                        (px - (cx + kx), py - (cy + ky))
                        for (px, py), (cx, cy) in zip(positions, slot_centres, strict=True)
                    ]
                else:  # the same terms, added as they are formed
                    pull = [
                        (a + (px - (cx + kx)), b + (py - (cy + ky)))
                        for (a, b), (px, py), (cx, cy) in zip(
                            pull, positions, slot_centres, strict=True
                        )
                    ]
                n_terms += 1
        return nb_pos, nb_margin, pull, n_terms

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

    @staticmethod
    def _safe_stop(
        z0: np.ndarray, u: np.ndarray, nb_pos: np.ndarray, nb_margin: np.ndarray
    ) -> np.ndarray:
        """Fallback safety: no forward speed toward a neighbour already inside its margin."""
        heading = np.array([math.cos(z0[2]), math.sin(z0[2])])
        for k in range(nb_pos.shape[0]):
            if not math.isfinite(nb_margin[k, 0]):
                continue
            towards = nb_pos[k, 0] - z0[:2]
            dist = math.hypot(towards[0], towards[1])
            if dist < nb_margin[k, 0] and u[0] * (heading @ towards) > 0:
                return np.array([0.0, u[1]])
        return u

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
        # Target and slots over j = 0..M+1: slot i = target - trail + offsets[i].
        track, tgt_vel = self.target.predicted_track(inp.stamp_ns, s.period_ns, M + 2)
        trail_x, trail_y, offsets = self.formation.placement(tgt_vel)
        centres = [(x - trail_x, y - trail_y) for x, y in track]
        ox, oy = offsets[self.index]
        mine = [(cx + ox, cy + oy) for cx, cy in centres]
        u_s, heading_s = self._steady_inputs(mine, beta_f, z0_f[2])
        nb_pos, nb_margin, pull, n_terms = self._neighbours(inp, ages, centres, offsets)
        weight = s.q_position + n_terms * s.q_formation
        goal = self._goal(mine[1 : M + 1], pull, n_terms, weight)
        # Linearization trajectory.
        (sx0, sy0), (sx1, sy1) = mine[0], mine[-1]
        slot_vel = ((sx1 - sx0) / ((M + 1) * tau), (sy1 - sy0) / ((M + 1) * tau))
        candidates = [u_s, self._pursuit_inputs(z0_f, mine, slot_vel, beta_f)]
        if self._last_plan is not None:
            shifted = self._last_plan.inputs.tolist()
            candidates.append(shifted[1:] + shifted[-1:])
        lin_states, lin_inputs = self._seed(z0_f, candidates, beta_f, goal)
        # (The rollout's headings are continuous from z0's: no unwrapping needed.)
        # Target headings: the steady headings, unwrapped near the linearization's.
        targets = [
            (gx, gy, ref + (h - ref + math.pi) % _TWO_PI - math.pi)
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
            neighbour_positions=nb_pos,
            neighbour_margins=nb_margin,
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
            u = self._safe_stop(z0, u, np.array(nb_pos), np.array(nb_margin))
            inputs = np.repeat(u[None, :], M, axis=0)
            states, c, status = (
                rollout(z0, inputs, beta, tau),
                np.zeros((M, 2)),
                f"fallback: {sol.status}",
            )
        states[:, 2] = [  # wrapped to [-pi, pi), in floats (M + 1 of them)
            (h + math.pi) % _TWO_PI - math.pi for h in states[:, 2].tolist()
        ]
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
        )
