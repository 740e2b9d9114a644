"""The target's path behind it, as an agent (or the judge) has seen it: a polyline of the
positions the target was at, its arc lengths, and the path smoothed at a point with its course
there (docs/design.md, "Formation reference"). The formation's centre is a point of this path,
a trail of arc behind the target (`fleetmpc.onboard.core.formation.FormationReference`).
"""

import bisect
import copy
import math

import numpy as np

__all__ = ["CHORD_HALF_M", "START_MIN_M", "TargetPath"]

PATH_SPACING_M = 0.05
"""A position of the target joins its path once it lies this far from the last one kept: an
estimate's jitter about a target that hovers adds no length."""

CHORD_HALF_M = 4.0
"""The path is smoothed at a point over this much arc before it and after it (`TargetPath.at`):
an estimated path's jitter of a few centimetres tilts its course by under a hundredth of a
radian (its chord's ends move by it over 8 m), and on a steady turn the course is the tangent's
at the middle, without lag."""

FOLD_SHARE = 0.25
"""A chord shorter than this share of the arc it spans folds back on itself (the target turned
straight back, by more than about 150 degrees): it tells no course there, and the reference
course holds. (At half its arc, the test before, a 120-degree corner sat on the line: an
estimate that rounded it inside folded, the truth's did not, and the agents' reference stalled
for two seconds behind the judge's.)"""

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


def _piece_moments(x0, y0, x1, y1) -> tuple:
    """The integrals of 1, x and y along the straight piece from (x0, y0) to (x1, y1): three
    floats, or three arrays for arrays of pieces."""
    w = ((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5
    return (w, w * (x0 + x1) / 2.0, w * (y0 + y1) / 2.0)


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
        point added at the end adds its piece to them, points dropped at the start take their
        entries out (`_drop_moments`)."""
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
            self._drop_moments(drop)

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

    def _drop_moments(self, drop: int) -> None:
        """The running moments less those of the first `drop` points, dropped: a window's
        moments are differences of running sums, which the dropped pieces' share leaves as they
        are. Their origin stays where it was until the newest point is `keep_m` from it; then
        they are computed afresh about the newest point (kept small, for precision)."""
        if self._moments is None:
            return
        running, ox, oy = self._moments
        del running[:drop]
        if math.hypot(self.xs[-1] - ox, self.ys[-1] - oy) > self._keep_m:
            self._moments = None

    def _running_moments(self) -> tuple[list[list[float]], float, float]:
        """The integrals of 1, x and y along the path from its first point to each point
        (K, 3), about an origin near its newest point (kept small, for precision), and that
        origin; computed afresh when the path is begun, cut or has moved `keep_m` away from the
        origin, otherwise kept up as points come and go (`extend`, `_drop_moments`)."""
        if self._moments is None:
            ox, oy = self.xs[-1], self.ys[-1]
            x, y = np.asarray(self.xs) - ox, np.asarray(self.ys) - oy
            pieces = np.column_stack(_piece_moments(x[:-1], y[:-1], x[1:], y[1:]))
            running = np.vstack([np.zeros((1, 3)), np.cumsum(pieces, axis=0)])
            self._moments = (running.tolist(), ox, oy)
        return self._moments

    def at(self, s: float) -> tuple[tuple[float, float], float | None]:
        """The path smoothed at arc length s: the mean of the path from CHORD_HALF_M before s
        to CHORD_HALF_M after it (no further than the newest point, unless s lies beyond it),
        and its course there, the direction of the chord between the window's ends (the mean
        of the path's direction over the window, weighed by length). The mean takes out the
        jitter of estimated positions and moves smoothly round a waypoint's corner; on a turn
        of radius R it lies CHORD_HALF_M^2 / (6 R) inside the path (5 cm at 50 m), the same for
        every agent and the judge; on a steady turn the chord is the tangent at s, and at a
        corner it bisects the turn. The course is None where it is not known: on a tail not yet
        set, or where the path folds back on itself (its chord shorter than FOLD_SHARE of its
        arc: a target that turned straight back)."""
        lo = s - CHORD_HALF_M
        hi = s + CHORD_HALF_M if s >= self.length_m else min(s + CHORD_HALF_M, self.length_m)
        if self.tail_course is None and lo < self.ss[0]:
            return self.point_at(s), None
        # The path between the window's ends, each piece weighed by its length (so that the
        # mean moves smoothly as the ends slide along): its mean from the pieces' moments, the
        # whole pieces' from the running sums, the two partial ones at the ends on their own.
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
        point = (ox + m[1] / m[0], oy + m[2] / m[0])
        dx, dy = bx - ax, by - ay
        if math.hypot(dx, dy) < max(FOLD_SHARE * (hi - lo), PATH_SPACING_M):
            return point, None
        return point, math.atan2(dy, dx)
