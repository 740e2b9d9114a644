"""Simulated time for the SITL: an integer count of nanoseconds since boot.

`RealTimeClock` runs K times faster than the wall clock (K = `--speed`); `ManualClock` only
moves when a test advances it. Runners read time only through a `Clock`.
"""

import time
from fractions import Fraction
from typing import Protocol

from fleetmpc.errors import ConfigError

__all__ = ["Clock", "ManualClock", "RealTimeClock"]


class Clock(Protocol):
    """Source of simulated time."""

    def now_ns(self) -> int:
        """Simulated nanoseconds since boot; never decreases."""
        ...

    def wall_seconds(self, sim_ns: int) -> float:
        """Wall-clock seconds that `sim_ns` of simulated time takes (0 for a manual clock)."""
        ...


class RealTimeClock:
    """Wall-clock time scaled by `speed` (> 1 runs faster than real time), exact in integers."""

    def __init__(self, *, speed: float = 1.0) -> None:
        if not (isinstance(speed, int | float) and 0.01 <= speed <= 1000.0):
            raise ConfigError("speed", f"must be a number in [0.01, 1000], got {speed!r}")
        self._speed = Fraction(speed).limit_denominator(1000)
        self._start_ns = time.monotonic_ns()

    @property
    def speed(self) -> float:
        """Simulated seconds per wall-clock second."""
        return float(self._speed)

    def now_ns(self) -> int:
        elapsed_ns = time.monotonic_ns() - self._start_ns
        return elapsed_ns * self._speed.numerator // self._speed.denominator

    def wall_seconds(self, sim_ns: int) -> float:
        return max(sim_ns, 0) / float(self._speed) * 1e-9


class ManualClock:
    """A clock that moves only when told to; for tests and lockstep runs."""

    def __init__(self, *, start_ns: int = 0) -> None:
        self._now_ns = int(start_ns)

    def now_ns(self) -> int:
        return self._now_ns

    def wall_seconds(self, sim_ns: int) -> float:
        return 0.0

    def advance(self, duration_ns: int) -> int:
        """Move time forward by `duration_ns` (>= 0) and return the new time."""
        if duration_ns < 0:
            raise ValueError(f"time cannot go backwards (duration_ns = {duration_ns})")
        self._now_ns += int(duration_ns)
        return self._now_ns
