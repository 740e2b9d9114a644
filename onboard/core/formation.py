"""Formation geometry: slots around a centre that trails the target by d_s along a reference
course, and the reference course itself (docs/design.md, "Formation reference").

World frame: slot offsets are (North, East). Course frame: offsets are (forward, right) in the
frame whose x axis is the reference course; with NED axes "right" is the positive rotation, so a
course-frame offset o maps to Rot(course) o. In both frames the centre trails the target by d_s
along the reference course.

The reference course follows the target's course but turns at most at a bounded rate, so a slot
never asks its vehicle for more than it can fly: when the formation turns at rate r about the
target, slot i moves at the target's velocity plus r times its lever arm L_i (its distance from
the target: |o_i - (d_s, 0)| in the course frame, d_s in the world frame), so at most at the
target's speed v plus r L_i. With the tightened speed bound V̄, the limit spends three quarters
of the spare speed V̄ - v on the turn and keeps a quarter (SPEED_RESERVE) for wind,
effectiveness errors and catching up, and half the tightened yaw-rate bound ω̄:
    r_max(v) = min(ω̄ / 2, (1 - SPEED_RESERVE) (V̄ - v) / max_i L_i)
(`CourseRateLimit`), at the target's speed: a target that slows down to turn (the lobes of a
figure eight) leaves the formation more room to turn with it. The speed the limit reads follows
the target's at most at SPEED_SLEW_M_S2, so the dip and overshoot of an estimated speed while
the filter turns its velocity round a corner move neither the sweep's rate.
The reference course turns at the target's turn rate plus a gentle correction toward the
target's course, the sum clipped to r_max:
    dpsi/dt = clip(omega_target + k (course - psi), -r_max, r_max),   k = COURSE_GAIN_PER_S,
(stepped as psi += dt clip(omega + k (course - psi - omega dt)): a steady turn is followed exactly)
so on a steady turn it keeps up without lag, the noise of the course estimate reaches it only
through k, and at a waypoint corner the formation sweeps round at r_max instead of jumping.
A target that turns back on itself (an out-and-back, a stop and return) leaves no side to
sweep by: the wrapped error is near +-pi and its sign is the noise's. Within REVERSAL_BAND_RAD of
a reversal the reference sweeps at +r_max, to starboard (the positive rotation in NED), as the
give-way rule turns vessels meeting head-on: every agent, and the judge, sweep the same way.
A target slower than STOPPING_SHARE of the speed the limit reads is stopping: its course is not
known, and the reference turns on to the last course that was (docs/design.md, "a target that
stops").
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.config import FormationSettings
from fleetmpc.onboard.core.unicycle import wrap, wrap_angle

__all__ = [
    "CourseRateLimit",
    "Formation",
    "ReferenceCourse",
    "TrueReference",
    "course_rate_limit",
    "reference_courses",
]

MIN_COURSE_SPEED_M_S = 0.05
"""Below this target speed the course is not defined: the reference course holds."""

SPEED_RESERVE = 0.25
"""Share of the spare speed (tightened bound less the target's speed) the reference course's turn
leaves for wind, effectiveness errors and catching up."""

COURSE_GAIN_PER_S = 0.2
"""How fast the reference course corrects toward the target's course [1/s]: a time constant of
5 s, so the noise of a course estimate reaches it attenuated 25-fold per period, while the turn
rate, where it is significant, carries it round a steady turn without lag. (With the turn rate
fed forward unconditionally, 0.2 let the turn-rate errors of a figure eight through threefold
and 0.3 was kept; with the significance test, 0.2 against 0.3 took the suite's learning ratios
down by up to 0.04, a straight line's by 0.10, the figure eight's up by 0.01.)"""

SPEED_SLEW_M_S2 = 0.05
"""How fast the speed the rate limit reads may change [m/s^2]: faster than a target that slows
into a turn (a figure eight's 0.015 m/s^2), far slower than an estimate's swing at a corner."""

STOPPING_SHARE = 1.0 / 3.0
"""A target slower than this share of the speed the rate limit reads (its recent speed) is
taken to be stopping: its course is not known until it picks up speed again."""

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
        """Each slot's distance from the target, about which the formation turns (N,) [m]."""
        trail = self.settings.trail_m
        if self.settings.frame == "course":
            return np.hypot(self._offsets[:, 0] - trail, self._offsets[:, 1])
        return np.full(self.size, abs(trail))

    def placement(self, course_rad: float) -> tuple[float, float, list[tuple[float, float]]]:
        """Where the slots sit around the target at a reference course, as plain floats.

        Returns (trail_x, trail_y, offsets): the centre is the target position less
        (trail_x, trail_y), and slot i is the centre plus offsets[i].
        """
        ux, uy = math.cos(course_rad), math.sin(course_rad)
        trail = self.settings.trail_m
        offsets = self._offsets_list
        if self.settings.frame == "course":  # (forward, right) rotated by the course
            offsets = [(ox * ux - oy * uy, ox * uy + oy * ux) for ox, oy in offsets]
        return trail * ux, trail * uy, offsets

    def slots(self, target_m: np.ndarray, courses_rad: np.ndarray) -> np.ndarray:
        """Slots (K, N, 2) for target positions (K, 2) at reference courses (K,)."""
        out = np.empty((len(courses_rad), self.size, 2))
        for k, (course, (tx, ty)) in enumerate(zip(courses_rad, target_m, strict=True)):
            trail_x, trail_y, offsets = self.placement(float(course))
            out[k] = np.array(offsets) + (tx - trail_x, ty - trail_y)
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


class ReferenceCourse:
    """The formation's reference course: the target's course, turned at most at the rate
    `limit` allows at the target's speed.

    Angles are unwrapped (continuous over time), in radians.
    """

    def __init__(self, limit: CourseRateLimit) -> None:
        self.limit = limit
        self.value: float | None = None
        """The reference course now, None before the target's course was known."""
        self.limit_speed_m_s = 0.0
        """The target speed the rate limit reads (module docstring) [m/s]."""
        self.min_speed_m_s = MIN_COURSE_SPEED_M_S
        """Below this target speed the course is not known (an estimate's owner raises it to
        what its uncertainty allows) [m/s]."""
        self.last_course: float | None = None
        """The target's course when it last had one: a target that stops leaves the reference
        turning on to it, so the formation ends its sweep aligned with the way it came."""

    @staticmethod
    def course_of(
        velocity_m_s: Sequence[float], min_speed_m_s: float = MIN_COURSE_SPEED_M_S
    ) -> float | None:
        """The course of a velocity, None when it is slower than min_speed_m_s."""
        vx, vy = velocity_m_s
        if math.hypot(vx, vy) < min_speed_m_s:
            return None
        return math.atan2(vy, vx)

    def _known_course(self, velocity_m_s: Sequence[float]) -> float | None:
        """The course of a velocity, None while it is not known: slower than min_speed_m_s,
        or than STOPPING_SHARE of the speed the rate limit reads (a target that stops: its
        estimate's velocity swings past zero and its course then says nothing)."""
        slowest = max(self.min_speed_m_s, STOPPING_SHARE * self.limit_speed_m_s)
        return self.course_of(velocity_m_s, slowest)

    def _turned(
        self, current: float, velocity_m_s: Sequence[float], turn_rate: float, dt_s: float
    ) -> float:
        course = self._known_course(velocity_m_s)
        if course is None:  # (stopped: on to its last course, no turn fed forward)
            course, turn_rate = self.last_course, 0.0
            if course is None:
                return current
        rate_max = self.limit.at(self.limit_speed_m_s)
        if abs(wrap(course - current)) > math.pi - REVERSAL_BAND_RAD:
            return current + dt_s * rate_max  # a near-reversal: sweep to starboard
        # (The error against where the turn alone would take it: a steady turn has none.)
        rate = turn_rate + COURSE_GAIN_PER_S * wrap(course - current - turn_rate * dt_s)
        return current + dt_s * (-rate_max if rate < -rate_max else min(rate, rate_max))

    def reset(self, velocity_m_s: Sequence[float]) -> None:
        """Take the target's course as it is (no rate limit), if it has one."""
        course = self.course_of(velocity_m_s, self.min_speed_m_s)
        if course is not None:
            self.value = course if self.value is None else self.value + wrap(course - self.value)
            self.last_course = course
        self.limit_speed_m_s = math.hypot(*velocity_m_s)

    def follow(
        self, velocity_m_s: Sequence[float], dt_s: float, *, turn_rate_rad_s: float = 0.0
    ) -> float | None:
        """Advance by dt_s with the target's velocity and turn rate now; the new value."""
        if self.value is None:
            self.reset(velocity_m_s)
        else:
            slew = SPEED_SLEW_M_S2 * dt_s
            change = math.hypot(*velocity_m_s) - self.limit_speed_m_s
            self.limit_speed_m_s += -slew if change < -slew else min(change, slew)
            self.value = self._turned(self.value, velocity_m_s, turn_rate_rad_s, dt_s)
            course = self._known_course(velocity_m_s)
            if course is not None:
                self.last_course = course
        return self.value

    def replay(
        self,
        value_then: float,
        velocity_m_s: Sequence[float],
        dt_s: float,
        steps: int,
        *,
        turn_rate_rad_s: float = 0.0,
    ) -> float:
        """The value the reference would have now, had it turned from value_then through
        `steps` periods of dt_s with this velocity and turn rate (the current value stays)."""
        current = value_then
        for _ in range(steps):
            current = self._turned(current, velocity_m_s, turn_rate_rad_s, dt_s)
        return current

    def ahead(
        self,
        velocities_m_s: Sequence[Sequence[float]],
        dt_s: float,
        *,
        turn_rate_rad_s: float = 0.0,
    ) -> list[float]:
        """The reference courses along a predicted path (one per velocity, dt_s apart, turning
        at turn_rate_rad_s), from the current value (which stays as it is); needs a value."""
        if self.value is None:
            raise RuntimeError("the reference course is not known yet")
        out, current = [], self.value
        for v in velocities_m_s:
            current = self._turned(current, v, turn_rate_rad_s, dt_s)
            out.append(current)
        return out


class TrueReference:
    """The reference course of a target whose true velocity is known at each period, as the
    agents would place it from a perfect estimate (the turn rate from consecutive courses): the
    slots a run is judged against."""

    def __init__(self, limit: CourseRateLimit) -> None:
        self._course = ReferenceCourse(limit)
        self._last: float | None = None

    def follow(self, velocity_m_s: Sequence[float], dt_s: float) -> float:
        """The reference course [rad] after dt_s more, for the target's velocity now."""
        course = ReferenceCourse.course_of(velocity_m_s)
        rate = 0.0
        if course is not None and self._last is not None and dt_s > 0:
            rate = wrap(course - self._last) / dt_s
        if course is not None:
            self._last = course
        value = self._course.follow(velocity_m_s, dt_s, turn_rate_rad_s=rate)
        return 0.0 if value is None else value


def reference_courses(
    velocities_m_s: np.ndarray, dt_s: float, limit: CourseRateLimit
) -> np.ndarray:
    """`TrueReference` over a whole run: courses (K,) for velocities (K, 2) dt_s apart, wrapped
    to [-pi, pi)."""
    ref = TrueReference(limit)
    out = [ref.follow(v, dt_s) for v in np.asarray(velocities_m_s, float).tolist()]
    return np.asarray(wrap_angle(np.array(out)))
