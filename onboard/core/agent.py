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
from onboard.core.unicycle import rollout, unwrap, wrap_angle

__all__ = ["Agent", "AgentInput", "AgentOutput"]


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


def _unwrap_near(angles: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return reference + wrap_angle(angles - reference)


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
        self._last_command = np.zeros(2)
        self._last_plan: Plan | None = None
        self.fallbacks = 0
        self.steps = 0

    # -- pieces of a period ---------------------------------------------------------------------
    def _steady_inputs(
        self, slots: np.ndarray, beta: np.ndarray, yaw: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """u_s (M, 2) and steady headings (M + 1,) keeping the learned model on slots (M + 2, 2)."""
        tau = self.settings.period_s
        a_v, a_w, d = beta[0], beta[1], beta[2:]
        g = (slots[1:] - slots[:-1]) / tau - d[None, :]
        speed = np.hypot(g[:, 0], g[:, 1])
        heading = np.arctan2(g[:, 1], g[:, 0])
        still = speed < 1e-3
        if still.any():
            heading[still] = yaw
        heading = unwrap(heading)
        u_s = np.empty((self.settings.horizon, 2))
        u_s[:, 0] = speed[:-1] / a_v
        u_s[:, 1] = np.diff(heading) / (tau * a_w)
        return u_s, heading

    def _pursuit_inputs(
        self, z0: np.ndarray, slots: np.ndarray, slot_vel: np.ndarray, beta: np.ndarray
    ) -> np.ndarray:
        """Inputs of a simple pursuit of the slot, to seed the linearization from far away."""
        s, tau = self.settings, self.settings.period_s
        a_v, a_w, d_x, d_y = (float(b) for b in beta)
        x, y, th = (float(v) for v in z0)
        vx, vy = float(slot_vel[0]), float(slot_vel[1])
        v_max, w_max = s.speed_max_m_s, s.yaw_rate_max_rad_s
        out = []
        for sx, sy in slots[1 : s.horizon + 1].tolist():
            gx, gy = vx + 0.5 * (sx - x) - d_x, vy + 0.5 * (sy - y) - d_y
            err = math.remainder(math.atan2(gy, gx) - th, 2 * math.pi)
            v = min(math.hypot(gx, gy) / a_v * max(math.cos(err), 0.0), v_max)
            w = min(max(err / (tau * a_w), -w_max), w_max)
            out.append((v, w))
            phi = th + 0.5 * tau * a_w * w
            x += tau * (a_v * v * math.cos(phi) + d_x)
            y += tau * (a_v * v * math.sin(phi) + d_y)
            th += tau * a_w * w
        return np.array(out)

    def _seed(
        self, z0: np.ndarray, candidates: list[np.ndarray], beta: np.ndarray, goal: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The candidate input sequence whose learned rollout ends closest to the goal."""
        s = self.settings
        best, best_cost = None, np.inf
        for u in candidates:
            u = np.clip(u, -self.u_max, self.u_max)
            v = u[:, 0]
            u[:, 0] = np.where(
                v < 0,
                np.minimum(v, -s.min_linearization_speed_m_s),
                np.maximum(v, s.min_linearization_speed_m_s),
            )
            z = rollout(z0, u, beta, s.period_s)
            cost = float(np.sum((z[1:, :2] - goal) ** 2))
            if cost < best_cost:
                best, best_cost = (z, u), cost
        assert best is not None
        return best

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
        if inp.measurement is not None and np.all(np.isfinite(inp.measurement)):
            self.dekf.step(np.asarray(inp.measurement, float), applied)
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
        z0 = self.dekf.z.copy()
        beta = self.dekf.beta.copy()
        # Target and slots over j = 0..M+1.
        tgt, tgt_vel = self.target.predict(inp.stamp_ns, s.period_ns, M + 2)
        slots_all = self.formation.slots(tgt, tgt_vel)  # (M+2, N, 2)
        mine = slots_all[:, self.index]
        u_s, heading_s = self._steady_inputs(mine, beta, float(z0[2]))
        # Neighbours.
        N = len(self.neighbour_ids)
        nb_pos = np.zeros((N, M, 2))
        nb_margin = np.full((N, M), np.inf)
        pull = np.zeros((M, 2))
        n_terms = 0
        for k, nid in enumerate(self.neighbour_ids):
            plan = inp.neighbour_plans.get(nid)
            if plan is None or ages[nid] > s.plan_forget_s or ages[nid] < -s.period_s:
                continue
            age = max(ages[nid], 0.0)
            nb_pos[k] = plan.positions_at(
                inp.stamp_ns + s.period_ns, M, max_extrapolation_s=s.plan_extrapolation_s
            )
            nb_margin[k] = s.d_safe_m + 2.0 * self.mpc.tube_radius_m[1:] + s.speed_max_m_s * age
            if age <= s.plan_stale_s:
                kidx = self.fleet_ids.index(nid)
                pull += nb_pos[k] - slots_all[1 : M + 1, kidx]
                n_terms += 1
        weight = s.q_position + n_terms * s.q_formation
        targets = np.empty((M, 3))
        targets[:, :2] = (
            s.q_position * mine[1 : M + 1] + s.q_formation * (n_terms * mine[1 : M + 1] + pull)
        ) / weight
        # Linearization trajectory.
        candidates = [
            u_s.copy(),
            self._pursuit_inputs(z0, mine, (mine[-1] - mine[0]) / ((M + 1) * tau), beta),
        ]
        if self._last_plan is not None:
            candidates.append(np.vstack([self._last_plan.inputs[1:], self._last_plan.inputs[-1:]]))
        lin_states, lin_inputs = self._seed(z0, candidates, beta, targets[:, :2])
        lin_states[:, 2] = unwrap(lin_states[:, 2])
        targets[:, 2] = _unwrap_near(heading_s[1 : M + 1], lin_states[1:, 2])
        n_full = len(self.neighbour_ids)
        data = QpData(
            z0=z0,
            lin_states=lin_states,
            lin_inputs=lin_inputs,
            beta=beta,
            u_s=u_s,
            targets=targets,
            position_weights=np.full(M, weight),
            terminal_scale=weight / (s.q_position + n_full * s.q_formation),
            neighbour_positions=nb_pos,
            neighbour_margins=nb_margin,
        )
        sol = self.mpc.solve(data)
        if sol.ok:
            inputs = np.clip(sol.inputs, -self.u_max, self.u_max)
            states, c, status = sol.learned, sol.c, "solved"
        else:
            self.fallbacks += 1
            ref = np.array([mine[0, 0], mine[0, 1], heading_s[0]])
            u = self._safe_stop(z0, self.mpc.fallback_input(z0, ref, u_s[0]), nb_pos, nb_margin)
            inputs = np.repeat(u[None, :], M, axis=0)
            states, c, status = (
                rollout(z0, inputs, beta, tau),
                np.zeros((M, 2)),
                f"fallback: {sol.status}",
            )
        states = states.copy()
        states[:, 2] = wrap_angle(states[:, 2])
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
            slot_m=mine[0].copy(),
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
