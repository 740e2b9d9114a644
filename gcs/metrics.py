"""Run metrics (the numbers the issue gates and the paper's Figs. 1-4 are about)."""

import math

import numpy as np

from fleetmpc.gcs.record import FlightRecord

__all__ = [
    "format_summary",
    "judged_metrics",
    "known_model_figures",
    "CORNER_MIN_SPEED_M_S",
    "CORNER_RECOVERED_M",
    "CORNER_SPEED_STEP_M_S",
    "CORNER_TURN_RAD",
    "REVERSAL_FRACTION",
    "compute_metrics",
    "corner_indices",
    "corner_recovery_s",
    "pair_indices",
    "plan_age_summary",
    "target_prediction_rms_m",
    "yaw_rate_reversals_per_vehicle_min",
]

REVERSAL_FRACTION = 0.5
"""A yaw-rate reversal: consecutive commands of opposite signs, both larger in magnitude than this
fraction of the yaw-rate bound."""

CORNER_TURN_RAD = 0.5
"""A corner: the true target's course changes by more than this from one period to the next
[rad]."""

CORNER_MIN_SPEED_M_S = 0.05
"""...while the target moves faster than this on both sides of the change [m/s]."""

CORNER_SPEED_STEP_M_S = 0.3
"""Also a corner: the true target's speed changes by more than this from one period to the next
(it stops or sets off at once) [m/s]."""

CORNER_RECOVERED_M = 0.3
"""Recovered from a corner: the worst vehicle's distance to its slot stays within this [m]."""


def pair_indices(n: int) -> list[tuple[int, int]]:
    """Every unordered pair of vehicle indices."""
    return [(a, b) for a in range(n) for b in range(a + 1, n)]


def _window(t_s: np.ndarray, seconds: float) -> np.ndarray:
    return t_s >= t_s[-1] - seconds + 1e-9


def compute_metrics(rec: FlightRecord) -> dict:
    """Metrics of a run; windows are the last 10 s (formation) and last 5 s (c)."""
    n = len(rec.vehicle_ids)
    w10 = _window(rec.t_s, 10.0)
    w5 = _window(rec.t_s, 5.0)
    pos = rec.truth[:, :, :2]
    pairs = pair_indices(n)
    sep_err = []
    for a, b in pairs:
        d = np.linalg.norm(pos[:, a] - pos[:, b], axis=1)
        sep_err.append(float(np.mean(np.abs(d[w10] - rec.desired_distance_m[a, b]))))
    # The fleet's centre (each vehicle less its slot's offset, averaged) against the formation's.
    centre = np.mean(pos - rec.slot_offsets_world, axis=1)
    centre_err = np.linalg.norm(centre - (rec.slots[:, 0] - rec.slot_offsets_world[:, 0]), axis=1)
    slot_dist = np.linalg.norm(pos - rec.slots, axis=2)
    c_norm = np.linalg.norm(rec.c, axis=2)
    tol = 1e-9
    known = np.isfinite(rec.command).all(axis=-1)  # a live record may miss some commands
    inside = (np.abs(rec.command[..., 0]) <= rec.speed_max_m_s + tol) & (
        np.abs(rec.command[..., 1]) <= rec.yaw_rate_max_rad_s + tol
    )
    b_end, t_end = rec.beta[-1], rec.beta_truth[-1]
    beta_error = [
        {
            "vehicle": int(vid),
            "speed_effectiveness": float(abs(b_end[i, 0] - t_end[i, 0]) / t_end[i, 0]),
            "yaw_rate_effectiveness": float(abs(b_end[i, 1] - t_end[i, 1]) / t_end[i, 1]),
            "drift_m_s": float(np.linalg.norm(b_end[i, 2:] - t_end[i, 2:])),
        }
        for i, vid in enumerate(rec.vehicle_ids)
    ]
    times = rec.step_time_ms[np.isfinite(rec.step_time_ms)]
    return {
        "separation_pairs": [[rec.vehicle_ids[a], rec.vehicle_ids[b]] for a, b in pairs],
        "separation_error_m": sep_err,
        "centre_distance_error_m": float(np.mean(centre_err[w10])),
        "formation_rms_m": float(np.sqrt(np.mean(slot_dist[w10] ** 2))),
        "c_norm_final": float(np.max(np.mean(c_norm[w5], axis=0))),
        "min_separation_m": float(rec.min_separation_m),
        "inputs_within_bounds": float(np.mean(inside[known])) if known.any() else None,
        "beta_error": beta_error,
        "step_time_ms": {
            "median": float(np.median(times)) if times.size else None,
            "p99": float(np.percentile(times, 99)) if times.size else None,
        },
        "qp_fallbacks": int(np.sum(~rec.qp_ok)),
        "yaw_rate_reversals_per_vehicle_min": yaw_rate_reversals_per_vehicle_min(rec),
        "slot_rms_max_vehicle_m": float(np.max(np.sqrt(np.mean(slot_dist[w10] ** 2, axis=0)))),
        "target_prediction_rms_m": target_prediction_rms_m(rec),
        "corner_recovery_s": corner_recovery_s(rec),
        "corners": len(corner_indices(rec.target_velocity)),
        "plan_age_s": plan_age_summary(rec),
        **({} if rec.network is None else {"network": rec.network}),
    }


def plan_age_summary(rec: FlightRecord) -> dict | None:
    """Median, p99 and largest age of the neighbours' plans as the agents used them, and the
    share of (period, vehicle, neighbour) with no plan at all [s]; None when not recorded."""
    if rec.plan_age_s is None or rec.plan_age_s.size == 0:
        return None
    ages = np.asarray(rec.plan_age_s, dtype=float)
    known = ages[np.isfinite(ages)]
    return {
        "median": float(np.median(known)) if known.size else None,
        "p99": float(np.percentile(known, 99)) if known.size else None,
        "max": float(known.max()) if known.size else None,
        "missing_fraction": float(1.0 - known.size / ages.size),
    }


def yaw_rate_reversals_per_vehicle_min(rec: FlightRecord) -> float:
    """Yaw-rate reversals per vehicle and minute of flight, over the whole run.

    A reversal is a pair of consecutive periods whose commanded yaw rates have opposite signs,
    both beyond `REVERSAL_FRACTION` of the bound; a non-finite command breaks the pair. 0.0 for
    a run of no duration (it has no pairs).
    """
    w = rec.command[..., 1]  # (K, N)
    big = np.abs(w) > REVERSAL_FRACTION * rec.yaw_rate_max_rad_s  # False where not finite
    flips = (w[:-1] * w[1:] < 0.0) & big[:-1] & big[1:]
    minutes = (float(rec.t_s[-1]) - float(rec.t_s[0])) / 60.0
    if not minutes > 0.0:
        return 0.0
    return float(np.sum(flips)) / (len(rec.vehicle_ids) * minutes)


def target_prediction_rms_m(rec: FlightRecord) -> float | None:
    """RMS error of the recorded target prediction against where the target then was [m].

    Over every period k whose prediction is finite and whose target position H periods later is
    in the record (H = `prediction_horizon_periods`); None without a prediction or such k.
    """
    if rec.target_prediction is None or rec.prediction_horizon_periods < 0:
        return None
    h = rec.prediction_horizon_periods
    k = len(rec.t_s) - h  # periods whose horizon ends inside the record
    if k <= 0:
        return None
    predicted = np.asarray(rec.target_prediction, dtype=float)[:k]
    known = np.isfinite(predicted).all(axis=1)
    if not known.any():
        return None
    err = predicted[known] - rec.target[h:][known]
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


def corner_indices(target_velocity_m_s: np.ndarray) -> list[int]:
    """Periods at which the target turns a corner (its first period on the new course), from its
    velocity (K, 2) [m/s] sampled once a period.

    A corner is a change of course of more than `CORNER_TURN_RAD` from one period to the next
    while the target moves faster than `CORNER_MIN_SPEED_M_S` on both sides, or a change of
    speed of more than `CORNER_SPEED_STEP_M_S` (a stop, a start); a run of consecutive such
    periods is one manoeuvre, counted once at its first period.
    """
    v = np.asarray(target_velocity_m_s, dtype=float)
    speed = np.hypot(v[:, 0], v[:, 1])
    course = np.arctan2(v[:, 1], v[:, 0])
    turn = np.abs(np.angle(np.exp(1j * np.diff(course))))  # wrapped to [0, pi]
    moving = (speed[:-1] > CORNER_MIN_SPEED_M_S) & (speed[1:] > CORNER_MIN_SPEED_M_S)
    jump = np.abs(np.diff(speed)) > CORNER_SPEED_STEP_M_S
    sharp = np.flatnonzero(((turn > CORNER_TURN_RAD) & moving) | jump) + 1
    return [int(k) for i, k in enumerate(sharp) if i == 0 or sharp[i - 1] != k - 1]


def corner_recovery_s(rec: FlightRecord) -> float | None:
    """The longest recovery from a corner of the target [s]; None when it turned none.

    Recovery from a corner at t_c: the first time t >= t_c from which the worst vehicle's
    distance to its slot stays within `CORNER_RECOVERED_M` until the next corner (or the end of
    the run), less t_c; inf when that never happens.
    """
    corners = corner_indices(rec.target_velocity)
    if not corners:
        return None
    pos = rec.truth[:, :, :2]
    worst = np.max(np.linalg.norm(pos - rec.slots, axis=2), axis=1)  # nan where unknown
    within = worst <= CORNER_RECOVERED_M  # False where not finite
    ends = [*corners[1:], len(rec.t_s)]
    recovery = []
    for start, end in zip(corners, ends, strict=True):
        out = np.flatnonzero(~within[start:end])
        first = start if out.size == 0 else start + int(out[-1]) + 1
        recovery.append(math.inf if first >= end else float(rec.t_s[first]) - float(rec.t_s[start]))
    return max(recovery)


def _fraction(x: float | None) -> str:
    return "unknown" if x is None else f"{x:.4f}"


def format_summary(metrics: dict) -> str:
    """A human-readable table of the metrics."""
    rows = [
        ("scenario", metrics["scenario"]),
        ("learning", "on" if metrics["learning"] else "off"),
        ("feasible", "yes" if metrics["feasible"] else "NO (the target outruns the team)"),
        ("duration", f"{metrics['duration_s']:.1f} s"),
    ]
    rows += _separation_rows(metrics)
    rows += [
        ("centre distance error", _metres(metrics["centre_distance_error_m"])),
        ("formation RMS", _metres(metrics["formation_rms_m"])),
        *_known_model_rows(metrics),
        ("||c|| final", f"{metrics['c_norm_final']:.4f}"),
        ("min separation", f"{metrics['min_separation_m']:.3f} m"),
        ("inputs within U", _fraction(metrics["inputs_within_bounds"])),
        ("QP fallbacks", str(metrics["qp_fallbacks"])),
    ]
    rows += _manoeuvre_rows(metrics)
    rows += _network_rows(metrics)
    st = metrics["step_time_ms"]
    if st["median"] is not None:
        rows.append(("agent step", f"median {st['median']:.3f} ms, p99 {st['p99']:.3f} ms"))
    if "periods_recorded" in metrics:  # a live run's ground station
        recorded, expected = metrics["periods_recorded"], metrics["periods_expected"]
        rows.append(("periods recorded", f"{recorded} of {expected}"))
    rows += _beta_rows(metrics["beta_error"])
    for vid in metrics.get("beta_error_without_truth", ()):
        rows.append((f"beta error UAV {vid}", "unknown: no simulated truth (a real autopilot)"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


SUMMARY_LISTED_MAX = 10
"""Up to this many pairs (or vehicles) the summary lists each one; a larger fleet's gets the
worst and the median (`--metrics` holds every one)."""


def _separation_rows(metrics: dict) -> list[tuple[str, str]]:
    pairs, errors = metrics["separation_pairs"], metrics["separation_error_m"]
    if len(pairs) <= SUMMARY_LISTED_MAX:
        return [
            (f"separation error {a}-{b}", f"{e:.4f} m")
            for (a, b), e in zip(pairs, errors, strict=True)
        ]
    worst = int(np.argmax(errors))
    a, b = pairs[worst]
    return [
        (
            f"separation error, {len(pairs)} pairs",
            f"worst {a}-{b} {errors[worst]:.4f} m, median {np.median(errors):.4f} m",
        )
    ]


def _beta_rows(beta_error: list[dict]) -> list[tuple[str, str]]:
    if len(beta_error) <= SUMMARY_LISTED_MAX:
        return [
            (
                f"beta error UAV {b['vehicle']}",
                f"a_V {100 * b['speed_effectiveness']:.1f} %, "
                f"a_w {100 * b['yaw_rate_effectiveness']:.1f} %, "
                f"drift {b['drift_m_s']:.3f} m/s",
            )
            for b in beta_error
        ]

    def worst(key: str) -> dict:
        return max(beta_error, key=lambda b: b[key])

    v, w, d = worst("speed_effectiveness"), worst("yaw_rate_effectiveness"), worst("drift_m_s")
    return [
        (
            f"beta error, {len(beta_error)} UAVs",
            f"worst a_V {100 * v['speed_effectiveness']:.1f} % (UAV {v['vehicle']}), "
            f"a_w {100 * w['yaw_rate_effectiveness']:.1f} % (UAV {w['vehicle']}), "
            f"drift {d['drift_m_s']:.3f} m/s (UAV {d['vehicle']})",
        )
    ]


NOT_JUDGED = "not judged: the target is not the scenario's (fleetmpc up --target)"
"""What the summary says of a figure against the target when the ground station does not know
where the target was (`TARGET_FIGURES`)."""

TARGET_FIGURES = (
    "centre_distance_error_m",
    "formation_rms_m",
    "slot_rms_max_vehicle_m",
    "target_prediction_rms_m",
    "corners",
    "corner_recovery_s",
)
"""The metrics measured against the scenario's target, which mean nothing when the fleet
follows another (a MAVLink system): the ground station leaves them None then."""


def judged_metrics(
    rec: FlightRecord, *, ground_truth: list[int] | None, target_source: str = "script"
) -> dict:
    """`compute_metrics` less what the run cannot judge, as the ground station and `fleetmpc
    report` of its recording both give them: the learned model's error of a vehicle its
    simulator sent no ground truth for (`ground_truth`: the vehicles that did; None: all, a
    lockstep run) is left out and the vehicle listed in `beta_error_without_truth`; a fleet
    that followed another target than the scenario's (`target_source` not "script") has
    `TARGET_FIGURES` None."""
    metrics = compute_metrics(rec)
    if ground_truth is not None:
        errors = metrics["beta_error"]
        metrics["beta_error"] = [b for b in errors if b["vehicle"] in ground_truth]
        untrue = [b["vehicle"] for b in errors if b["vehicle"] not in ground_truth]
        if untrue:
            metrics["beta_error_without_truth"] = untrue
    if target_source != "script":
        metrics |= dict.fromkeys(TARGET_FIGURES)
    return metrics


def known_model_figures(metrics: dict, known_rms_m: float) -> dict:
    """The known-model run's formation RMS beside a run's `metrics`, and their ratio
    (`learned_over_known`; NaN when the known model's is 0)."""
    rms = metrics["formation_rms_m"]
    ratio = rms / known_rms_m if rms is not None and known_rms_m > 0 else float("nan")
    return {"known_model_formation_rms_m": known_rms_m, "learned_over_known": ratio}


def _metres(x: float | None) -> str:
    return NOT_JUDGED if x is None else f"{x:.4f} m"


def _known_model_rows(metrics: dict) -> list[tuple[str, str]]:
    """The known-model run's formation RMS and the ratio, where `sim --known-model` added them."""
    if "known_model_formation_rms_m" not in metrics:
        return []
    return [
        ("formation RMS, known model", f"{metrics['known_model_formation_rms_m']:.4f} m"),
        ("learned over known", f"{metrics['learned_over_known']:.2f}"),
    ]


def _network_rows(metrics: dict) -> list[tuple[str, str]]:
    """Rows of the plan ages the agents used and of what the plan bus did (a lockstep run's)."""
    rows = []
    ages = metrics.get("plan_age_s")
    if ages is not None and ages["max"] is not None:
        rows.append(
            (
                "neighbour plan age",
                f"median {ages['median']:.2f} s, p99 {ages['p99']:.2f} s, max {ages['max']:.2f} s,"
                f" none {100 * ages['missing_fraction']:.1f} %",
            )
        )
    network = metrics.get("network")
    if network is None:
        return rows
    for fault in network["faults"]:
        rows.append(("fault injected", fault))
    injected = network.get("injected")
    if injected:
        done = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in injected.items() if v)
        rows.append(("faults did", done or "nothing"))
    got = network["received"]
    rows.append(
        (
            "plan bus received",
            f"{got['published']} plans sent, {got['accepted']} messages accepted (plans and"
            f" target observations); dropped as duplicates {got['duplicates']}, out of order"
            f" {got['out_of_order']}",
        )
    )
    each = network.get("per_agent_period")
    if each is not None:
        rows.append(
            (
                "plan bus per agent",
                f"{each['accepted']:.1f} messages kept and {each['filtered']:.1f} plans dropped"
                " as beyond its neighbourhood, per period",
            )
        )
    return rows


def _manoeuvre_rows(metrics: dict) -> list[tuple[str, str]]:
    """Rows of the worst vehicle, yaw-rate reversals, target prediction and corners (absent from
    a metrics file written before they existed)."""
    rows = []
    if "slot_rms_max_vehicle_m" in metrics:
        rows.append(("worst vehicle slot RMS", _metres(metrics["slot_rms_max_vehicle_m"])))
    reversals = metrics.get("yaw_rate_reversals_per_vehicle_min")
    if reversals is not None:
        rows.append(("yaw-rate reversals", f"{reversals:.2f} per vehicle-minute"))
    if "target_prediction_rms_m" in metrics:
        rms = metrics["target_prediction_rms_m"]
        rows.append(("target prediction RMS", "unknown" if rms is None else f"{rms:.3f} m"))
    corners = metrics.get("corners")
    if corners is not None:
        rows.append(("target corners", str(corners)))
    recovery = metrics.get("corner_recovery_s")
    if recovery is not None:
        text = "never" if recovery == math.inf else f"{recovery:.1f} s"
        rows.append(("corner recovery (worst)", text))
    return rows
