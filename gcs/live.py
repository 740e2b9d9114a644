"""A flight record assembled live from what a ground station receives.

`LiveRecord` takes timestamped telemetry (vehicle positions and headings in fleet time), the
agents' plans and statuses and the target's observations, and turns them into the same
`FlightRecord` the lockstep simulation produces, on the control-period grid, so the metrics,
the figures and the recording are computed by the same code for both.

What each FlightRecord field holds in a live run:

- `truth`: the vehicle's reported position and heading (telemetry, so with the sensor noise),
  interpolated linearly to the period times; a vehicle with no telemetry falls back to the
  first state of its plans (the agent's estimate);
- `target`, `target_velocity`, `slots`, `slot_offsets_world`, `beta_truth`: from the scenario's
  scripted target and truth parameters (what the scenario knows);
- `command`, `qp_ok`, `step_time_ms`: from the plan stamped at that period (the plan's first
  input is the command the agent sent), held from the previous period if that plan is missing;
- `c`: only the norm of c_0 travels on the wire; it is stored in the first component;
- `beta`: the latest status at or before the period;
- `min_separation_m`: over the telemetry interpolated on the plant tick of the scenario.
"""

import math
from bisect import bisect_right
from dataclasses import dataclass, field

import numpy as np

from gcs.record import FlightRecord
from onboard.core.formation import Formation
from onboard.core.target_estimator import TargetEstimator
from protocol.messages import PlanMessage, StatusMessage, TargetObservation
from protocol.scenario import Scenario

__all__ = ["LiveRecord", "formation_reference"]


def formation_reference(
    formation: Formation, trail_m: float, target_m: np.ndarray, target_velocity_m_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slots (N, 2) of the true target and each slot's offset from the formation centre (N, 2)."""
    slots = formation.slots(np.asarray(target_m)[None, :], target_velocity_m_s)[0]
    course = formation.course(target_velocity_m_s)
    centre = target_m - trail_m * np.array([math.cos(course), math.sin(course)])
    return slots, slots - centre[None, :]


@dataclass
class _Track:
    """One vehicle's timestamped samples (fleet seconds), in arrival order per source."""

    t_s: list[float] = field(default_factory=list)
    pose: list[tuple[float, float, float]] = field(default_factory=list)
    plans: dict[int, PlanMessage] = field(default_factory=dict)
    """Plans by period index."""
    status_t_s: list[float] = field(default_factory=list)
    statuses: list[StatusMessage] = field(default_factory=list)


class LiveRecord:
    """Collects a live run; `record(periods)` gives the FlightRecord of its first periods."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.period_ns = scenario.controller.period_ns
        self.ids = scenario.vehicle_ids
        self._tracks = {vid: _Track() for vid in self.ids}
        self._formation = Formation(scenario.formation)
        self._target = TargetEstimator(
            observation_std_m=max(scenario.target.observation_noise_m, 1e-3),
            accel_std_m_s2=scenario.controller.target_accel_std_m_s2,
        )
        self.target_observations = 0

    # -- inputs -----------------------------------------------------------------------------------
    def add_pose(self, vehicle_id: int, t_s: float, north_m: float, east_m: float, yaw_rad: float):
        """A telemetry sample of a vehicle at fleet time `t_s`; out-of-order samples are dropped."""
        track = self._tracks.get(vehicle_id)
        if track is None or not all(map(math.isfinite, (t_s, north_m, east_m, yaw_rad))):
            return
        if track.t_s and t_s <= track.t_s[-1]:
            return
        track.t_s.append(t_s)
        track.pose.append((north_m, east_m, yaw_rad))

    def add_plan(self, message: PlanMessage) -> None:
        track = self._tracks.get(message.sender_id)
        if track is not None and message.stamp_ns % self.period_ns == 0:
            track.plans[message.stamp_ns // self.period_ns] = message

    def add_status(self, message: StatusMessage) -> None:
        track = self._tracks.get(message.sender_id)
        t_s = message.stamp_ns * 1e-9
        if track is not None and (not track.status_t_s or t_s > track.status_t_s[-1]):
            track.status_t_s.append(t_s)
            track.statuses.append(message)

    def add_target(self, message: TargetObservation) -> None:
        if self._target.observe(message.stamp_ns, np.array([message.north_m, message.east_m])):
            self.target_observations += 1

    # -- queries ----------------------------------------------------------------------------------
    def latest_time_s(self, vehicle_id: int) -> float | None:
        """Fleet time of the vehicle's newest position (telemetry or, without it, plan)."""
        track = self._tracks[vehicle_id]
        if track.t_s:
            return track.t_s[-1]
        if track.plans:
            return max(track.plans) * self.period_ns * 1e-9
        return None

    def complete_periods(self) -> int:
        """Periods whose time every vehicle's position has passed (so they can be interpolated)."""
        times = [self.latest_time_s(vid) for vid in self.ids]
        if any(t is None for t in times):
            return 0
        return max(0, int(math.floor(min(times) * 1e9 / self.period_ns)) + 1)

    def latest_status(self, vehicle_id: int) -> StatusMessage | None:
        statuses = self._tracks[vehicle_id].statuses
        return statuses[-1] if statuses else None

    def latest_plan(self, vehicle_id: int) -> PlanMessage | None:
        plans = self._tracks[vehicle_id].plans
        return plans[max(plans)] if plans else None

    def target_prediction(self, stamp_ns: int) -> np.ndarray | None:
        """The ground station's own constant-velocity prediction of the target over the horizon."""
        if not self._target.ready:
            return None
        pos, _ = self._target.predict(
            stamp_ns, self.period_ns, self.scenario.controller.horizon + 1
        )
        return pos

    # -- the record -------------------------------------------------------------------------------
    def _poses(self, vehicle_id: int, t_s: np.ndarray) -> np.ndarray:
        track = self._tracks[vehicle_id]
        if track.t_s:
            ts = np.asarray(track.t_s)
            pose = np.asarray(track.pose)
            yaw = np.unwrap(pose[:, 2])
            cols = [np.interp(t_s, ts, pose[:, 0]), np.interp(t_s, ts, pose[:, 1])]
            return np.stack([*cols, np.interp(t_s, ts, yaw)], axis=-1)
        out = np.full((len(t_s), 3), np.nan)
        ks = sorted(track.plans)
        for j, t in enumerate(t_s):
            i = bisect_right(ks, round(t * 1e9 / self.period_ns)) - 1
            if i >= 0:
                out[j] = track.plans[ks[i]].plan.states[0]
        return out

    def record(self, periods: int | None = None) -> FlightRecord:
        """The FlightRecord of periods 0 .. `periods` - 1 (default: every complete period)."""
        sc = self.scenario
        k_n = self.complete_periods() if periods is None else periods
        if k_n < 1:
            raise ValueError("no complete control period yet")
        n = len(self.ids)
        t_s = np.arange(k_n) * self.period_ns * 1e-9
        truth = np.stack([self._poses(vid, t_s) for vid in self.ids], axis=1)
        target = np.empty((k_n, 2))
        target_vel = np.empty((k_n, 2))
        slots = np.empty((k_n, n, 2))
        offsets = np.empty((k_n, n, 2))
        for k, t in enumerate(t_s):
            target[k], target_vel[k] = sc.target.state_at(float(t))
            slots[k], offsets[k] = formation_reference(
                self._formation, sc.formation.trail_m, target[k], target_vel[k]
            )
        command = np.full((k_n, n, 2), np.nan)
        c = np.full((k_n, n, 2), np.nan)
        qp_ok = np.ones((k_n, n), dtype=bool)
        step_ms = np.full((k_n, n), np.nan)
        beta = np.full((k_n, n, 4), np.nan)
        beta_truth = np.empty((k_n, n, 4))
        for i, vid in enumerate(self.ids):
            track = self._tracks[vid]
            truth_params = sc.vehicle(vid).truth
            held = None
            for k in range(k_n):
                msg = track.plans.get(k)
                if msg is not None:
                    held = msg
                    step_ms[k, i] = msg.status.solve_time_us * 1e-3
                    qp_ok[k, i] = not msg.status.qp_fallback
                if held is not None:
                    command[k, i] = held.plan.inputs[0]
                    c[k, i] = (held.status.first_c_norm, 0.0)
                j = bisect_right(track.status_t_s, t_s[k] + 1e-9) - 1
                if j >= 0:
                    beta[k, i] = track.statuses[j].status.beta.as_tuple()
                beta_truth[k, i] = (
                    truth_params.speed_effectiveness,
                    truth_params.yaw_rate_effectiveness,
                    *truth_params.wind.at(float(t_s[k])),
                )
        return FlightRecord(
            scenario=sc.name,
            vehicle_ids=self.ids,
            t_s=t_s,
            truth=truth,
            target=target,
            target_velocity=target_vel,
            slots=slots,
            command=command,
            c=c,
            beta=beta,
            beta_truth=beta_truth,
            qp_ok=qp_ok,
            step_time_ms=step_ms,
            desired_distance_m=self._formation.desired_distances(),
            trail_m=sc.formation.trail_m,
            slot_offsets_world=offsets,
            min_separation_m=self._min_separation(float(t_s[-1])),
            speed_max_m_s=sc.controller.speed_max_m_s,
            yaw_rate_max_rad_s=sc.controller.yaw_rate_max_rad_s,
            d_safe_m=sc.controller.d_safe_m,
        )

    def _min_separation(self, end_s: float) -> float:
        n = len(self.ids)
        if n < 2:
            return math.inf
        grid = np.arange(0.0, end_s + 1e-9, self.scenario.tick_ns * 1e-9)
        pos = np.stack([self._poses(vid, grid)[:, :2] for vid in self.ids], axis=1)
        d = np.linalg.norm(pos[:, :, None, :] - pos[:, None, :, :], axis=-1)
        a, b = np.triu_indices(n, 1)
        return float(np.nanmin(d[:, a, b]))
