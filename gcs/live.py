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
from bisect import bisect_left, bisect_right, insort
from dataclasses import dataclass, field

import numpy as np

from gcs.record import FlightRecord, LiveRows, RunConstants
from onboard.core.formation import Formation
from onboard.core.target_estimator import TargetEstimator
from protocol.messages import PlanMessage, StatusMessage, TargetObservation
from protocol.scenario import Scenario

__all__ = ["LiveRecord", "formation_reference"]


def formation_reference(
    formation: Formation, target_m: np.ndarray, target_velocity_m_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slots (K, N, 2) of the true target over K periods and each slot's offset from the
    formation centre (K, N, 2), for target positions and velocities (K, 2).

    The course is stateful (the last known course holds while the target is nearly still), so
    the periods go through `formation.placement` in order; the rest is array arithmetic with the
    same float operations, period by period, as a scalar computation.
    """
    placements = [formation.placement(v) for v in np.asarray(target_velocity_m_s).tolist()]
    trail = np.array([(x, y) for x, y, _ in placements]).reshape(-1, 2)
    offsets = np.array([o for _, _, o in placements]).reshape(len(placements), formation.size, 2)
    centre = np.asarray(target_m, dtype=float).reshape(-1, 2) - trail
    slots = centre[:, None, :] + offsets
    return slots, slots - centre[:, None, :]


def _unwrap_tail(raw: np.ndarray, *, previous_raw: float | None, correction: float) -> tuple:
    """`np.unwrap` of a sequence continued by `raw`, given the last raw value before it and the
    correction accumulated so far; returns (unwrapped raw, new accumulated correction). Same
    operations, in the same order, as one `np.unwrap` over the whole sequence."""
    if previous_raw is None:
        first, raw_rest = raw[:1], raw[1:]
        unwrapped, correction = _unwrap_tail(raw_rest, previous_raw=raw[0], correction=0.0)
        return np.concatenate([first, unwrapped]), correction
    if len(raw) == 0:
        return raw, correction
    dd = np.diff(np.concatenate([[previous_raw], raw]))
    ddmod = np.mod(dd + np.pi, 2 * np.pi) - np.pi
    ddmod[(ddmod == -np.pi) & (dd > 0)] = np.pi
    ph_correct = ddmod - dd
    ph_correct[abs(dd) < np.pi] = 0
    cumulative = np.cumsum(np.concatenate([[correction], ph_correct]))[1:]
    return raw + cumulative, float(cumulative[-1])


class _Rows:
    """An array grown along its first axis with room to spare: putting rows costs those rows,
    not a copy of every row before them (as a concatenation would, every flush)."""

    def __init__(self) -> None:
        self._buffer: np.ndarray | None = None
        self.count = 0

    def put(self, at: int, rows: np.ndarray) -> None:
        """Rows `at` .. of the array become `rows`; the rows after them are dropped."""
        end = at + len(rows)
        if self._buffer is None or end > len(self._buffer):
            grown = np.empty((max(2 * end, 64), *rows.shape[1:]), dtype=rows.dtype)
            if self._buffer is not None:
                grown[:at] = self._buffer[:at]
            self._buffer = grown
        self._buffer[at:end] = rows
        self.count = end

    @property
    def rows(self) -> np.ndarray:
        """The array's rows (a view, valid until the next `put`)."""
        return np.empty((0,)) if self._buffer is None else self._buffer[: self.count]


@dataclass
class _Track:
    """One vehicle's timestamped samples (fleet seconds), in arrival order per source."""

    t_s: list[float] = field(default_factory=list)
    pose: list[tuple[float, float, float]] = field(default_factory=list)
    plans: dict[int, PlanMessage] = field(default_factory=dict)
    """Plans by period index."""
    plan_periods: list[int] = field(default_factory=list)
    """The periods of `plans`, sorted."""
    status_t_s: list[float] = field(default_factory=list)
    statuses: list[StatusMessage] = field(default_factory=list)
    arrays: tuple[_Rows, ...] = field(default_factory=lambda: tuple(_Rows() for _ in range(4)))
    """t_s, north, east and unwrapped yaw of the first samples, as arrays (filled on demand)."""
    yaw_correction: float = 0.0


_SCENARIO_FIELDS = ("target", "target_velocity", "slots", "slot_offsets_world", "beta_truth")
"""Per-period fields that depend only on the scenario (computed once per period)."""
_RECEIVED_FIELDS = ("truth", "command", "c", "qp_ok", "step_time_ms", "beta", "separation_min")
"""Per-period fields built from what was received (recomputed if late input changes them)."""
_LIVE_FIELDS = ("plans", "setpoint_rate_hz", "plan_age_s")
"""Received per-period fields that are not in a FlightRecord (see `LiveRows`)."""


class LiveRecord:
    """Collects a live run; `record(periods)` gives the FlightRecord of its first periods.

    Periods already built are cached, so a growing record costs only its new periods: the
    scenario's fields are computed once per period, and the received fields are rebuilt from
    the first period a late input (a plan, a status, or a position sample that moves the
    interpolation) can change.
    """

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
        self._target_pending: TargetObservation | None = None
        self._scenario_rows = {name: _Rows() for name in _SCENARIO_FIELDS}
        self._received_rows = {name: _Rows() for name in _RECEIVED_FIELDS + _LIVE_FIELDS}
        self._pairs = np.triu_indices(len(self.ids), 1)
        """Index arrays of every vehicle pair (a, b), a < b."""
        self._valid = 0
        """Periods whose received fields in the cache are current."""

    def _invalidate(self, period: int) -> None:
        self._valid = max(0, min(self._valid, period))

    # -- inputs -----------------------------------------------------------------------------------
    def add_pose(self, vehicle_id: int, t_s: float, north_m: float, east_m: float, yaw_rad: float):
        """A telemetry sample of a vehicle at fleet time `t_s`; out-of-order samples are dropped."""
        track = self._tracks.get(vehicle_id)
        if track is None or not all(map(math.isfinite, (t_s, north_m, east_m, yaw_rad))):
            return
        if track.t_s and t_s <= track.t_s[-1]:
            return
        # Periods after the previous newest sample were interpolated to it (or, without any
        # sample, taken from the plans): they change.
        self._invalidate(int(track.t_s[-1] * 1e9 // self.period_ns) if track.t_s else 0)
        track.t_s.append(t_s)
        track.pose.append((north_m, east_m, yaw_rad))

    def add_plan(self, message: PlanMessage) -> None:
        track = self._tracks.get(message.sender_id)
        if track is not None and message.stamp_ns % self.period_ns == 0:
            period = message.stamp_ns // self.period_ns
            if period not in track.plans:
                insort(track.plan_periods, period)
            track.plans[period] = message
            self._invalidate(period)

    def add_status(self, message: StatusMessage) -> None:
        track = self._tracks.get(message.sender_id)
        t_s = message.stamp_ns * 1e-9
        if track is not None and (not track.status_t_s or t_s > track.status_t_s[-1]):
            track.status_t_s.append(t_s)
            track.statuses.append(message)
            self._invalidate(message.stamp_ns // self.period_ns)

    def add_target(self, message: TargetObservation) -> None:
        """A target observation. Only the newest one is kept until `target_prediction` fuses it:
        the prediction is for display, once per flush, and the filter costs some 30 us per
        observation."""
        newest = self._target_pending
        if newest is None or message.stamp_ns > newest.stamp_ns:
            self._target_pending = message
        self.target_observations += 1

    # -- queries ----------------------------------------------------------------------------------
    def latest_time_s(self, vehicle_id: int) -> float | None:
        """Fleet time of the vehicle's newest position (telemetry or, without it, plan)."""
        track = self._tracks[vehicle_id]
        if track.t_s:
            return track.t_s[-1]
        if track.plans:
            return track.plan_periods[-1] * self.period_ns * 1e-9
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
        track = self._tracks[vehicle_id]
        return track.plans[track.plan_periods[-1]] if track.plans else None

    def target_prediction(self, stamp_ns: int) -> np.ndarray | None:
        """The ground station's own constant-velocity prediction of the target over the horizon."""
        pending, self._target_pending = self._target_pending, None
        if pending is not None:
            self._target.observe(pending.stamp_ns, np.array([pending.north_m, pending.east_m]))
        if not self._target.ready:
            return None
        pos, _ = self._target.predict(
            stamp_ns, self.period_ns, self.scenario.controller.horizon + 1
        )
        return pos

    # -- the record -------------------------------------------------------------------------------
    def _samples(self, track: _Track) -> tuple[np.ndarray, ...]:
        """(S,) t_s, north, east, unwrapped yaw of every sample (converted incrementally)."""
        done = track.arrays[0].count
        if done < len(track.t_s):
            new = np.asarray(track.pose[done:], dtype=float)
            yaw, track.yaw_correction = _unwrap_tail(
                new[:, 2],
                previous_raw=track.pose[done - 1][2] if done else None,
                correction=track.yaw_correction,
            )
            columns = (np.asarray(track.t_s[done:]), new[:, 0], new[:, 1], yaw)
            for rows, column in zip(track.arrays, columns, strict=True):
                rows.put(done, column)
        return tuple(rows.rows for rows in track.arrays)

    def _poses(self, vehicle_id: int, t_s: np.ndarray) -> np.ndarray:
        track = self._tracks[vehicle_id]
        if track.t_s:
            ts, north, east, yaw = self._samples(track)
            cols = [np.interp(t_s, ts, north), np.interp(t_s, ts, east)]
            return np.stack([*cols, np.interp(t_s, ts, yaw)], axis=-1)
        out = np.full((len(t_s), 3), np.nan)
        ks = track.plan_periods
        for j, t in enumerate(t_s):
            i = bisect_right(ks, round(t * 1e9 / self.period_ns)) - 1
            if i >= 0:
                out[j] = track.plans[ks[i]].plan.states[0]
        return out

    def _scenario_periods(self, k_n: int) -> None:
        """Extend the scenario's per-period fields to `k_n` periods."""
        sc = self.scenario
        k0 = self._scenario_rows["target"].count
        if k_n <= k0:
            return
        t_s = np.arange(k0, k_n) * self.period_ns * 1e-9
        states = [sc.target.state_at(float(t)) for t in t_s]
        target = np.array([p for p, _ in states], dtype=float).reshape(-1, 2)
        target_vel = np.array([v for _, v in states], dtype=float).reshape(-1, 2)
        slots, offsets = formation_reference(self._formation, target, target_vel)
        beta_truth = np.empty((len(t_s), len(self.ids), 4))
        times = t_s.tolist()
        for i, vid in enumerate(self.ids):
            truth = sc.vehicle(vid).truth
            beta_truth[:, i, 0] = truth.speed_effectiveness
            beta_truth[:, i, 1] = truth.yaw_rate_effectiveness
            beta_truth[:, i, 2:] = [truth.wind.at(t) for t in times]
        new = {
            "target": target,
            "target_velocity": target_vel,
            "slots": slots,
            "slot_offsets_world": offsets,
            "beta_truth": beta_truth,
        }
        for name, rows in new.items():
            self._scenario_rows[name].put(k0, rows)

    def _received_periods(self, k0: int, k_n: int) -> dict[str, np.ndarray]:
        """The received fields of periods k0 .. k_n - 1."""
        n = len(self.ids)
        k = k_n - k0
        t_s = np.arange(k0, k_n) * self.period_ns * 1e-9
        truth = np.stack([self._poses(vid, t_s) for vid in self.ids], axis=1)
        command = np.full((k, n, 2), np.nan)
        c = np.full((k, n, 2), np.nan)
        qp_ok = np.ones((k, n), dtype=bool)
        step_ms = np.full((k, n), np.nan)
        beta = np.full((k, n, 4), np.nan)
        horizon = self.scenario.controller.horizon
        plans = np.full((k, n, horizon + 1, 2), np.nan)
        rate = np.full((k, n), np.nan)
        ages = np.full((k, n, max(n - 1, 0)), np.nan)
        t_search = (t_s + 1e-9).tolist()
        for i, vid in enumerate(self.ids):
            track = self._tracks[vid]
            # The plan of each period (held from the previous one when it is missing).
            before = bisect_left(track.plan_periods, k0)
            held = track.plans[track.plan_periods[before - 1]] if before else None
            helds = []
            for j in range(k):
                msg = track.plans.get(k0 + j)
                if msg is not None:
                    held = msg
                    step_ms[j, i] = msg.status.solve_time_us * 1e-3
                    qp_ok[j, i] = not msg.status.qp_fallback
                helds.append(held)
            rows = [j for j, h in enumerate(helds) if h is not None]
            if rows:
                command[rows, i] = [helds[j].plan.inputs[0] for j in rows]
                c[rows, i, 0] = [helds[j].status.first_c_norm for j in rows]
                c[rows, i, 1] = 0.0
                whole = [j for j in rows if helds[j].plan.states.shape[0] == horizon + 1]
                if whole:
                    plans[whole, i] = [helds[j].plan.states[:, :2] for j in whole]
            # The latest status at or before each period.
            latest = [bisect_right(track.status_t_s, t) - 1 for t in t_search]
            rows = [j for j, st in enumerate(latest) if st >= 0]
            if rows:
                statuses = [track.statuses[latest[j]].status for j in rows]
                beta[rows, i] = [st.beta.as_tuple() for st in statuses]
                rate[rows, i] = [st.setpoint_rate_hz for st in statuses]
                others = {o: a for a, o in enumerate(x for x in self.ids if x != vid)}
                for j, st in zip(rows, statuses, strict=True):
                    for a in st.neighbour_plan_ages:
                        if a.vehicle_id in others:
                            ages[j, i, others[a.vehicle_id]] = a.age_ns * 1e-9
        return {
            "truth": truth,
            "command": command,
            "c": c,
            "qp_ok": qp_ok,
            "step_time_ms": step_ms,
            "beta": beta,
            "separation_min": self._separation_minima(k0, k_n),
            "plans": plans,
            "setpoint_rate_hz": rate,
            "plan_age_s": ages,
        }

    def _separation_minima(self, k0: int, k_n: int) -> np.ndarray:
        """Per period k0 .. k_n - 1, the closest approach over the plant ticks since the previous
        period (period k covers the ticks up to t_k; period 0 the tick at 0)."""
        n = len(self.ids)
        if n < 2:
            return np.full(k_n - k0, math.inf)
        tick_s = self.scenario.tick_ns * 1e-9
        # Ticks up to period k: the length of np.arange(0.0, t_k + 1e-9, tick_s).
        t_s = np.arange(k0 - 1 if k0 else 0, k_n) * self.period_ns * 1e-9
        ends = np.ceil((t_s + 1e-9) / tick_s).astype(np.int64)
        first = ends[0] if k0 else 0
        ends = ends[1:] if k0 else ends
        grid = np.arange(first, ends[-1]) * tick_s
        pos = np.stack([self._poses(vid, grid)[:, :2] for vid in self.ids], axis=1)
        a, b = self._pairs
        d = np.linalg.norm(pos[:, a, :] - pos[:, b, :], axis=-1)  # (ticks, pairs)
        starts = np.concatenate([[first], ends[:-1]]) - first
        out = np.full(len(ends), np.nan)
        has_ticks = ends - first > starts
        if has_ticks.any():
            per_tick = np.fmin.reduce(d, axis=1)
            out[has_ticks] = np.fmin.reduceat(per_tick, starts[has_ticks])
        return out

    def _update_cache(self, k_n: int) -> None:
        k0 = min(self._valid, self._received_rows["truth"].count)
        if k_n <= k0:
            return
        new = self._received_periods(k0, k_n)
        for name, rows in new.items():
            self._received_rows[name].put(k0, rows)
        self._valid = k_n

    def record(self, periods: int | None = None, *, first: int = 0) -> FlightRecord:
        """The FlightRecord of periods `first` .. `periods` - 1 (default: every complete period;
        a growing record's tail costs only its periods), its minimum separation the whole
        run's up to `periods`."""
        k_n = self.complete_periods() if periods is None else periods
        if k_n < 1:
            raise ValueError("no complete control period yet")
        if not 0 <= first < k_n:
            raise ValueError(f"no periods in {first} .. {k_n - 1}")
        self._scenario_periods(k_n)
        self._update_cache(k_n)
        got = {name: r.rows for name, r in (self._scenario_rows | self._received_rows).items()}
        rows = {
            name: values[first:k_n].copy()
            for name, values in got.items()
            if name not in _LIVE_FIELDS and name != "separation_min"
        }
        with np.errstate(invalid="ignore"):
            min_separation = np.fmin.reduce(got["separation_min"][:k_n])
        return FlightRecord(
            t_s=np.arange(first, k_n) * self.period_ns * 1e-9,
            **rows,
            min_separation_m=float(min_separation),
            **self.constants().as_fields(),
        )

    def constants(self) -> RunConstants:
        """What the record holds that is the same in every period."""
        sc = self.scenario
        return RunConstants(
            scenario=sc.name,
            vehicle_ids=self.ids,
            desired_distance_m=self._formation.desired_distances(),
            trail_m=sc.formation.trail_m,
            speed_max_m_s=sc.controller.speed_max_m_s,
            yaw_rate_max_rad_s=sc.controller.yaw_rate_max_rad_s,
            d_safe_m=sc.controller.d_safe_m,
        )

    def live_rows(self, start: int, periods: int) -> LiveRows:
        """Plans, setpoint rates and plan ages of periods `start` .. `periods` - 1, and the
        target prediction at the last of them (what the ground station logs beside the
        record's slice)."""
        if not 0 <= start < periods:
            raise ValueError(f"no periods in {start} .. {periods - 1}")
        self._update_cache(periods)
        rows = {name: self._received_rows[name].rows[start:periods].copy() for name in _LIVE_FIELDS}
        return LiveRows(
            **rows, target_prediction=self.target_prediction((periods - 1) * self.period_ns)
        )
