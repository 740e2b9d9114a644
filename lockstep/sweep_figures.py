"""The figures of a sweep: each metric against each varied field, the median over seeds with a
95 % confidence band, the gates as dashed lines; PNG and SVG.

A figure's x axis is one factor of the sweep: a varied field (``--vary``), learning (when both
on and off are flown), the fault file (when several are), or the scenario when nothing else
varies. Each line is one combination of the other factors (the scenario among them), and each
point the median of its runs over the seeds. The band is the distribution-free 95 % confidence
interval of that median: the order statistics x_(j) and x_(n+1-j) with j the largest for which
P(B <= j - 1) <= 2.5 %, B ~ Binomial(n, 1/2); with five seeds or fewer no such j exists and the
band is the range of the seeds (its coverage 1 - 2^(1-n) is written on the figure). A run that
failed has no numbers and is not counted; an infinite value (a corner never recovered from)
counts in the order statistics and is not drawn.

The figures depend only on the table's rows (sorted here, so not on the order runs finished in):
the same rows give the same files, byte for byte (SVG ids are salted with a constant and carry
no date).
"""

import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import binom  # noqa: E402

from fleetmpc.lockstep import suite  # noqa: E402

__all__ = ["FIGURE_METRICS", "Factor", "median_band", "sweep_factors", "write_sweep_figures"]

CONFIDENCE = 0.95


def _slot_gate(row: dict) -> float:
    paper = row["scenario"] == suite.PAPER_SCENARIO
    return suite.PAPER_SLOT_RMS_MAX_M if paper else suite.SLOT_RMS_MAX_M


FIGURE_METRICS: dict[str, tuple[str, Callable[[dict], float] | None]] = {
    "formation_rms_m": ("formation RMS, last 10 s [m]", _slot_gate),
    "min_separation_m": ("closest approach [m]", lambda row: row["d_safe_m"]),
    "separation_error_max_m": ("worst pair's separation error [m]", None),
    "centre_distance_error_m": ("fleet centre error [m]", None),
    "yaw_rate_reversals_per_vehicle_min": (
        "yaw-rate reversals [1/(vehicle min)]",
        lambda row: suite.REVERSALS_MAX_PER_VEHICLE_MIN,
    ),
    "qp_fallback_fraction": (
        "QP fallbacks [share of agent steps]",
        lambda row: suite.QP_FALLBACK_MAX_FRACTION,
    ),
    "target_prediction_rms_m": ("target prediction RMS [m]", None),
    "corner_recovery_s": (
        "longest corner recovery [s]",
        lambda row: suite.CORNER_RECOVERY_MAX_S,
    ),
}
"""Metric column -> (axis label, its gate for a row, or None). The slot-RMS gate holds for
learning-on runs with a feasible target, the corner gate for those with corners; the line shows
the threshold whatever the run."""

_COLOURS = ("tab:blue", "tab:red", "tab:green", "tab:orange", "tab:purple", "tab:brown")
_STYLE = {"svg.hashsalt": "fleetmpc-sweep", "svg.fonttype": "path", "figure.dpi": 100}


@dataclass(frozen=True)
class Factor:
    """One factor of a sweep: a column and its values, in the sweep's order."""

    column: str
    values: tuple[Any, ...]

    @property
    def numeric(self) -> bool:
        return all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in self.values
        )


def sweep_factors(rows: Sequence[dict], varied: Sequence[str]) -> tuple[list[Factor], list[Factor]]:
    """The factors that vary in `rows`: those drawn along x (the varied columns, learning,
    faults; the scenario when none of them varies) and all of them (the scenario too)."""
    factors = []
    for column in (*varied, "learning", "faults", "scenario"):
        values: list[Any] = []
        for r in rows:
            if r[column] not in values:
                values.append(r[column])
        if len(values) > 1 or (column == "scenario" and not factors):
            factors.append(Factor(column, tuple(_order(values))))
    along = [f for f in factors if f.column != "scenario"] or factors
    return along, factors


def _order(values: list[Any]) -> list[Any]:
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return sorted(values)
    if all(isinstance(v, bool) for v in values):
        return sorted(values, reverse=True)
    return sorted(values, key=lambda v: json.dumps(v, sort_keys=True))


def median_band(values: Sequence[float]) -> tuple[float, float, float, float]:
    """Median of `values`, the ends of its 95 % confidence interval (module docstring) and
    that interval's coverage; NaNs when there are none."""
    x = np.sort(np.asarray(values, dtype=float))
    n = x.size
    if n == 0:
        return math.nan, math.nan, math.nan, math.nan
    cdf = binom.cdf(np.arange(n), n, 0.5)  # P(B <= k), k = 0 .. n - 1
    ok = np.flatnonzero(cdf <= (1.0 - CONFIDENCE) / 2.0)
    j = int(ok[-1]) + 1 if ok.size else 1
    coverage = 1.0 - 2.0 * float(cdf[j - 1])
    median = float(np.median(x)) if np.isfinite(x).all() else float(x[(n - 1) // 2])
    return median, float(x[j - 1]), float(x[n - j]), coverage


def _label(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    if value is None:
        return "none"
    return value if isinstance(value, str) else json.dumps(value)


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")


def _finite(x: float) -> float:
    return x if math.isfinite(x) else math.nan


def _figure(
    rows: Sequence[dict], metric: str, x: Factor, others: Sequence[Factor], seeds: int
) -> plt.Figure:
    label, gate = FIGURE_METRICS[metric]
    keyed: dict[tuple, dict[Any, list[dict]]] = {}
    for r in rows:
        key = tuple(json.dumps(r[f.column], sort_keys=True) for f in others)
        keyed.setdefault(key, {}).setdefault(json.dumps(r[x.column], sort_keys=True), []).append(r)
    positions = list(x.values) if x.numeric else list(range(len(x.values)))
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    gates: dict[tuple, list[float]] = {}
    coverages = set()
    for i, key in enumerate(sorted(keyed)):
        colour = _COLOURS[i % len(_COLOURS)]
        med, lo, hi, gate_values = [], [], [], []
        for value in x.values:
            group = keyed[key].get(json.dumps(value, sort_keys=True), [])
            values = [r[metric] for r in group if r[metric] is not None]
            m, a, b, coverage = median_band(values)
            if values:
                coverages.add(round(coverage, 4))
            med.append(_finite(m))
            lo.append(_finite(a))
            hi.append(_finite(b))
            g = [gate(r) for r in group] if gate is not None else []
            gate_values.append(g[0] if g and len(set(g)) == 1 else math.nan)
        name = ", ".join(
            f"{f.column} {_label(json.loads(k))}" for f, k in zip(others, key, strict=True)
        )
        ax.plot(positions, med, marker="o", color=colour, label=name or "median")
        ax.fill_between(positions, lo, hi, color=colour, alpha=0.2, linewidth=0)
        gates[key] = gate_values
    if gate is not None:
        every = {v for g in gates.values() for v in g if not math.isnan(v)}
        if len(every) == 1:
            ax.axhline(every.pop(), color="black", linestyle="--", linewidth=1, label="gate")
        else:
            for i, key in enumerate(sorted(gates)):
                colour = _COLOURS[i % len(_COLOURS)]
                ax.plot(
                    positions,
                    gates[key],
                    color=colour,
                    linestyle="--",
                    linewidth=1,
                    label="gate" if i == 0 else None,
                )
    if not x.numeric or len(positions) <= 12:
        ax.set_xticks(positions, [_label(v) for v in x.values])
    ax.set_xlabel(x.column)
    ax.set_ylabel(label)
    band = (
        "95 % CI of the median"
        if coverages and min(coverages) >= CONFIDENCE
        else f"range of the seeds (CI coverage {min(coverages, default=0):.0%})"
    )
    ax.set_title(f"{metric} vs {x.column}\nmedian over {seeds} seeds, band: {band}", fontsize=10)
    ax.grid(True, alpha=0.3)
    if len(keyed) > 1 or gate is not None:
        ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def write_sweep_figures(
    rows: Sequence[dict], varied: Sequence[str], out_dir: str | Path, *, seeds: int
) -> list[Path]:
    """Write every figure (`FIGURE_METRICS` x the sweep's factors) into `out_dir` as
    ``METRIC__FACTOR.png`` and ``.svg``; the paths written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    flown = sorted((r for r in rows if r["status"] == "ok"), key=lambda r: r["run_id"])
    if not flown:
        return []
    along, factors = sweep_factors(flown, varied)
    paths = []
    with plt.rc_context(_STYLE):
        for metric in FIGURE_METRICS:
            if all(r[metric] is None for r in flown):
                continue
            for x in along:
                others = [f for f in factors if f is not x]
                fig = _figure(flown, metric, x, others, seeds)
                stem = out / f"{metric}__{_slug(x.column)}"
                fig.savefig(stem.with_suffix(".png"))
                fig.savefig(stem.with_suffix(".svg"), metadata={"Date": None})
                plt.close(fig)
                paths += [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    return paths
