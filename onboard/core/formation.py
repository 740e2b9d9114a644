"""Formation geometry: slots around a centre that trails the target by d_s along its course.

World frame: slot offsets are (North, East). Course frame: offsets are (forward, right) in the
frame whose x axis is the target's course (the direction of its velocity); with NED axes "right"
is the positive rotation, so a course-frame offset o maps to Rot(course) o.
"""

import math

import numpy as np

from onboard.core.config import FormationSettings

__all__ = ["Formation"]


class Formation:
    """Slot positions of every vehicle for a (predicted) target trajectory."""

    def __init__(self, settings: FormationSettings, *, min_course_speed_m_s: float = 0.05) -> None:
        self.settings = settings
        self._offsets = np.array(settings.slots_m)
        self._offsets_list = [(float(x), float(y)) for x, y in settings.slots_m]
        self._min_speed = min_course_speed_m_s
        self._course = 0.0

    @property
    def size(self) -> int:
        return self._offsets.shape[0]

    def course(self, target_velocity_m_s: np.ndarray | tuple[float, float]) -> float:
        """Target course [rad]; the last known course while the target is (nearly) still."""
        vx, vy = target_velocity_m_s
        vx, vy = float(vx), float(vy)  # plain floats from an array or a pair alike
        if math.hypot(vx, vy) >= self._min_speed:
            self._course = math.atan2(vy, vx)
        return self._course

    def placement(
        self, target_velocity_m_s: np.ndarray | tuple[float, float]
    ) -> tuple[float, float, list[tuple[float, float]]]:
        """Where the slots sit around the target, in the world frame, as plain floats.

        Returns (trail_x, trail_y, offsets): the centre is the target position less
        (trail_x, trail_y), and slot i is the centre plus offsets[i].
        """
        c = self.course(target_velocity_m_s)
        ux, uy = math.cos(c), math.sin(c)
        trail = self.settings.trail_m
        offsets = self._offsets_list
        if self.settings.frame == "course":  # (forward, right) rotated by the course
            offsets = [(ox * ux - oy * uy, ox * uy + oy * ux) for ox, oy in offsets]
        return trail * ux, trail * uy, offsets

    def slots(self, target_positions_m: np.ndarray, target_velocity_m_s: np.ndarray) -> np.ndarray:
        """Slots (K, N, 2) for target positions (K, 2) moving with one velocity (2,)."""
        trail_x, trail_y, offsets = self.placement(target_velocity_m_s)
        centre = np.asarray(target_positions_m, dtype=float) - np.array([trail_x, trail_y])
        return centre[:, None, :] + np.array(offsets)

    def desired_distances(self) -> np.ndarray:
        """Desired distance between every pair of slots (N, N) [m]."""
        d = self._offsets[:, None, :] - self._offsets[None, :, :]
        return np.hypot(d[..., 0], d[..., 1])
