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
  scripted target and truth parameters (what the scenario knows), but for the wind of a vehicle
  that reports its true wind (our SITL's WIND_COV): the newest sample at or before the period;
- `command`, `qp_ok`, `step_time_ms`: from the plan stamped at that period (the plan's first
  input is the command the agent sent), held from the previous period if that plan is missing;
- `c`: only the norm of c_0 travels on the wire; it is stored in the first component;
- `beta`: the latest status at or before the period;
- `min_separation_m`: over the telemetry interpolated on the plant tick of the scenario;
- `plan_age_s`: the ages of the neighbours' plans in the latest status at or before the period;
- `target_prediction`: NaN (the agents do not send theirs).

Beside the record, `live_rows` gives each period's plans, setpoint rates and the ground
station's own prediction of the target over the horizon, made at the period's time from every
observation stamped at or before it.
"""

import math
from bisect import bisect_right, insort
from dataclasses import dataclass, field

import numpy as np

from fleetmpc.gcs.growable import Growable
from fleetmpc.gcs.metrics import pair_indices
from fleetmpc.gcs.record import FlightRecord, LiveRows, RunConstants
from fleetmpc.gcs.scenario_rows import ScenarioRows
from fleetmpc.onboard.core.target_estimator import TargetEstimator
from fleetmpc.onboard.core.unicycle import wrap
from fleetmpc.protocol.messages import PlanMessage, StatusMessage, TargetObservation
from fleetmpc.scenario import Scenario

__all__ = ["LiveRecord"]


def _unwrap_step(previous_rad: float, yaw_rad: float, *, correction: float) -> float:
    """`np.unwrap` one sample further: the correction [rad] it adds to `yaw_rad`, following
    `previous_rad` to which it added `correction`. The same float operations as `np.unwrap`
    (Python's float `%` is numpy's `np.mod`: fmod, then the divisor's sign), one sample at a
    time, as the samples arrive."""
    dd = yaw_rad - previous_rad
    ddmod = wrap(dd)
    if ddmod == -math.pi and dd > 0:
        ddmod = math.pi
    return correction + (0.0 if abs(dd) < math.pi else ddmod - dd)


def _hold(events: np.ndarray, arrived: np.ndarray, before: np.ndarray) -> np.ndarray:
    """Per period and vehicle, the latest row of `events` (K, N, W) that arrived (`arrived`
    (K, N)) at or before the period, else `before` (N, W), the row held before the first period.
    Copies of the rows: the same floats."""
    k, n = arrived.shape
    index = np.where(arrived, np.arange(1, k + 1)[:, None], 0)
    np.maximum.accumulate(index, axis=0, out=index)
    rows = np.empty((k + 1, *events.shape[1:]))
    rows[0] = before
    rows[1:] = events
    return rows[index, np.arange(n)]


@dataclass
class _Track:
    """One vehicle's timestamped samples (fleet seconds), in arrival order per source."""

    pending: list[float] = field(default_factory=list)
    """t_s, north, east and unwrapped yaw of each telemetry sample not yet in `columns`, in time
    order, one after the other."""
    newest_t_s: float | None = None
    """Fleet time of the newest telemetry sample."""
    raw_yaw: float | None = None
    """The newest sample's yaw as received [rad]."""
    plans: dict[int, PlanMessage] = field(default_factory=dict)
    """Plans by period index."""
    plan_periods: list[int] = field(default_factory=list)
    """The periods of `plans`, sorted."""
    status: StatusMessage | None = None
    """The newest status (the table holds every status's row)."""
    columns: Growable = field(default_factory=lambda: Growable((4, 0), axis=1))
    """Every telemetry sample but the pending ones, as columns (4, S) t_s, north, east and
    unwrapped yaw, each contiguous as `np.interp` wants it (filled on demand)."""
    yaw_correction: float = 0.0
    """What the unwrapping adds to the newest sample's raw yaw [rad]."""
    wind: list[tuple[float, float, float]] = field(default_factory=list)
    """The true wind's samples (t_s, North, East), in time order."""


_RECEIVED_FIELDS = ("truth", "command", "c", "qp_ok", "step_time_ms", "beta", "plan_age_s")
"""Per-period FlightRecord fields built from what was received."""
_LIVE_FIELDS = ("plans", "setpoint_rate_hz", "plan_age_s")
"""Received per-period fields that are not in a FlightRecord (see `LiveRows`)."""
_CACHED = ("truth", "qp_ok", "step_time_ms", "separation_min", "plan_held", "status_held")
"""What the received fields are made of, per period (recomputed if late input changes it): the
positions, the plan flags, the closest approach over the period, and each vehicle's plan row
and status row held at the period (see `_PLAN_COLUMNS`, `_STATUS_COLUMNS`)."""

_PLAN_COLUMNS = 6
"""A plan's row in the plan table: command (2), c (2: |c_0|, 0), step time [ms], QP fallback
(1 or 0; NaN where no plan arrived), then the planned positions (M + 1, 2) flattened (NaN if the
plan does not span the horizon)."""
_STATUS_COLUMNS = 6
"""A status's row in the status table: arrived (1; NaN where none did), beta (4), setpoint rate
[Hz], then the age of each other vehicle's plan [s] (N - 1, NaN where not reported)."""


class LiveRecord:
    """Collects a live run; `record(periods)` gives the FlightRecord of its first periods.

    Periods already built are cached, so a growing record costs only its new periods: the
    scenario's fields are computed once per period, and the received fields are rebuilt from
    the first period a late input (a plan, a status, or a position sample that moves the
    interpolation) can change. Plans and statuses become rows of two tables, by period and
    vehicle, as they are needed, and the telemetry columns grow by the new samples, so
    building a record in slices costs little more than building it once: the work per slice
    is a fixed number of array operations for the whole fleet, besides one interpolation per
    vehicle and column.
    """

    def __init__(self, scenario: Scenario, *, periods: int = 0) -> None:
        """periods: the periods the run is expected to have, whose scenario fields (which
        depend on nothing received) are computed now, before the flight."""
        self.scenario = scenario
        self.period_ns = scenario.controller.period_ns
        self.ids = scenario.vehicle_ids
        n = len(self.ids)
        self._tracks = {vid: _Track() for vid in self.ids}
        self._index = {vid: i for i, vid in enumerate(self.ids)}
        self._others = [
            {o: a for a, o in enumerate(x for x in self.ids if x != vid)} for vid in self.ids
        ]
        """Per vehicle, the column of each other vehicle in its plan ages."""
        self._scenario_rows = ScenarioRows(scenario)
        horizon = scenario.controller.horizon
        self._target = TargetEstimator(
            observation_std_m=max(scenario.target.observation_noise_m, 1e-3)
        )
        self.target_observations = 0
        self._target_pending: list[tuple[int, TargetObservation]] = []
        """Observations not fused yet, by stamp."""
        self._target_paths = Growable((0, horizon + 1, 2), fill=math.nan)
        """The ground station's target prediction at each period's time, for the periods
        predicted so far (NaN before the first observation)."""
        self._no_plan = [math.nan] * 2 * (horizon + 1)
        self._plan_table = Growable((0, n, _PLAN_COLUMNS + 2 * (horizon + 1)), fill=math.nan)
        self._status_table = Growable((0, n, _STATUS_COLUMNS + max(n - 1, 0)), fill=math.nan)
        """Per period and vehicle, the row of the plan or status that arrived for that period
        (NaN where none did)."""
        self._pending_plans: dict[tuple[int, int], list[float]] = {}
        """Rows of the plans not in the plan table yet, by (period, vehicle index), made as
        the plans arrive (the work is the same whether the record is built once or a flush at
        a time)."""
        self._pending_statuses: dict[tuple[int, int], list[float]] = {}
        """Rows of the statuses not in the status table yet, by (first period at or after
        them, vehicle index); a newer status of the same vehicle and period replaces an older
        one."""
        self._received_rows = {name: Growable() for name in _CACHED}
        self._constant_fields = self.constants().as_fields()
        self._desired_distance_m = self._constant_fields.pop("desired_distance_m")
        """The record's constants (an array, copied into each record) and the others."""
        self._pairs = np.array(pair_indices(n), dtype=np.intp).reshape(-1, 2).T
        """Index arrays (2, P) of every vehicle pair (a, b), a < b, in `pair_indices` order."""
        self._valid = 0
        """Periods whose received fields in the cache are current."""
        if periods > 0:
            self._scenario_rows.extend(periods)

    def _invalidate(self, period: int) -> None:
        self._valid = max(0, min(self._valid, period))

    # -- inputs -----------------------------------------------------------------------------------
    def add_pose(self, vehicle_id: int, t_s: float, north_m: float, east_m: float, yaw_rad: float):
        """A telemetry sample of a vehicle at fleet time `t_s`; out-of-order samples are dropped."""
        track = self._tracks.get(vehicle_id)
        if track is None or not all(map(math.isfinite, (t_s, north_m, east_m, yaw_rad))):
            return
        newest = track.newest_t_s
        if newest is not None and t_s <= newest:
            return
        # Periods after the previous newest sample were interpolated to it (or, without any
        # sample, taken from the plans): they change.
        self._invalidate(int(newest * 1e9 // self.period_ns) if newest is not None else 0)
        yaw = yaw_rad
        if track.raw_yaw is not None:
            track.yaw_correction = _unwrap_step(
                track.raw_yaw, yaw_rad, correction=track.yaw_correction
            )
            yaw = yaw_rad + track.yaw_correction
        track.raw_yaw = yaw_rad
        track.pending += (t_s, north_m, east_m, yaw)
        track.newest_t_s = t_s

    def add_wind(self, vehicle_id: int, t_s: float, north_m_s: float, east_m_s: float) -> None:
        """A sample of the true wind where a vehicle is, at fleet time `t_s` (a simulator's
        truth); out-of-order and non-finite samples are dropped."""
        track = self._tracks.get(vehicle_id)
        if track is None or not all(map(math.isfinite, (t_s, north_m_s, east_m_s))):
            return
        if track.wind and t_s <= track.wind[-1][0]:
            return
        track.wind.append((t_s, north_m_s, east_m_s))

    def _with_true_wind(self, beta_truth: np.ndarray, first: int) -> np.ndarray:
        """`beta_truth` (K, N, 4) of periods from `first` on, its wind columns the newest true
        wind sample at or before each period where a vehicle has one (a copy when any has)."""
        t = (first + np.arange(len(beta_truth))) * self.period_ns * 1e-9
        out = beta_truth
        for vid, track in self._tracks.items():
            if not track.wind:
                continue
            samples = np.array(track.wind)
            at = np.searchsorted(samples[:, 0], t + 1e-9, side="right") - 1
            if out is beta_truth:
                out = beta_truth.copy()
            known = at >= 0
            out[known, self._index[vid], 2:4] = samples[at[known], 1:]
        return out

    def add_plan(self, message: PlanMessage) -> None:
        track = self._tracks.get(message.sender_id)
        if track is not None and message.stamp_ns % self.period_ns == 0:
            period = message.stamp_ns // self.period_ns
            if period not in track.plans:
                insort(track.plan_periods, period)
            track.plans[period] = message
            self._pending_plans[period, self._index[message.sender_id]] = self._plan_row(message)
            self._invalidate(period)

    def add_status(self, message: StatusMessage) -> None:
        track = self._tracks.get(message.sender_id)
        t_s = message.stamp_ns * 1e-9
        if track is not None and (track.status is None or t_s > track.status.stamp_ns * 1e-9):
            track.status = message
            period = self._first_period_at(t_s)
            i = self._index[message.sender_id]
            self._pending_statuses[period, i] = self._status_row(message, i)
            self._invalidate(period)

    def _first_period_at(self, t_s: float) -> int:
        """The first period whose time (1 ns tolerance) is at or after `t_s`: the first a status
        stamped at `t_s` is the latest of (the same float comparison as a search of the status
        times for each period's)."""
        k = max(int(t_s * 1e9 // self.period_ns), 0)
        while k > 0 and (k - 1) * self.period_ns * 1e-9 + 1e-9 >= t_s:
            k -= 1
        while not k * self.period_ns * 1e-9 + 1e-9 >= t_s:
            k += 1
        return k

    def add_target(self, message: TargetObservation) -> None:
        """A target observation, kept until the prediction of the first period at or after its
        stamp fuses it (one that comes after that period was predicted is fused with the next
        one's, or dropped by the filter if it is older than one it has)."""
        insort(self._target_pending, (message.stamp_ns, message), key=lambda p: p[0])
        self.target_observations += 1

    # -- queries ----------------------------------------------------------------------------------
    def latest_time_s(self, vehicle_id: int) -> float | None:
        """Fleet time of the vehicle's newest position (telemetry or, without it, plan)."""
        track = self._tracks[vehicle_id]
        if track.newest_t_s is not None:
            return track.newest_t_s
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
        return self._tracks[vehicle_id].status

    def latest_plan(self, vehicle_id: int) -> PlanMessage | None:
        track = self._tracks[vehicle_id]
        return track.plans[track.plan_periods[-1]] if track.plans else None

    def target_paths(self, periods: int) -> np.ndarray:
        """The ground station's own prediction of the target over the horizon (the coordinated-
        turn filter of the agents) at the time of each of the first `periods` periods
        (periods, M + 1, 2) North, East [m], NaN before the first observation. Each period's
        is made once, from the observations stamped at or before its time received by then."""
        done = self._target_paths.count
        if periods > done:
            count = self.scenario.controller.horizon + 1
            rows = np.full((periods - done, count, 2), np.nan)
            pending = self._target_pending
            for j, k in enumerate(range(done, periods)):
                stamp_ns = k * self.period_ns
                fused = 0
                while fused < len(pending) and pending[fused][0] <= stamp_ns:
                    m = pending[fused][1]
                    self._target.observe(m.stamp_ns, np.array([m.north_m, m.east_m]))
                    fused += 1
                del pending[:fused]
                if self._target.ready:
                    rows[j], _ = self._target.predict(stamp_ns, self.period_ns, count)
            self._target_paths.append(rows)
        return self._target_paths.array[:periods]

    # -- the record -------------------------------------------------------------------------------
    def _convert_samples(self) -> None:
        """Every vehicle's new telemetry samples appended to its columns."""
        for track in self._tracks.values():
            if track.pending:
                new = np.array(track.pending, dtype=float)
                track.columns.append(new.reshape(-1, 4).T)
                track.pending.clear()

    def _poses(self, t_s: np.ndarray, *, yaw_until: int) -> np.ndarray:
        """(N, 3, T) north, east and yaw of every vehicle at times `t_s` (T,), the yaw only at
        the first `yaw_until` (undefined after)."""
        self._convert_samples()
        out = np.empty((len(self.ids), 3, len(t_s)))
        for i, vid in enumerate(self.ids):
            track = self._tracks[vid]
            if track.columns.count:
                ts, north, east, yaw = track.columns.array
                out[i, 0] = np.interp(t_s, ts, north)
                out[i, 1] = np.interp(t_s, ts, east)
                out[i, 2, :yaw_until] = np.interp(t_s[:yaw_until], ts, yaw)
                continue
            ks = track.plan_periods
            for j, t in enumerate(t_s.tolist()):
                i_plan = bisect_right(ks, round(t * 1e9 / self.period_ns)) - 1
                out[i, :, j] = track.plans[ks[i_plan]].plan.states[0] if i_plan >= 0 else math.nan
        return out

    def _plan_row(self, message: PlanMessage) -> list[float]:
        """The plan table's row of a plan (see `_PLAN_COLUMNS`)."""
        plan, status = message.plan, message.status
        whole = plan.states.shape[0] == self.scenario.controller.horizon + 1
        return [
            *plan.inputs[0].tolist(),
            status.first_c_norm,
            0.0,
            status.solve_time_us * 1e-3,
            float(status.qp_fallback),
            *(plan.states[:, :2].ravel().tolist() if whole else self._no_plan),
        ]

    def _status_row(self, message: StatusMessage, i: int) -> list[float]:
        """The status table's row of vehicle i's status (see `_STATUS_COLUMNS`)."""
        st = message.status
        ages = [math.nan] * (len(self.ids) - 1)
        others = self._others[i]
        for a in st.neighbour_plan_ages:
            if a.vehicle_id in others:
                ages[others[a.vehicle_id]] = a.age_ns * 1e-9
        return [1.0, *st.beta.as_tuple(), st.setpoint_rate_hz, *ages]

    def _take_pending(self, k_n: int) -> None:
        """Pending plans and statuses of periods before `k_n` into their tables."""
        for pending, table in (
            (self._pending_plans, self._plan_table),
            (self._pending_statuses, self._status_table),
        ):
            due = [key for key in pending if key[0] < k_n]
            if due:
                rows = [pending.pop(key) for key in due]
                table.reserve(max(p for p, _ in due) + 1)
                table.array[[p for p, _ in due], [i for _, i in due]] = rows

    def _held_before(self, name: str, k0: int) -> np.ndarray:
        """The held row of each vehicle at period k0 - 1 (NaN before period 0: a message's
        stamp is not negative)."""
        if k0:
            return self._received_rows[name].array[k0 - 1]
        return np.nan

    def _received_periods(self, k0: int, k_n: int) -> dict[str, np.ndarray]:
        """The received fields of periods k0 .. k_n - 1."""
        k = k_n - k0
        self._take_pending(k_n)
        self._plan_table.reserve(k_n)
        self._status_table.reserve(k_n)
        events = self._plan_table.array[k0:k_n]
        arrived = ~np.isnan(events[:, :, 5])
        plan = _hold(events, arrived, self._held_before("plan_held", k0))
        statuses = self._status_table.array[k0:k_n]
        status = _hold(statuses, statuses[:, :, 0] == 1.0, self._held_before("status_held", k0))
        # The period times, then the plant ticks since the previous period (the separation's).
        t_s = np.arange(k0, k_n) * self.period_ns * 1e-9
        ticks, tick_ends = self._separation_ticks(k0, k_n)
        pos = self._poses(np.concatenate([t_s, ticks]), yaw_until=k)
        return {
            "truth": pos[:, :, :k].transpose(2, 0, 1),
            "qp_ok": events[:, :, 5] != 1.0,
            "step_time_ms": events[:, :, 4],
            "separation_min": self._separation_minima(pos[:, :2, k:], tick_ends),
            "plan_held": plan,
            "status_held": status,
        }

    def _received(
        self, first: int, k_n: int, names: tuple[str, ...], *, copy: bool = True
    ) -> dict[str, np.ndarray]:
        """The received fields `names` of periods `first` .. `k_n` - 1 (cached): copies, or
        views of the cache."""
        rows = {name: self._received_rows[name].array[first:k_n] for name in _CACHED}
        plan, status = rows["plan_held"], rows["status_held"]
        k, n = plan.shape[:2]
        views = {
            "truth": rows["truth"],
            "command": plan[:, :, 0:2],
            "c": plan[:, :, 2:4],
            "qp_ok": rows["qp_ok"],
            "step_time_ms": rows["step_time_ms"],
            "beta": status[:, :, 1:5],
            "plans": plan[:, :, _PLAN_COLUMNS:].reshape(k, n, -1, 2),
            "setpoint_rate_hz": status[:, :, 5],
            "plan_age_s": status[:, :, _STATUS_COLUMNS:],
        }
        return {name: views[name].copy() if copy else views[name] for name in names}

    def _separation_ticks(self, k0: int, k_n: int) -> tuple[np.ndarray, np.ndarray]:
        """The plant ticks (T,) [s] periods k0 .. k_n - 1 cover (period k the ticks up to t_k,
        period 0 the tick at 0), and where each period's ticks end in them (K,)."""
        tick_s = self.scenario.tick_ns * 1e-9
        # Ticks up to period k: the length of np.arange(0.0, t_k + 1e-9, tick_s).
        t_s = np.arange(k0 - 1 if k0 else 0, k_n) * self.period_ns * 1e-9
        ends = np.ceil((t_s + 1e-9) / tick_s).astype(np.int64)
        first = ends[0] if k0 else 0
        ends = ends[1:] if k0 else ends
        return np.arange(first, ends[-1]) * tick_s, ends - first

    def _separation_minima(self, pos: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Per period, the closest approach over its plant ticks, from every vehicle's position
        (N, 2, T) on the ticks and where each period's ticks end (K,)."""
        if len(self.ids) < 2:
            return np.full(len(ends), math.inf)
        a, b = self._pairs
        diff = pos[a] - pos[b]
        d = np.sqrt(np.add.reduce(diff * diff, axis=1))  # (pairs, ticks), as np.linalg.norm
        starts = np.concatenate([[0], ends[:-1]])
        out = np.full(len(ends), np.nan)
        has_ticks = ends > starts
        if has_ticks.any():
            per_tick = np.fmin.reduce(d, axis=0)
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

    def record(
        self, periods: int | None = None, *, first: int = 0, copy: bool = True
    ) -> FlightRecord:
        """The FlightRecord of periods `first` .. `periods` - 1 (default: every complete period;
        a growing record's tail costs only its periods), its minimum separation the whole
        run's up to `periods`. With `copy` False its per-period arrays are views of the
        collected ones, only valid, and only to be read, until the next input or build."""
        k_n = self.complete_periods() if periods is None else periods
        if k_n < 1:
            raise ValueError("no complete control period yet")
        if not 0 <= first < k_n:
            raise ValueError(f"no periods in {first} .. {k_n - 1}")
        self._scenario_rows.extend(k_n)
        self._update_cache(k_n)
        scenario = self._scenario_rows.rows(first, k_n)
        rows = {name: a.copy() if copy else a for name, a in scenario.items()}
        rows["beta_truth"] = self._with_true_wind(rows["beta_truth"], first)
        rows |= self._received(first, k_n, _RECEIVED_FIELDS, copy=copy)
        with np.errstate(invalid="ignore"):
            min_separation = np.fmin.reduce(self._received_rows["separation_min"].array[:k_n])
        return FlightRecord(
            t_s=np.arange(first, k_n) * self.period_ns * 1e-9,
            **rows,
            min_separation_m=float(min_separation),
            target_prediction=np.full((k_n - first, 2), np.nan),
            **self._constant_fields,
            desired_distance_m=self._desired_distance_m.copy(),
        )

    def constants(self) -> RunConstants:
        """What the record holds that is the same in every period."""
        formation = self._scenario_rows.formation
        return RunConstants.of_scenario(self.scenario, formation.desired_distances())

    def live_rows(self, start: int, periods: int, *, copy: bool = True) -> LiveRows:
        """Plans, setpoint rates, plan ages and the target predictions of periods `start` ..
        `periods` - 1 (what the ground station logs beside the record's slice); with `copy`
        False, views as `record` gives them."""
        if not 0 <= start < periods:
            raise ValueError(f"no periods in {start} .. {periods - 1}")
        self._update_cache(periods)
        rows = self._received(start, periods, _LIVE_FIELDS, copy=copy)
        paths = self.target_paths(periods)[start:]
        return LiveRows(**rows, target_path=paths.copy() if copy else paths)
