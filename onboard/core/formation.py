"""Formation geometry: slots around a centre that trails the target by d_s along the target's
path, turned to a reference course (docs/design.md, "Formation reference").

World frame: slot offsets are (North, East). Course frame: offsets are (forward, right) in the
frame whose x axis is the reference course; with NED axes "right" is the positive rotation, so a
course-frame offset o maps to Rot(course) o.

The centre flies in the target's track: it is the point of the target's path d_s of arc behind
the target (`TargetPath`), where the target was, not a point d_s behind it along its course now.
On a straight line the two are the same; in a turn the centre stays on the path, and the
direction the target points now, the least certain thing an estimate knows of it, no longer
swings a centre 10 m behind it by a lever of 10 m: what reaches the slots is where the target
was (an estimate a few centimetres off) and the path's course there, read from a few metres of
path already flown (`TargetPath.at`). At a corner the centre goes
round the corner when it gets there, as the target did. A target that hovers or stops leaves
its path as it is: the centre stops where it is.

The reference course follows the path's course at the centre but turns at most at a bounded
rate, so a slot never asks its vehicle for more than it can fly: when a course-frame formation
turns at rate r, slot i moves at the centre's velocity (the target's, when it was there) plus r
times its lever arm L_i = |o_i|, so at most at the target's speed v plus r L_i. With the
tightened speed bound V̄, the limit spends half the spare speed V̄ - v on the turn and keeps
half (SPEED_RESERVE) for wind, effectiveness errors and catching up, and half the tightened
yaw-rate bound ω̄:
    r_max(v) = min(ω̄ / 2, (1 - SPEED_RESERVE) (V̄ - v) / max_i L_i)
(`CourseRateLimit`), at the target's speed: a target that slows down to turn (the lobes of a
figure eight) leaves the formation more room to turn with it. The speed the limit reads follows
the target's at most at SPEED_SLEW_M_S2, so the dip and overshoot of an estimated speed while
the filter turns its velocity round a corner move neither the sweep's rate. Each period the
reference course steps toward the path's course, at most r_max dt: on a turn the formation can
follow it keeps up without lag, and at a waypoint corner it sweeps round at r_max. Where the
path turned straight back (an out-and-back) it folds and tells no course: the reference
holds until the path leads away again, then, the target's course being near its opposite with
no side to sweep by, it sweeps at +r_max, to starboard (the positive rotation in NED), as the
give-way rule turns vessels meeting head-on: every agent, and the judge, sweep the same way.
"""

import bisect
import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.config import FormationSettings
from fleetmpc.onboard.core.unicycle import wrap

__all__ = [
    "CourseRateLimit",
    "Formation",
    "FormationReference",
    "TargetPath",
    "course_rate_limit",
    "true_reference",
]

PATH_SPACING_M = 0.05
"""A position of the target joins its path once it lies this far from the last one kept: an
estimate's jitter about a target that hovers adds no length."""

CHORD_HALF_M = 4.0
"""The path is smoothed at a point over this much arc before it and after it (`TargetPath.at`):
an estimated path's jitter of a few centimetres tilts its course by under a hundredth of a
radian, and on a steady turn the course is the tangent's at the middle, without lag."""

FOLD_SHARE = 0.5
"""A chord shorter than this share of the arc it spans folds back on itself (the target turned
straight back): it tells no course there, and the reference course holds."""

SPEED_RESERVE = 0.5
"""Share of the spare speed (tightened bound less the target's speed) the reference course's turn
leaves for wind, effectiveness errors and catching up."""

START_MIN_M = 0.5
"""An estimated path begins once it is this long; one that loses its course (its target stops)
before was no start, and begins again when the course is known again (an estimate's noise about
a hovering target can stand clear of its uncertainty for a moment)."""

LOCATE_BACK_M = 2.0
"""A stopped target is placed on the last this much of its path: further back than an estimate
overshoots a stop, short of where the target was before it turned back, if it did."""

LOCATE_TOLERANCE_M = 0.1
"""Points of the path this much farther from a stopped target than the nearest are as near: an
estimated path's jitter."""

STOPPING_SHARE = 1.0 / 3.0
"""A target slower than this share of the speed the rate limit reads (its recent speed) is taken
to be stopping: its course is not known, and its positions do not lay its path."""

SPEED_SLEW_M_S2 = 0.05
"""How fast the speed the rate limit reads may change [m/s^2]: faster than a target that slows
into a turn (a figure eight's 0.015 m/s^2), far slower than an estimate's swing at a corner."""

REVERSAL_BAND_RAD = math.radians(20.0)
"""A target course within this of the reference's opposite is a reversal (module docstring):
the reference sweeps to starboard, whichever side the estimate's noise puts it on."""

MIN_COURSE_RATE_RAD_S = 0.01
"""The reference course turns at least this fast, even when the team has no spare speed (the
feasibility check reports that case)."""


class Formation:
    """Slot positions of every vehicle for a reference course."""

    def __init__(self, settings: FormationSettings) -> None:
        self.settings = settings
        self._offsets = np.array(settings.slots_m)
        self._offsets_list = [(float(x), float(y)) for x, y in settings.slots_m]
        self.links = _nearest_links(self.desired_distances(), settings.neighbours)
        """The formation graph: the slots each slot is linked to, by index, in increasing
        order (docs/design.md, "Neighbourhood")."""
        self.max_degree = max(map(len, self.links))
        """The most links any slot has: every agent sizes its stage weights by it, so that the
        whole fleet computes the same tube and reference-course rate."""

    @property
    def size(self) -> int:
        return self._offsets.shape[0]

    def lever_arms_m(self) -> np.ndarray:
        """Each slot's distance from the centre, about which a course-frame formation turns
        (N,) [m]; zeros in the world frame, which does not turn."""
        if self.settings.frame == "course":
            return np.hypot(self._offsets[:, 0], self._offsets[:, 1])
        return np.zeros(self.size)

    def offsets(self, course_rad: float) -> list[tuple[float, float]]:
        """Each slot's offset from the centre (North, East) at a reference course, as floats."""
        if self.settings.frame != "course":
            return self._offsets_list
        ux, uy = math.cos(course_rad), math.sin(course_rad)
        return [(ox * ux - oy * uy, ox * uy + oy * ux) for ox, oy in self._offsets_list]

    def slots(self, centres_m: np.ndarray, courses_rad: np.ndarray) -> np.ndarray:
        """Slots (K, N, 2) around centres (K, 2) at reference courses (K,)."""
        out = np.empty((len(courses_rad), self.size, 2))
        for k, (course, centre) in enumerate(zip(courses_rad, centres_m, strict=True)):
            out[k] = np.array(self.offsets(float(course))) + centre
        return out

    def desired_distances(self) -> np.ndarray:
        """Desired distance between every pair of slots (N, N) [m]."""
        d = self._offsets[:, None, :] - self._offsets[None, :, :]
        return np.hypot(d[..., 0], d[..., 1])


def _nearest_links(distances: np.ndarray, count: int) -> tuple[tuple[int, ...], ...]:
    """Each slot linked to its `count` nearest slots (ties broken by index)."""
    n = distances.shape[0]
    return tuple(
        tuple(
            sorted(
                sorted((j for j in range(n) if j != i), key=lambda j: (distances[i, j], j))[:count]
            )
        )
        for i in range(n)
    )


@dataclass(frozen=True)
class CourseRateLimit:
    """r_max(v) [rad/s]: how fast the reference course may turn at the target's speed v (module
    docstring), never below MIN_COURSE_RATE_RAD_S."""

    speed_bound_m_s: float
    """V̄: the tightened speed bound [m/s]."""
    yaw_rate_bound_rad_s: float
    """ω̄: the tightened yaw-rate bound [rad/s]."""
    lever_m: float
    """The longest lever arm max_i L_i [m]."""

    @classmethod
    def fixed(cls, rate_rad_s: float) -> "CourseRateLimit":
        """The same limit at every speed (no lever arm)."""
        return cls(speed_bound_m_s=math.inf, yaw_rate_bound_rad_s=2.0 * rate_rad_s, lever_m=0.0)

    def at(self, speed_m_s: float) -> float:
        """r_max at the target's speed `speed_m_s`."""
        spare = (1.0 - SPEED_RESERVE) * (self.speed_bound_m_s - speed_m_s)
        by_speed = math.inf if self.lever_m < 1e-9 else spare / self.lever_m
        return max(MIN_COURSE_RATE_RAD_S, min(0.5 * self.yaw_rate_bound_rad_s, by_speed))


def course_rate_limit(
    formation: Formation, *, speed_bound_m_s: float, yaw_rate_bound_rad_s: float
) -> CourseRateLimit:
    """r_max(v) (module docstring) from the tightened input bounds and the lever arms."""
    return CourseRateLimit(
        speed_bound_m_s=speed_bound_m_s,
        yaw_rate_bound_rad_s=yaw_rate_bound_rad_s,
        lever_m=float(formation.lever_arms_m().max()),
    )


def _piece_moments(x0, y0, x1, y1) -> tuple:
    """The integrals of 1, x, y, xx, yy, xy along the straight piece from (x0, y0) to (x1, y1):
    six floats, or six arrays for arrays of pieces."""
    w = ((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5
    return (
        w,
        w * (x0 + x1) / 2.0,
        w * (y0 + y1) / 2.0,
        w * (x0 * x0 + x0 * x1 + x1 * x1) / 3.0,
        w * (y0 * y0 + y0 * y1 + y1 * y1) / 3.0,
        w * (2.0 * x0 * y0 + x0 * y1 + x1 * y0 + 2.0 * x1 * y1) / 6.0,
    )


class TargetPath:
    """The target's path behind it: a polyline of the positions it was at (its estimates, for an
    agent), a point kept once it lies PATH_SPACING_M from the last, with their arc lengths.

    The path begins where the target's course is first known. Before its first point it goes
    on straight back along its tail course (the target's course, as given while the path is
    shorter than `tail_m`); beyond its last point it goes straight on along its end course (the
    chord over its last CHORD_HALF_M). Points more than `keep_m` of arc behind the newest are
    dropped.

    Only a target whose course is known (one that moves) lays its path; a target that turns
    straight back lays its way back beside its way out. A stopped one is placed on the path
    where it is nearest (`_locate`): an estimate that overshoots a stop and comes back is
    placed where it first passed, and the overshoot is dropped when it moves on.
    """

    def __init__(self, *, tail_m: float, keep_m: float) -> None:
        self._tail_m = tail_m
        self._keep_m = keep_m
        self.xs: list[float] = []
        self.ys: list[float] = []
        self.ss: list[float] = []
        """Arc length of each point from the first point the path had [m]."""
        self.length_m = 0.0
        """Arc length of the target's newest position (at most the last point's, or less where
        a stopped target came back along the path) [m]."""
        self._start_course: float | None = None
        """The target's course as the path began (None before it was known)."""
        self._start_m = START_MIN_M
        self._stopped = False
        """True from a stop until the target has got `start_m` clear of where it stopped."""
        self._moments: tuple[list[list[float]], float, float] | None = None
        """The running moments of the points (`_running_moments`), None when out of date; a
        point added at the end adds its piece to them."""
        self._kept = 0
        """How many of the points stay (the rest: the newest position, too close to stay)."""

    @property
    def tail_course(self) -> float | None:
        """The target's course as the path began, once it has begun (START_MIN_M long): the
        path goes on straight back along it before its first point. None before."""
        begun = self.ss and (self.ss[0] > 0.0 or self.length_m >= self._start_m)
        return self._start_course if begun else None

    def extend(
        self, x: float, y: float, course: float | None = None, *, start_m: float = START_MIN_M
    ) -> None:
        """Add the target's newest position, and its course if it is known (the class's
        docstring: a moving target's position joins the path, the last one as its end until
        the next comes, kept if it lies PATH_SPACING_M from the last point kept; a stopped
        one's is placed on the path). While the path is shorter than its tail, the course given
        sets the tail course. The path has begun once it is `start_m` long, and a target that
        stopped moves on once it is `start_m` clear of where it stopped (an estimate's noise
        about a hovering target stands clear of its uncertainty now and then; a course that is
        certain, the judge's, may pass 0)."""
        self._start_m = start_m
        xs, ys, ss = self.xs, self.ys, self.ss
        starting = ss and ss[0] == 0.0 and self.length_m < start_m
        if not xs or self._start_course is None or (course is None and starting):
            # (Not begun, or a start that did not last: an estimate's noise about a target
            # that hovers.)
            self.xs, self.ys, self.ss, self._kept = [x], [y], [0.0], 1
            self._start_course, self.length_m, self._stopped = course, 0.0, False
            self._moments = None
            return
        if len(xs) > self._kept:  # (the previous end, too close to stay)
            del xs[-1], ys[-1], ss[-1]
            if self._moments is not None:
                self._moments[0].pop()
        if course is not None and self._stopped:  # (moving again once it has got clear)
            sx, sy = self.point_at(self.length_m)
            self._stopped = math.hypot(x - sx, y - sy) < start_m
        if course is None or self._stopped:  # (stopped: placed on the path, not laying it)
            self._stopped = True
            self.length_m = self._locate(x, y)
            return
        if self.length_m < ss[-1]:  # (it stopped short of the path's end: resume from there)
            self._cut(self.length_m)
        step = math.hypot(x - xs[-1], y - ys[-1])
        xs.append(x)
        ys.append(y)
        ss.append(ss[-1] + step)
        self.length_m = ss[-1]
        if self._moments is not None:
            running, ox, oy = self._moments
            piece = _piece_moments(xs[-2] - ox, ys[-2] - oy, x - ox, y - oy)
            running.append([a + b for a, b in zip(running[-1], piece, strict=True)])
        if ss[0] == 0.0 and ss[-1] <= self._tail_m:  # (the tail is still in use)
            self._start_course = course
        if step < PATH_SPACING_M:
            return
        self._kept = len(xs)
        if ss[1] < ss[-1] - self._keep_m:
            drop = bisect.bisect_left(ss, ss[-1] - self._keep_m) - 1
            del xs[:drop], ys[:drop], ss[:drop]
            self._kept -= drop
            self._moments = None

    def _locate(self, x: float, y: float) -> float:
        """Where a stopped target at (x, y) is on the path [m of arc]: the nearest point of the
        path's last LOCATE_BACK_M (and of its straight continuation) on the earliest pass that
        comes as near; so an estimate that overshot the stop and came back is placed where it
        first passed."""
        xs, ys, ss = self.xs, self.ys, self.ss
        first = max(bisect.bisect_left(ss, ss[-1] - LOCATE_BACK_M) - 1, 0)
        found: list[tuple[float, float]] = []  # (distance, arc length)
        for i in range(first, len(xs) - 1):
            ex, ey, length = xs[i + 1] - xs[i], ys[i + 1] - ys[i], ss[i + 1] - ss[i]
            along = ((x - xs[i]) * ex + (y - ys[i]) * ey) / max(ex * ex + ey * ey, 1e-12)
            along = min(max(along, 0.0), 1.0)
            gap = math.hypot(x - xs[i] - along * ex, y - ys[i] - along * ey)
            found.append((gap, ss[i] + along * length))
        end = self._end_course()
        beyond = 0.0
        if end is not None:
            beyond = max((x - xs[-1]) * math.cos(end) + (y - ys[-1]) * math.sin(end), 0.0)
        px, py = self.point_at(ss[-1] + beyond)
        found.append((math.hypot(x - px, y - py), ss[-1] + beyond))
        # The earliest pass by (x, y) as near as the nearest, to where it is nearest.
        nearest = min(g for g, _ in found)
        i = next(i for i, (g, _) in enumerate(found) if g <= nearest + LOCATE_TOLERANCE_M)
        while i + 1 < len(found) and found[i + 1][0] <= found[i][0]:
            i += 1
        return found[i][1]

    def _cut(self, s: float) -> None:
        """End the path at arc length s (no earlier than its first point): what lay beyond
        (an estimate's overshoot of a stop) is dropped."""
        s = max(s, self.ss[0])
        self._moments = None
        x, y = self.point_at(s)
        keep = bisect.bisect_left(self.ss, s)
        del self.xs[keep:], self.ys[keep:], self.ss[keep:]
        self.xs.append(x)
        self.ys.append(y)
        self.ss.append(s)
        self._kept = len(self.xs)

    def copy(self) -> "TargetPath":
        """A copy that extends on its own (a prediction's path) and keeps all it is given (a
        prediction is short; what it would drop lies beyond every window)."""
        out = copy.copy(self)
        out.xs, out.ys, out.ss = self.xs[:], self.ys[:], self.ss[:]
        out._keep_m = math.inf
        if self._moments is not None:
            running, ox, oy = self._moments
            out._moments = (running[:], ox, oy)
        return out

    def _end_course(self) -> float | None:
        """The course of the chord over the last CHORD_HALF_M of the points, None while that
        is shorter than PATH_SPACING_M."""
        ax, ay = self.point_at(self.ss[-1] - CHORD_HALF_M)
        dx, dy = self.xs[-1] - ax, self.ys[-1] - ay
        return None if math.hypot(dx, dy) < PATH_SPACING_M else math.atan2(dy, dx)

    def point_at(self, s: float) -> tuple[float, float]:
        """The point at arc length s (straight on before the first point and after the last)."""
        xs, ys, ss = self.xs, self.ys, self.ss
        if s <= ss[0]:
            back = ss[0] - s
            course = 0.0 if self.tail_course is None else self.tail_course
            return xs[0] - back * math.cos(course), ys[0] - back * math.sin(course)
        if s >= ss[-1]:
            on = s - ss[-1]
            course = self._end_course() if on > 0.0 else None
            if course is None:
                return xs[-1], ys[-1]
            return xs[-1] + on * math.cos(course), ys[-1] + on * math.sin(course)
        i = bisect.bisect_right(ss, s)
        f = (s - ss[i - 1]) / (ss[i] - ss[i - 1])
        return xs[i - 1] + f * (xs[i] - xs[i - 1]), ys[i - 1] + f * (ys[i] - ys[i - 1])

    def _running_moments(self) -> tuple[list[list[float]], float, float]:
        """The integrals of 1, x, y, xx, yy, xy along the path from its first point to each
        point (K, 6), about an origin at its newest point (kept small, for precision), and that
        origin; computed once per change of the path."""
        if self._moments is None:
            ox, oy = self.xs[-1], self.ys[-1]
            x, y = np.asarray(self.xs) - ox, np.asarray(self.ys) - oy
            pieces = np.column_stack(_piece_moments(x[:-1], y[:-1], x[1:], y[1:]))
            running = np.vstack([np.zeros((1, 6)), np.cumsum(pieces, axis=0)])
            self._moments = (running.tolist(), ox, oy)
        return self._moments

    def at(self, s: float) -> tuple[tuple[float, float], float | None]:
        """The path smoothed at arc length s: the mean of the path from CHORD_HALF_M before s
        to CHORD_HALF_M after it (no further than the newest point, unless s lies beyond it),
        and the course of the straight line fitted to it there (least squares, orthogonal), the
        way the path goes. The mean takes out the jitter of estimated positions and moves
        smoothly round a waypoint's corner; on a turn of radius R it lies CHORD_HALF_M^2 / (6 R)
        inside the path (5 cm at 50 m), the same for every agent and the judge. The course is
        None where it is not known: on a tail not yet set, or where the path folds back on
        itself (its chord shorter than FOLD_SHARE of its arc: a target that turned straight
        back)."""
        lo = s - CHORD_HALF_M
        hi = s + CHORD_HALF_M if s >= self.length_m else min(s + CHORD_HALF_M, self.length_m)
        if self.tail_course is None and lo < self.ss[0]:
            return self.point_at(s), None
        # The path between the window's ends, each piece weighed by its length (so that the fit
        # moves smoothly as the ends slide along): its mean, and the principal axis of its
        # spread, from the pieces' moments: the whole pieces' from the running sums, the two
        # partial ones at the ends on their own.
        (ax, ay), (bx, by) = self.point_at(lo), self.point_at(hi)
        i, j = bisect.bisect_right(self.ss, lo), bisect.bisect_left(self.ss, hi)
        running, ox, oy = self._running_moments()
        if i < j:
            whole = [a - b for a, b in zip(running[j - 1], running[i], strict=True)]
            first = _piece_moments(ax - ox, ay - oy, self.xs[i] - ox, self.ys[i] - oy)
            last = _piece_moments(self.xs[j - 1] - ox, self.ys[j - 1] - oy, bx - ox, by - oy)
            m = [a + b + c for a, b, c in zip(whole, first, last, strict=True)]
        else:
            m = _piece_moments(ax - ox, ay - oy, bx - ox, by - oy)
        if m[0] < PATH_SPACING_M:  # (a target that has not moved)
            return self.point_at(s), None
        mx, my = m[1] / m[0], m[2] / m[0]
        sxx, syy, sxy = m[3] / m[0] - mx * mx, m[4] / m[0] - my * my, m[5] / m[0] - mx * my
        axis = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
        ux, uy = math.cos(axis), math.sin(axis)
        point = (ox + mx, oy + my)
        dx, dy = bx - ax, by - ay
        if math.hypot(dx, dy) < max(FOLD_SHARE * (hi - lo), PATH_SPACING_M):
            return point, None
        return point, axis if ux * dx + uy * dy >= 0.0 else wrap(axis + math.pi)


class FormationReference:
    """Where the formation is: its centre on the target's path, `trail` of arc behind the
    target, and its reference course, the path's course there turned at most at the rate
    `limit` allows (module docstring). The same for an agent (fed its estimates of the target)
    and for the judge of a run (fed the truth).

    Angles are unwrapped (continuous over time), in radians.
    """

    def __init__(self, formation: "Formation", limit: CourseRateLimit) -> None:
        self.trail_m = formation.settings.trail_m
        self.limit = limit
        self.path = TargetPath(
            tail_m=abs(self.trail_m) + CHORD_HALF_M,
            keep_m=abs(self.trail_m) + 2.0 * CHORD_HALF_M + 1.0,
        )
        self.value: float | None = None
        """The reference course now, None before the path's course at the centre was known."""
        self.limit_speed_m_s = 0.0
        """The target speed the rate limit reads (module docstring) [m/s]."""

    @property
    def course(self) -> float:
        """The reference course, 0 (North) while it is not known."""
        return 0.0 if self.value is None else self.value

    def _turned(self, current: float | None, course: float | None, dt_s: float) -> float | None:
        if course is None:
            return current
        if current is None:
            return course
        error = wrap(course - current)
        rate_max = self.limit.at(self.limit_speed_m_s)
        if abs(error) > math.pi - REVERSAL_BAND_RAD:
            return current + dt_s * rate_max  # a near-reversal: sweep to starboard
        return current + max(-rate_max * dt_s, min(error, rate_max * dt_s))

    def follow(
        self,
        position_m: Sequence[float],
        velocity_m_s: Sequence[float],
        dt_s: float,
        *,
        velocity_std_m_s: float = 0.0,
    ) -> tuple[tuple[float, float], float]:
        """Advance by dt_s with the target at `position_m` and `velocity_m_s` now: the centre
        and the reference course. The target's course is known while its speed stands clear
        of its estimate's uncertainty (three standard deviations `velocity_std_m_s`) and of
        STOPPING_SHARE of the speed the rate limit reads (a target that stops: its estimate's
        velocity swings past zero, and its course then says nothing)."""
        speed_m_s = math.hypot(*velocity_m_s)
        slew = SPEED_SLEW_M_S2 * dt_s
        if self.value is None:
            # No course yet, so nothing to sweep: the limit reads the speed as it is, and the
            # first course is swept at the rate of the speed the target has then (slewing up
            # from a settling estimate's first few cm/s took 20 s, during which the reference
            # turned faster than the judge's, a lead it kept while both turned at the limit).
            self.limit_speed_m_s = speed_m_s
        else:
            change = speed_m_s - self.limit_speed_m_s
            self.limit_speed_m_s += -slew if change < -slew else min(change, slew)
        slowest = max(3.0 * velocity_std_m_s, STOPPING_SHARE * self.limit_speed_m_s)
        course = None
        if speed_m_s > slowest and speed_m_s > 0.0:
            course = math.atan2(velocity_m_s[1], velocity_m_s[0])
        start_m = START_MIN_M if velocity_std_m_s > 0.0 else 0.0
        self.path.extend(float(position_m[0]), float(position_m[1]), course, start_m=start_m)
        if self.path.tail_course is None:  # (no course yet, or a start that did not last)
            self.value = None
        centre, course = self.path.at(self.path.length_m - self.trail_m)
        self.value = self._turned(self.value, course, dt_s)
        return centre, self.course

    def follow_run(
        self, positions_m: np.ndarray, velocities_m_s: np.ndarray, dt_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """`follow` through positions and velocities (K, 2) dt_s apart, whose course is certain
        (the truth's): centres (K, 2) and reference courses (K,)."""
        centres, courses = [], []
        for p, v in zip(
            np.asarray(positions_m, float).tolist(),
            np.asarray(velocities_m_s, float).tolist(),
            strict=True,
        ):
            centre, course = self.follow(p, v, dt_s)
            centres.append(centre)
            courses.append(course)
        return np.array(centres, float).reshape(-1, 2), np.array(courses, float)

    def ahead(
        self,
        positions_m: Sequence[tuple[float, float]],
        velocities_m_s: Sequence[tuple[float, float]],
        dt_s: float,
        *,
        velocity_std_m_s: float = 0.0,
    ) -> list[tuple[tuple[float, float], float]]:
        """The centres and reference courses along a predicted target track (positions and
        velocities dt_s apart, after the ones followed last): `follow` along it from the
        current state, which stays as it is. So a prediction is placed as the estimates it
        predicts will be: a moving target's positions lay its path, a stopped one's are placed
        on the path where it stopped."""
        kept = self.path, self.value, self.limit_speed_m_s
        self.path = self.path.copy()
        try:
            return [
                self.follow(p, v, dt_s, velocity_std_m_s=velocity_std_m_s)
                for p, v in zip(positions_m, velocities_m_s, strict=True)
            ]
        finally:
            self.path, self.value, self.limit_speed_m_s = kept


def true_reference(
    formation: "Formation",
    limit: CourseRateLimit,
    positions_m: np.ndarray,
    velocities_m_s: np.ndarray,
    dt_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Centres (K, 2) and reference courses (K,) of the formation around the true target, at
    positions and velocities (K, 2) dt_s apart from the start of a run: the reference a run is
    judged against, as the agents would place it from a perfect estimate."""
    return FormationReference(formation, limit).follow_run(positions_m, velocities_m_s, dt_s)
