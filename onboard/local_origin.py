"""Where an autopilot's local frame begins, in the scenario's frame (docs/design.md, "MAVLink").

A real autopilot's LOCAL_POSITION_NED starts where its estimator started, not at the scenario's
origin. Its GLOBAL_POSITION_INT, placed against the scenario's home, says where it is in the
scenario's frame; the difference, averaged, is the shift between the two.
"""

__all__ = ["ORIGIN_MAX_DT_NS", "ORIGIN_SAMPLES", "OriginShift"]

ORIGIN_SAMPLES = 25
"""Global fixes averaged into the local origin's place (5 s at 5 Hz): a fix is quantized to
1e-7 degrees, about a centimetre."""
ORIGIN_MAX_DT_NS = 100_000_000
"""A global fix and a local position further apart in time than this are not compared [ns]."""


class OriginShift:
    """Where an autopilot's local origin (LOCAL_POSITION_NED's) lies in the scenario's frame,
    from global fixes placed against the scenario's home: the mean of (global - local) over
    recent pairs, the local position carried to the fix's time with its velocity. A real
    autopilot's local origin is where its estimator started, not the scenario's origin."""

    def __init__(self) -> None:
        self._last_local: tuple[int, float, float, float, float] | None = None
        self._samples: list[tuple[float, float]] = []
        self.value: tuple[float, float] | None = None

    def local(self, t_ns: int, x: float, y: float, vx: float, vy: float) -> None:
        self._last_local = (t_ns, float(x), float(y), float(vx), float(vy))

    def global_fix(self, t_ns: int, north: float, east: float) -> None:
        if self._last_local is None:
            return
        t_l, x, y, vx, vy = self._last_local
        dt_ns = t_ns - t_l
        if abs(dt_ns) > ORIGIN_MAX_DT_NS:
            return
        dt = dt_ns * 1e-9
        self._samples = [
            *self._samples[-(ORIGIN_SAMPLES - 1) :],
            (north - x - vx * dt, east - y - vy * dt),
        ]
        n = len(self._samples)
        self.value = (sum(s[0] for s in self._samples) / n, sum(s[1] for s in self._samples) / n)
