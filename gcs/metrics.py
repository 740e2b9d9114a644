"""Run metrics (the numbers the issue gates and the paper's Figs. 1-4 are about)."""

import numpy as np

from gcs.record import FlightRecord

__all__ = ["compute_metrics", "pair_indices"]


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
    centre = np.mean(pos - rec.slot_offsets_world, axis=1)
    centre_err = np.abs(np.linalg.norm(centre - rec.target, axis=1) - rec.trail_m)
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
    }
