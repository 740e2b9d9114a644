"""The checks every live target fix passes before it becomes an observation.

A fix is rejected, and counted under its fault, when it comes from another system than the one
followed, is not a number, repeats or goes back on the source's clock, lies ahead of fleet time,
lies implausibly far from home, or implies an implausible speed from the last fix accepted. Each
rejection has a line naming the fault and the numbers behind it; nothing raises.
"""

import math
from dataclasses import dataclass, field

from fleetmpc.errors import ConfigError
from fleetmpc.targets.fix import Fix
from fleetmpc.validate import positive

__all__ = ["FAULTS", "ObservationScreen", "ScreenLimits"]

FAULTS = ("wrong system", "not a number", "repeat", "backwards", "future", "too far", "jump")
"""The faults a fix is rejected for, in the order they are checked."""


@dataclass(frozen=True)
class ScreenLimits:
    """What a plausible target fix is."""

    system_id: int | None = None
    """The MAVLink system followed (None: any; a file's track)."""
    max_range_m: float = 20_000.0
    """A fix further than this from home is rejected [m]."""
    max_speed_m_s: float = 30.0
    """A fix further from the last one accepted than this speed allows is rejected [m/s]."""
    jump_allowance_m: float = 5.0
    """Distance always allowed between consecutive fixes (GPS noise) [m]."""
    future_s: float = 1.0
    """A fix stamped later than fleet time now plus this is rejected [s]."""

    def __post_init__(self) -> None:
        if self.system_id is not None and not 1 <= self.system_id <= 255:
            raise ConfigError("sysid", f"must be in [1, 255], got {self.system_id}")
        positive("max_range_m", self.max_range_m)
        positive("max_speed_m_s", self.max_speed_m_s)
        positive("jump_allowance_m", self.jump_allowance_m, allow_zero=True)
        positive("future_s", self.future_s, allow_zero=True)


@dataclass
class ObservationScreen:
    """Checks fixes one by one against `limits` and the last fix it accepted; counts."""

    limits: ScreenLimits = field(default_factory=ScreenLimits)
    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAULTS, 0))
    _last: tuple[float, float, float] | None = None
    """(source_s, north_m, east_m) of the last fix accepted."""

    def check(
        self, fix: Fix, north_m: float, east_m: float, *, fleet_s: float | None, now_s: float
    ) -> str | None:
        """None if `fix` (at (north_m, east_m) about home, at `fleet_s` on fleet time as the
        source's clock maps it, None before that is known) is accepted at fleet time `now_s`;
        else the line that says why, its fault counted."""
        fault, why = self._fault(fix, north_m, east_m, fleet_s, now_s)
        if fault is None:
            self.accepted += 1
            self._last = (fix.source_s, north_m, east_m)
            return None
        self.rejected[fault] += 1
        where = f"system {fix.system_id} {fix.message} t={fix.source_s:.3f} s"
        return f"rejected ({fault}): {where}: {why}"

    def _fault(
        self, fix: Fix, north_m: float, east_m: float, fleet_s: float | None, now_s: float
    ) -> tuple[str | None, str]:
        lim = self.limits
        if lim.system_id is not None and fix.system_id != lim.system_id:
            return "wrong system", f"following system {lim.system_id}"
        values = (
            fix.source_s,
            fix.lat_deg,
            fix.lon_deg,
            north_m,
            east_m,
            *(fix.velocity_ne_m_s or ()),
        )
        if not all(math.isfinite(v) for v in values):
            return "not a number", (
                f"lat {fix.lat_deg:.7f} lon {fix.lon_deg:.7f} velocity {fix.velocity_ne_m_s}"
            )
        if self._last is not None:
            last_s, last_n, last_e = self._last
            if fix.source_s == last_s:
                return "repeat", "the same time as the last fix accepted"
            if fix.source_s < last_s:
                return "backwards", f"{last_s - fix.source_s:.3f} s before the last fix accepted"
        if fleet_s is not None and fleet_s > now_s + lim.future_s:
            return "future", f"stamped {fleet_s - now_s:.3f} s ahead of fleet time {now_s:.3f} s"
        distance = math.hypot(north_m, east_m)
        if distance > lim.max_range_m:
            return (
                "too far",
                f"{distance / 1000.0:.1f} km from home (limit {lim.max_range_m / 1000.0:g} km)",
            )
        if self._last is not None:
            dt = fix.source_s - last_s
            step = math.hypot(north_m - last_n, east_m - last_e)
            if step > lim.jump_allowance_m + lim.max_speed_m_s * dt:
                return "jump", f"{step:.1f} m in {dt:.3f} s from the last fix accepted"
        return None, ""

    def summary(self) -> str:
        """Accepted and rejected counts, one line."""
        faults = ", ".join(f"{name} {n}" for name, n in self.rejected.items() if n)
        return f"{self.accepted} accepted, {sum(self.rejected.values())} rejected" + (
            f" ({faults})" if faults else ""
        )
