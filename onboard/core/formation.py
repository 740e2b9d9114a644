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

import copy
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.config import FormationSettings
from fleetmpc.onboard.core.target_path import CHORD_HALF_M, START_MIN_M, TargetPath
from fleetmpc.onboard.core.unicycle import wrap

__all__ = [
    "CourseRateLimit",
    "Formation",
    "FormationReference",
    "course_rate_limit",
    "true_reference",
]

SPEED_RESERVE = 0.5
"""Share of the spare speed (tightened bound less the target's speed) the reference course's turn
leaves for wind, effectiveness errors and catching up."""

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

    def closest_slots(self) -> tuple[int, int, float]:
        """The two nearest slots (indices) and their distance [m]; needs two slots or more."""
        d = self.desired_distances()
        np.fill_diagonal(d, np.inf)
        a, b = np.unravel_index(int(np.argmin(d)), d.shape)
        return int(a), int(b), float(d[a, b])


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
        on the path where it stopped. A copy follows the track (a scout), so this reference
        keeps its state."""
        scout = copy.copy(self)
        scout.path = self.path.copy()
        return [
            scout.follow(p, v, dt_s, velocity_std_m_s=velocity_std_m_s)
            for p, v in zip(positions_m, velocities_m_s, strict=True)
        ]


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
