"""From a source's fix to an observation on fleet time: screened, placed about home, stamped.

Each fix is placed in the fleet's local North-East frame about the scenario's home
(`fleetmpc.protocol.local_frame.ned_from_geodetic`), screened (`fleetmpc.targets.screen`), and,
if accepted, stamped with the fleet time its source time maps to (`fleetmpc.targets.clock_map`,
the fix's arrival added first). Its noise is the one given, or estimated from the accepted fixes'
second differences. A source whose clock restarts or jumps (RESTART_AFTER fixes in a row going
back in time, or ahead of fleet time) has its clock and screen started afresh, and says so.
"""

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from fleetmpc.protocol.local_frame import ned_from_geodetic
from fleetmpc.targets.clock_map import SourceClock
from fleetmpc.targets.fix import Fix
from fleetmpc.targets.screen import ObservationScreen, ScreenLimits
from fleetmpc.targets.track import noise_estimate

__all__ = ["Observation", "ObservationPipeline"]

RESTART_AFTER = 10
"""Fixes in a row going back in time, or ahead of fleet time, after which the source's clock is
taken to have restarted or jumped, and its mapping is estimated afresh."""

NOISE_FIXES = 50
"""Accepted fixes the noise is estimated over."""

MIN_NOISE_M = 0.05
"""An estimated noise is never below this [m]."""


@dataclass(frozen=True)
class Observation:
    """An accepted fix as the fleet sees it."""

    stamp_ns: int
    """Fleet time of the fix [ns]."""
    north_m: float
    east_m: float
    velocity_m_s: tuple[float, float] | None
    noise_std_m: float


class ObservationPipeline:
    """Screens, places and stamps a source's fixes; `log` lines say what it rejected."""

    def __init__(
        self,
        *,
        home_lat_deg: float,
        home_lon_deg: float,
        limits: ScreenLimits,
        noise_m: float | None = None,
    ) -> None:
        self._home = (home_lat_deg, home_lon_deg)
        self._limits = limits
        self.screen = ObservationScreen(limits)
        self.clock = SourceClock()
        self._noise_m = noise_m
        self._recent: deque[tuple[float, float]] = deque(maxlen=NOISE_FIXES)
        self._clock_faults_in_a_row = 0
        """Fixes in a row rejected for the same fault of the source's clock."""
        self._clock_fault = ""
        self.log: list[str] = []

    def take(self, fix: Fix, now_s: float) -> Observation | None:
        """The observation `fix` makes, arrived at fleet time `now_s` [s]; None if rejected."""
        north, east = math.nan, math.nan
        if math.isfinite(fix.lat_deg) and math.isfinite(fix.lon_deg):
            north, east = ned_from_geodetic(
                fix.lat_deg, fix.lon_deg, home_lat_deg=self._home[0], home_lon_deg=self._home[1]
            )
        why = self.screen.check(fix, north, east, fleet_s=self._fleet_s(fix), now_s=now_s)
        if why is not None:
            self.log.append(why)
            self._restart_if_rebooted(why)
            return None
        self._clock_faults_in_a_row, self._clock_fault = 0, ""
        self.clock.add(fix.source_s, now_s)
        stamp_s = min(self.clock.fleet_s(fix.source_s), now_s)
        self._recent.append((north, east))
        return Observation(
            stamp_ns=max(0, round(stamp_s * 1e9)),
            north_m=north,
            east_m=east,
            velocity_m_s=fix.velocity_ne_m_s,
            noise_std_m=self.noise_m,
        )

    def _fleet_s(self, fix: Fix) -> float | None:
        return self.clock.fleet_s(fix.source_s) if math.isfinite(fix.source_s) else None

    def _restart_if_rebooted(self, why: str) -> None:
        fault = why.split(")", 1)[0].removeprefix("rejected (")
        same = fault in ("backwards", "future") and fault == self._clock_fault
        self._clock_fault = fault
        self._clock_faults_in_a_row = self._clock_faults_in_a_row + 1 if same else 1
        if fault in ("backwards", "future") and self._clock_faults_in_a_row >= RESTART_AFTER:
            went = "back in time" if fault == "backwards" else "ahead of fleet time"
            self.log.append(
                f"{RESTART_AFTER} fixes in a row went {went}: the source's clock restarted or"
                " jumped; its mapping is estimated afresh"
            )
            rejected = self.screen.rejected
            self.screen = ObservationScreen(self._limits, accepted=self.screen.accepted)
            self.screen.rejected = rejected
            self.clock.restart()
            self._clock_faults_in_a_row = 0

    @property
    def noise_m(self) -> float:
        """The fixes' noise: given, or estimated from the last accepted fixes [m]."""
        if self._noise_m is not None:
            return self._noise_m
        if len(self._recent) < 5:
            return 1.0
        return max(noise_estimate(np.array(self._recent)), MIN_NOISE_M)
