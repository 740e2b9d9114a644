"""A recorded track of the target, in the fleet's local frame: flown in lockstep as a scenario
target (`[target] kind = "track"`), replayed live by `fleetmpc target --source track:FILE`.

The track is what was observed: its positions carry the recording's own noise and its gaps. In a
lockstep run the agents are handed its fixes at their recorded times (a gap is a dropout) as they
are, noise and all, and the run is judged against the track smoothed: each fix replaced by the
mean of the fixes within `SMOOTH_S` of it (the white part of the noise averaged out; a slow
wander stays, as it would in any recording), linearly interpolated between fixes; its velocity
is the recorded one, or the smoothed positions' change over `VELOCITY_WINDOW_S`.
"""

import math
from dataclasses import dataclass

import numpy as np

from fleetmpc.errors import ConfigError

__all__ = ["RecordedTrack", "TrackFeed", "TrackStats", "noise_estimate", "track_stats"]

VELOCITY_WINDOW_S = 2.0
"""A track without velocities gets them from its smoothed positions' change over this window
[s]."""

SMOOTH_S = 1.0
"""The judged track is the mean of the fixes within this window centred on each [s]."""

MOVING_M_S = 0.3
"""Below this speed a track's course (and its turn rate) is not reported [m/s]."""

GAP_FACTOR = 3.0
"""A time between fixes longer than this many times the median is a gap."""


@dataclass(frozen=True, eq=False)
class RecordedTrack:
    """A target's recorded fixes in the local frame, time from the first fix."""

    times_s: np.ndarray
    """Time of each fix from the first [s], strictly increasing (K,)."""
    positions_m: np.ndarray
    """(North, East) of each fix about home [m] (K, 2)."""
    smoothed_m: np.ndarray | None = None
    """The judged positions (K, 2) [m]: `positions_m` smoothed over SMOOTH_S (computed)."""
    velocities_m_s: np.ndarray | None = None
    """Recorded (North, East) velocity of each fix [m/s] (K, 2), if the recording has them."""
    observation_noise_m: float = 0.5
    """Standard deviation of the fixes' noise, given or estimated [m]."""
    file: str = ""
    """Where the track was read from."""
    kind: str = "track"

    def __post_init__(self) -> None:
        t = np.asarray(self.times_s, float)
        p = np.asarray(self.positions_m, float).reshape(-1, 2)
        if len(t) < 2 or len(t) != len(p):
            raise ConfigError("target.file", f"{self.file}: needs at least 2 fixes, got {len(t)}")
        if not np.all(np.diff(t) > 0):
            k = int(np.argmin(np.diff(t) > 0)) + 1
            raise ConfigError("target.file", f"{self.file}: fix {k}'s time does not increase")
        object.__setattr__(self, "times_s", t - t[0])
        object.__setattr__(self, "positions_m", p)
        smooth = _smoothed(self.times_s, p)
        object.__setattr__(self, "smoothed_m", smooth)
        if self.velocities_m_s is None:
            object.__setattr__(self, "velocities_m_s", _velocities(self.times_s, smooth))

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1])

    @property
    def observation_rate_hz(self) -> float:
        """The fixes' median rate [Hz]."""
        return float(1.0 / np.median(np.diff(self.times_s)))

    def state_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Judged position and velocity (North, East) at t_s [m], [m/s]: the smoothed fixes
        interpolated;
        before the first fix, there; after the last, there and stopped."""
        (x, y), (vx, vy) = self.state_floats(t_s)
        return np.array((x, y)), np.array((vx, vy))

    def state_floats(self, t_s: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """`state_at` as plain floats."""
        t, p, v = self.times_s, self.smoothed_m, self.velocities_m_s
        if t_s >= t[-1]:
            return (float(p[-1, 0]), float(p[-1, 1])), (0.0, 0.0)
        x = float(np.interp(t_s, t, p[:, 0]))
        y = float(np.interp(t_s, t, p[:, 1]))
        return (x, y), (float(np.interp(t_s, t, v[:, 0])), float(np.interp(t_s, t, v[:, 1])))

    def feed(self, rng: np.random.Generator) -> "TrackFeed":
        """The observations a lockstep run publishes: the fixes at their times (`rng` unused:
        the recording has its own noise)."""
        return TrackFeed(self)


def _smoothed(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Each fix replaced by the mean of the fixes within SMOOTH_S / 2 of its time (K, 2)."""
    lo = np.searchsorted(t, t - 0.5 * SMOOTH_S, side="left")
    hi = np.searchsorted(t, t + 0.5 * SMOOTH_S, side="right")
    sums = np.vstack([np.zeros((1, 2)), np.cumsum(p, axis=0)])
    return (sums[hi] - sums[lo]) / (hi - lo)[:, None]


def _velocities(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The positions' change over VELOCITY_WINDOW_S centred on each fix (K, 2) [m/s]."""
    half = 0.5 * VELOCITY_WINDOW_S
    lo = np.clip(t - half, t[0], t[-1])
    hi = np.clip(t + half, t[0], t[-1])
    a = np.column_stack([np.interp(lo, t, p[:, i]) for i in range(2)])
    b = np.column_stack([np.interp(hi, t, p[:, i]) for i in range(2)])
    return (b - a) / np.maximum(hi - lo, 1e-9)[:, None]


class TrackFeed:
    """A recorded track's fixes in a lockstep run, each handed out at the first period at or
    after its time, stamped with its own time."""

    def __init__(self, track: RecordedTrack) -> None:
        self._stamps_ns = np.round(track.times_s * 1e9).astype(np.int64)
        self._positions = track.positions_m
        self._next = 0

    def due(self, t_ns: int) -> list[tuple[int, np.ndarray]]:
        """The fixes stamped at or before t_ns [ns] not handed out yet."""
        end = int(np.searchsorted(self._stamps_ns, t_ns, side="right"))
        out = [(int(self._stamps_ns[k]), self._positions[k].copy()) for k in range(self._next, end)]
        self._next = max(self._next, end)
        return out


@dataclass(frozen=True)
class TrackStats:
    """What a recorded track asks of a formation that follows it."""

    fixes: int
    duration_s: float
    rate_hz: float
    """Median rate of the fixes [Hz]."""
    speed_max_m_s: float
    speed_p95_m_s: float
    turn_rate_max_rad_s: float
    """Largest turn rate over TURN_WINDOW_S while moving [rad/s]."""
    turn_rate_p95_rad_s: float
    gaps: tuple[tuple[float, float], ...]
    """(start time, length) of every gap between fixes [s]."""


TURN_WINDOW_S = 2.0
"""A track's turn rate is its course's change over this window [s]."""


def track_stats(track: RecordedTrack) -> TrackStats:
    """Speeds, turn rates and gaps of a recorded track."""
    t = track.times_s
    dt = np.diff(t)
    median = float(np.median(dt))
    gaps = tuple((float(t[k]), float(dt[k])) for k in np.flatnonzero(dt > GAP_FACTOR * median))
    grid = np.arange(0.0, track.duration_s, 0.1)
    vel = np.array([track.state_at(s)[1] for s in grid])
    speed = np.hypot(vel[:, 0], vel[:, 1])
    course = np.arctan2(vel[:, 1], vel[:, 0])
    lag = max(1, round(TURN_WINDOW_S / 0.1))
    turn = np.angle(np.exp(1j * (course[lag:] - course[:-lag]))) / TURN_WINDOW_S
    moving = (speed[lag:] > MOVING_M_S) & (speed[:-lag] > MOVING_M_S)
    rates = np.abs(turn[moving]) if moving.any() else np.zeros(1)
    return TrackStats(
        fixes=len(t),
        duration_s=track.duration_s,
        rate_hz=1.0 / median,
        speed_max_m_s=float(speed.max()),
        speed_p95_m_s=float(np.percentile(speed, 95)),
        turn_rate_max_rad_s=float(rates.max()),
        turn_rate_p95_rad_s=float(np.percentile(rates, 95)),
        gaps=gaps,
    )


def noise_estimate(positions_m: np.ndarray) -> float:
    """The fixes' noise as their second differences show it: for white noise of std sigma on
    smooth motion, a second difference has std sigma sqrt(6) on each axis; taken from their
    median magnitude (0.6745 std for a normal), so that a gap or a corner does not count [m]."""
    d2 = np.diff(np.asarray(positions_m, float), n=2, axis=0)
    if len(d2) == 0:
        return 0.0
    return float(np.median(np.abs(d2)) / 0.6745 / math.sqrt(6.0))
