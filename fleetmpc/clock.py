"""The fleet's clocks, all integer nanoseconds.

A simulated vehicle's time since boot: `RealTimeClock` runs K times faster than the wall clock
(K = `--speed`); `ManualClock` only moves when a test advances it; the SITL reads time only
through a `Clock`.

Fleet time, shared by every process of a fleet: simulated nanoseconds since a common epoch,
``fleet_ns = (host_wall_ns - epoch_ns) * speed`` (`FleetClock`); `ClockSync` maps an
autopilot's boot time onto it (the agent runner and the ground station; see
`fleetmpc.onboard.runner` for how the epoch is agreed).
"""

import math
import threading
import time
from collections import deque
from fractions import Fraction
from typing import Protocol

from fleetmpc.errors import ConfigError

__all__ = [
    "Clock",
    "ClockSync",
    "EpochMismatchError",
    "FleetClock",
    "ManualClock",
    "RealTimeClock",
]


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


class EpochMismatchError(ConfigError):
    """The announced fleet epoch runs at a different speed than this process was started with."""


_SPEED_RTOL = 1e-6


class FleetClock:
    """Fleet time from the host's wall clock: (wall - epoch) x speed.

    Three ways to get the epoch: given at construction (`epoch_ns`), none at all (fleet time is
    the autopilot's boot time), or announced later (`awaiting_epoch=True`, then `set_epoch`
    once, e.g. from the fleet's epoch message). Reading and setting are guarded by a lock.
    """

    def __init__(
        self,
        *,
        epoch_ns: int | None = None,
        speed: float = 1.0,
        awaiting_epoch: bool = False,
        host_offset_ns: int = 0,
    ) -> None:
        if not (
            isinstance(speed, int | float)
            and not isinstance(speed, bool)
            and 0.01 <= speed <= 1000.0
        ):
            raise ConfigError("speed", f"must be in [0.01, 1000], got {speed!r}")
        if epoch_ns is not None and (isinstance(epoch_ns, bool) or not isinstance(epoch_ns, int)):
            raise ConfigError("epoch_ns", f"must be an integer, got {epoch_ns!r}")
        if awaiting_epoch and epoch_ns is not None:
            raise ConfigError("epoch_ns", "give an epoch or wait for one, not both")
        if isinstance(host_offset_ns, bool) or not isinstance(host_offset_ns, int):
            raise ConfigError("host_offset_ns", f"must be an integer, got {host_offset_ns!r}")
        self._speed = float(speed)
        self._lock = threading.Lock()
        self._epoch_ns = epoch_ns
        self._awaiting = awaiting_epoch
        self.host_offset_ns = host_offset_ns
        """How far this host's clock reads ahead of the fleet's [ns] (0 on a synchronized host;
        set to inject a clock offset)."""

    @property
    def speed(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self._speed

    @property
    def epoch_ns(self) -> int | None:
        """Host wall-clock time (time.time_ns) of fleet time 0; None: none (yet)."""
        with self._lock:
            return self._epoch_ns

    @property
    def uses_epoch(self) -> bool:
        """Fleet time comes from an epoch (given or awaited), not from the autopilot's boot."""
        with self._lock:
            return self._awaiting or self._epoch_ns is not None

    @property
    def ready(self) -> bool:
        """Fleet time can be told: an epoch is known, or none is used."""
        with self._lock:
            return not self._awaiting

    def set_epoch(self, epoch_ns: int, *, speed: float) -> bool:
        """Adopt an announced epoch; True if this call set it.

        Only the first announcement counts (later ones, even different, change nothing and
        return False). Raises EpochMismatchError if `speed` differs from this clock's speed.
        """
        if not math.isclose(speed, self._speed, rel_tol=_SPEED_RTOL):
            raise EpochMismatchError(
                "speed",
                f"the fleet epoch is announced at x{speed:g}, this process runs at "
                f"x{self._speed:g}",
            )
        if isinstance(epoch_ns, bool) or not isinstance(epoch_ns, int):
            raise ConfigError("epoch_ns", f"must be an integer, got {epoch_ns!r}")
        with self._lock:
            if not self._awaiting:
                return False
            self._epoch_ns, self._awaiting = epoch_ns, False
            return True

    def fleet_ns(self, wall_ns: int) -> int | None:
        """Fleet time at host wall time `wall_ns`: 0 without an epoch, None while awaiting one."""
        with self._lock:
            epoch, awaiting = self._epoch_ns, self._awaiting
        if awaiting:
            return None
        if epoch is None:
            return 0
        return round((wall_ns + self.host_offset_ns - epoch) * self._speed)


class ClockSync:
    """Offset from the autopilot's boot time to fleet time, by a moving minimum filter.

    Every telemetry sample gives ``fleet_ns(received) - time_boot_ns``; transport latency only
    ever makes it larger, so the minimum is the best estimate. An autopilot's clock may run at
    its own rate (PX4's SIH simulator runs about 1 % slower than the wall clock), so the minimum
    is taken over the samples received in the last `WINDOW_NS` of wall time only: the offset
    follows such a clock within its drift over the window. The filter keeps
    ``(received - first received) x speed - time_boot_ns``, which needs no epoch, so the
    samples taken before a late epoch announcement count as well.
    """

    WINDOW_NS = 3_000_000_000
    """Wall time over which the smallest sample is the offset [ns]: long enough to hold samples
    that crossed an idle link, short enough that a 1 % drift moves it by 30 ms at most."""

    def __init__(self, clock: FleetClock) -> None:
        self.clock = clock
        self.samples = 0
        self._ref_wall_ns: int | None = None
        self._window: deque[tuple[int, int]] = deque()
        """(received wall time, sample) of the window's candidates for its minimum, oldest
        first; each sample is smaller than every later one (a larger older one can never be
        the minimum again), so the first is the minimum."""
        self._last_ns = 0

    @property
    def _min_ns(self) -> int | None:
        return self._window[0][1] if self._window else None

    def update(self, *, time_boot_ns: int, received_wall_ns: int) -> None:
        """Take one telemetry sample."""
        if not self.clock.uses_epoch or time_boot_ns < 0:
            return
        if self._ref_wall_ns is None:
            self._ref_wall_ns = received_wall_ns
        sample = round((received_wall_ns - self._ref_wall_ns) * self.clock.speed) - time_boot_ns
        self.samples += 1
        self._last_ns = sample
        window = self._window
        while window and window[-1][1] >= sample:
            window.pop()
        window.append((received_wall_ns, sample))
        while window[0][0] < received_wall_ns - self.WINDOW_NS:
            window.popleft()

    def _shift(self) -> int | None:
        """Fleet time of the reference wall time (None before an epoch and a sample)."""
        if self._ref_wall_ns is None:
            return None
        return self.clock.fleet_ns(self._ref_wall_ns)

    @property
    def offset_ns(self) -> int | None:
        """Fleet time minus autopilot boot time (None before an epoch and a sample)."""
        if not self.clock.uses_epoch:
            return 0
        shift = self._shift()
        return None if shift is None or self._min_ns is None else self._min_ns + shift

    @property
    def last_sample_ns(self) -> int:
        """The newest sample's offset (0 before an epoch and a sample)."""
        shift = self._shift()
        return 0 if shift is None else self._last_ns + shift

    def fleet_ns(self, time_boot_ns: int) -> int | None:
        """Fleet time of an autopilot boot time (None before an epoch and a sample)."""
        offset = self.offset_ns
        return None if offset is None else time_boot_ns + offset
