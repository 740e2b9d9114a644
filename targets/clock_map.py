"""A source's clock mapped onto fleet time: offset and drift estimated from when fixes arrive.

A fix stamped `s` on the source's clock (its time since boot, a GPS time) arrives at fleet time
`r = s (1 + drift) + offset + delay`, the delay positive and varying. The mapping is the straight
line fitted (least squares) to the recent (s, r) pairs, refitted through the least-delayed pair
of each of ENVELOPE_BINS stretches of them, then lowered to pass under all of them (the
least-delayed fix had the least delay): its slope is 1 + drift, its value at s is the fleet
time of the fix. Until the pairs span `DRIFT_SPAN_S`, the drift is taken as 0.
"""

from collections import deque
from dataclasses import dataclass

__all__ = ["ClockEstimate", "SourceClock"]

DRIFT_SPAN_S = 20.0
"""Source time the pairs must span before a drift is estimated [s]."""

WINDOW = 600
"""Pairs kept (two minutes at 5 Hz)."""

ENVELOPE_BINS = 10
"""The drift is fitted through the least-delayed fix of each of this many stretches."""


@dataclass(frozen=True)
class ClockEstimate:
    """The mapping as last estimated."""

    offset_s: float
    """Fleet time at source time 0 [s]."""
    drift: float
    """Source clock's rate error (fleet seconds per source second, less 1)."""
    delay_spread_s: float
    """Largest delay of a recent fix beyond the least-delayed one [s]."""
    pairs: int
    """Pairs the estimate rests on."""

    def describe(self) -> str:
        return (
            f"source clock: offset {self.offset_s:.3f} s, drift {self.drift * 1e6:+.0f} ppm, "
            f"delay spread {self.delay_spread_s * 1e3:.0f} ms over {self.pairs} fixes"
        )


class SourceClock:
    """Estimates a source clock's mapping onto fleet time from (source, arrival) pairs."""

    def __init__(self, *, window: int = WINDOW) -> None:
        self._pairs: deque[tuple[float, float]] = deque(maxlen=window)
        self.estimate: ClockEstimate | None = None

    def add(self, source_s: float, arrived_fleet_s: float) -> None:
        """A fix stamped `source_s` arrived at `arrived_fleet_s`; re-estimate."""
        self._pairs.append((source_s, arrived_fleet_s))
        self.estimate = _fit(list(self._pairs))

    def fleet_s(self, source_s: float) -> float | None:
        """Fleet time of source time `source_s` [s], None before any pair."""
        e = self.estimate
        return None if e is None else e.offset_s + (1.0 + e.drift) * source_s

    def restart(self) -> None:
        """Forget the pairs (the source's clock restarted)."""
        self._pairs.clear()
        self.estimate = None


def _fit(pairs: list[tuple[float, float]]) -> ClockEstimate:
    s = [p[0] for p in pairs]
    n = len(pairs)
    slope = 1.0
    if max(s) - min(s) >= DRIFT_SPAN_S:
        slope = _slope(pairs)
        # Refit through the least-delayed fix of each of ENVELOPE_BINS stretches of source
        # time: the delays' spread leaves the fit, their floor stays.
        lo, width = min(s), (max(s) - min(s)) / ENVELOPE_BINS
        floor: dict[int, tuple[float, float]] = {}
        for a, b in pairs:
            k = min(int((a - lo) / width), ENVELOPE_BINS - 1)
            if k not in floor or b - slope * a < floor[k][1] - slope * floor[k][0]:
                floor[k] = (a, b)
        slope = _slope(list(floor.values()))
    residuals = [b - slope * a for a, b in pairs]
    offset = min(residuals)
    return ClockEstimate(
        offset_s=offset, drift=slope - 1.0, delay_spread_s=max(residuals) - offset, pairs=n
    )


def _slope(pairs: list[tuple[float, float]]) -> float:
    """Least-squares slope of fleet time over source time."""
    n = len(pairs)
    ms = sum(a for a, _ in pairs) / n
    mr = sum(b for _, b in pairs) / n
    sxx = sum((a - ms) ** 2 for a, _ in pairs)
    return sum((a - ms) * (b - mr) for a, b in pairs) / sxx
