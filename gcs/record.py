"""A flight record: what a run logged every control period, as arrays.

The input of the metrics and the figures."""

from dataclasses import dataclass, fields

import numpy as np

__all__ = ["PERIOD_FIELDS", "FlightRecord", "LiveRows", "RunConstants", "period_rows"]

PERIOD_FIELDS = (
    "truth",
    "target",
    "target_velocity",
    "slots",
    "command",
    "c",
    "beta",
    "beta_truth",
    "qp_ok",
    "step_time_ms",
    "slot_offsets_world",
    "target_prediction",
    "plan_age_s",
)
"""The FlightRecord fields with one row per period (besides `t_s`), in the order a recording
stores them. The last two are optional in a FlightRecord (None: not recorded); a recording
stores NaN for them then (`period_rows`)."""


@dataclass(frozen=True, eq=False)
class FlightRecord:
    """Per-period samples of a fleet run. K samples, N vehicles."""

    scenario: str
    vehicle_ids: tuple[int, ...]
    t_s: np.ndarray
    """Sample times (K,) [s]."""
    truth: np.ndarray
    """True vehicle states (K, N, 3): x North [m], y East [m], yaw [rad]."""
    target: np.ndarray
    """True target position (K, 2) [m]."""
    target_velocity: np.ndarray
    """True target velocity (K, 2) [m/s]."""
    slots: np.ndarray
    """Slots computed from the true target (K, N, 2) [m]."""
    command: np.ndarray
    """Applied commands (K, N, 2): speed [m/s], yaw rate [rad/s]."""
    c: np.ndarray
    """First decision variable c_0 of each vehicle's QP (K, N, 2)."""
    beta: np.ndarray
    """Learned (a_V, a_w, d_x, d_y) (K, N, 4)."""
    beta_truth: np.ndarray
    """True (a_V, a_w, wind North, wind East) (K, N, 4)."""
    qp_ok: np.ndarray
    """QP success flag (K, N)."""
    step_time_ms: np.ndarray
    """Per-agent control step wall time (K, N) [ms]; nan where not measured."""
    desired_distance_m: np.ndarray
    """Desired distance between slots (N, N) [m]."""
    trail_m: float
    """Desired target-to-centre distance d_s [m]."""
    slot_offsets_world: np.ndarray
    """Slot offset of each vehicle from the centre in the world frame (K, N, 2) [m]."""
    min_separation_m: float
    """Smallest distance between any two vehicles over the whole run, at plant rate [m]."""
    speed_max_m_s: float
    yaw_rate_max_rad_s: float
    d_safe_m: float
    target_prediction: np.ndarray | None = None
    """The first agent's prediction of the target's position at the end of its horizon, made at
    each period (K, 2) [m]; nan while it has no target (and throughout a live run: the agents do
    not send it); None when the run did not record it."""
    prediction_horizon_periods: int = 0
    """How many periods ahead `target_prediction` looks (the controller's horizon M)."""
    plan_age_s: np.ndarray | None = None
    """Age of each other vehicle's plan as vehicle i saw it (K, N, N - 1) [s], the others in
    fleet order; nan where it had none; None when the run did not record it."""
    network: dict | None = None
    """What the plan bus did: the faults injected, what the receivers counted; None when the
    run did not say."""


@dataclass(frozen=True, eq=False)
class LiveRows:
    """What only a live run adds to the periods of a FlightRecord slice (K rows, N vehicles).

    Each row holds what the ground station had received for that period: the plan stamped at
    it (held from an earlier period if it is missing), the latest status at or before it, and
    its prediction of the target from the observations stamped at or before it.
    """

    plans: np.ndarray
    """Each vehicle's planned positions (K, N, M + 1, 2) North, East [m]; nan before any plan."""
    setpoint_rate_hz: np.ndarray
    """Each vehicle's setpoint rate (K, N) [Hz]; nan before any status."""
    plan_age_s: np.ndarray
    """Age of each other vehicle's plan as vehicle i sees it (K, N, N - 1) [s], the others in
    fleet order; nan where not reported."""
    target_path: np.ndarray
    """The ground side's prediction of the target over the horizon, made at each row's time
    (K, M + 1, 2) North, East [m]; NaN in rows before its first target observation."""

    @classmethod
    def blank(cls, periods: int, vehicles: int) -> "LiveRows":
        """Rows of a run that knows no plan, plan age or setpoint rate (a FlightRecord alone)."""
        return cls(
            plans=np.full((periods, vehicles, 1, 2), np.nan),
            setpoint_rate_hz=np.full((periods, vehicles), np.nan),
            plan_age_s=np.full((periods, vehicles, max(vehicles - 1, 0)), np.nan),
            target_path=np.full((periods, 1, 2), np.nan),
        )


@dataclass(frozen=True, eq=False)
class RunConstants:
    """What a FlightRecord of a run holds that is the same in every period (known before the
    flight: a recording logs it when it opens)."""

    scenario: str
    vehicle_ids: tuple[int, ...]
    desired_distance_m: np.ndarray
    """Desired distance between slots (N, N) [m]."""
    trail_m: float
    """Desired target-to-centre distance d_s [m]."""
    speed_max_m_s: float
    yaw_rate_max_rad_s: float
    d_safe_m: float
    prediction_horizon_periods: int = 0
    """How many periods ahead the record's `target_prediction` looks (the controller's horizon
    M)."""
    plan_stale_s: float | None = None
    """The agents' plan age past which a neighbour counts as silent [s]: what the viewer counts
    as a stale plan. Not in a FlightRecord (None in the constants of one)."""

    @classmethod
    def of_scenario(cls, sc, desired_distance_m: np.ndarray) -> "RunConstants":
        """The constants of a run of scenario `sc` (a `fleetmpc.scenario.Scenario`) whose
        formation has these desired distances between slots (N, N) [m]."""
        return cls(
            scenario=sc.name,
            vehicle_ids=sc.vehicle_ids,
            desired_distance_m=desired_distance_m,
            trail_m=sc.formation.trail_m,
            speed_max_m_s=sc.controller.speed_max_m_s,
            yaw_rate_max_rad_s=sc.controller.yaw_rate_max_rad_s,
            d_safe_m=sc.controller.d_safe_m,
            prediction_horizon_periods=sc.controller.horizon,
            plan_stale_s=sc.controller.plan_stale_s,
        )

    @classmethod
    def of(cls, rec: FlightRecord) -> "RunConstants":
        """The constants of a record."""
        return cls(**{name: getattr(rec, name) for name in _record_constants()})

    def as_fields(self) -> dict:
        """The constants a FlightRecord holds, by field name."""
        return {name: getattr(self, name) for name in _record_constants()}


def _record_constants() -> tuple[str, ...]:
    """The RunConstants fields that are FlightRecord fields too."""
    record = {f.name for f in fields(FlightRecord)}
    return tuple(f.name for f in fields(RunConstants) if f.name in record)


def period_rows(rec: FlightRecord, name: str) -> np.ndarray:
    """The per-period field `name` of PERIOD_FIELDS: NaN rows of its shape where an optional
    one (`target_prediction`, `plan_age_s`) was not recorded."""
    value = getattr(rec, name)
    if value is not None:
        return np.asarray(value)
    k, n = rec.truth.shape[:2]
    shape = (k, 2) if name == "target_prediction" else (k, n, max(n - 1, 0))
    return np.full(shape, np.nan)
