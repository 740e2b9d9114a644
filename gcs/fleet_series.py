"""Fleet-level time series: a line or two for the whole fleet, whatever its size.

What the viewer shows by default (`fleetmpc.gcs.blueprint`): a fleet of 50 has 1,225 pairs and
2,450 (vehicle, neighbour) plan ages, too many lines to read; these say how the fleet as a whole
is doing each period, and the per-vehicle and per-pair series stay in the recording beside them
(docs/design.md, "Ground station and Rerun recording").
"""

import warnings

import numpy as np

from fleetmpc.gcs.record import FlightRecord, LiveRows

__all__ = ["FLEET_SERIES", "fleet_rows", "stale_plan_count"]

FLEET_SERIES = {
    "min_separation": ("minimum separation, d_safe [m]", ("minimum separation", "d_safe")),
    "formation_error": ("formation error [m]: worst, median", ("worst", "median")),
    "step_time_ms": ("agent step [ms]: median, p99", ("median", "p99")),
    "stale_plans": ("stale neighbour plans", ("stale plans",)),
    "learning_error": (
        "learned vs truth, worst",
        ("effectiveness (relative)", "drift [m/s]"),
    ),
}
"""Entity `series/fleet/<name>` -> (the view's title, its lines' names), in the views' order."""


def _quiet(reduce, values: np.ndarray, **kwargs) -> np.ndarray:
    """A NaN-ignoring numpy reduction over the last axis; NaN where a row has no value (numpy
    warns of such a row; it is simply not logged)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return reduce(values, axis=-1, **kwargs)


def stale_plan_count(plan_age_s: np.ndarray, *, plan_stale_s: float | None) -> np.ndarray:
    """(K,) per period, the (vehicle, neighbour) whose neighbour's plan, as the vehicle used it,
    is older than `plan_stale_s` (the agents' own limit: past it they take the neighbour as
    silent, until they forget its plan); NaN in periods where no vehicle reported an age, or
    with no limit known. A vehicle reports no age for a neighbour it has no plan of, whether
    that one is silent or beyond its neighbourhood (a large fleet's agents keep only their
    neighbourhood's plans): such a pair is not counted."""
    ages = np.asarray(plan_age_s, dtype=np.float64)
    k = ages.shape[0]
    flat = ages.reshape(k, -1)
    if plan_stale_s is None or flat.shape[1] == 0:
        return np.full(k, np.nan)
    reported = np.isfinite(flat).any(axis=1)
    with np.errstate(invalid="ignore"):
        stale = (flat > plan_stale_s).sum(axis=1)
    return np.where(reported, stale, np.nan)


def _learning_error(rec: FlightRecord) -> np.ndarray:
    """(K, 2) the worst vehicle's relative effectiveness error (a_V or a_w, whichever is worse)
    and the worst drift error [m/s] against the truth."""
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.abs(rec.beta[..., :2] - rec.beta_truth[..., :2]) / rec.beta_truth[..., :2]
    drift = np.linalg.norm(rec.beta[..., 2:] - rec.beta_truth[..., 2:], axis=-1)
    return np.stack([_quiet(np.nanmax, _quiet(np.nanmax, relative)), _quiet(np.nanmax, drift)], 1)


def fleet_rows(
    rec: FlightRecord,
    live: LiveRows,
    *,
    separation_m: np.ndarray,
    plan_stale_s: float | None,
) -> dict[str, np.ndarray]:
    """Each `FLEET_SERIES` entity's rows (K, lines) for a slice of periods; `separation_m`
    (K, P) is every pair's distance in those periods."""
    k = len(rec.t_s)
    slot_error = np.linalg.norm(rec.truth[:, :, :2] - rec.slots, axis=2)
    closest = _quiet(np.nanmin, separation_m) if separation_m.shape[1] else np.full(k, np.nan)
    return {
        "min_separation": np.stack([closest, np.full(k, rec.d_safe_m)], axis=1),
        "formation_error": np.stack(
            [_quiet(np.nanmax, slot_error), _quiet(np.nanmedian, slot_error)], axis=1
        ),
        "step_time_ms": np.stack(
            [
                _quiet(np.nanmedian, rec.step_time_ms),
                _quiet(np.nanpercentile, rec.step_time_ms, q=99),
            ],
            axis=1,
        ),
        "stale_plans": stale_plan_count(live.plan_age_s, plan_stale_s=plan_stale_s)[:, None],
        "learning_error": _learning_error(rec),
    }
