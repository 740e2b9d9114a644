"""Formation geometry: slots around a centre that trails the target by d_s along its course.

World frame: slot offsets are (North, East). Course frame: offsets are (forward, right) in the
frame whose x axis is the target's course (the direction of its velocity); with NED axes "right"
is the positive rotation, so a course-frame offset o maps to Rot(course) o.
"""

import numpy as np

from onboard.core.config import FormationSettings

__all__ = ["Formation"]


class Formation:
    """Slot positions of every vehicle for a (predicted) target trajectory."""

    def __init__(self, settings: FormationSettings, *, min_course_speed_m_s: float = 0.05) -> None:
        self.settings = settings
        self._offsets = np.array(settings.slots_m)
        self._min_speed = min_course_speed_m_s
        self._course = 0.0

    @property
    def size(self) -> int:
        return self._offsets.shape[0]

    def course(self, target_velocity_m_s: np.ndarray) -> float:
        """Target course [rad]; the last known course while the target is (nearly) still."""
        v = np.asarray(target_velocity_m_s, dtype=float)
        if np.hypot(v[0], v[1]) >= self._min_speed:
            self._course = float(np.arctan2(v[1], v[0]))
        return self._course

    def slots(self, target_positions_m: np.ndarray, target_velocity_m_s: np.ndarray) -> np.ndarray:
        """Slots (K, N, 2) for target positions (K, 2) moving with one velocity (2,)."""
        c = self.course(target_velocity_m_s)
        u = np.array([np.cos(c), np.sin(c)])
        centre = np.asarray(target_positions_m, dtype=float) - self.settings.trail_m * u
        offsets = self._offsets
        if self.settings.frame == "course":
            rot = np.array([[u[0], -u[1]], [u[1], u[0]]])
            offsets = offsets @ rot.T
        return centre[:, None, :] + offsets[None, :, :]

    def desired_distances(self) -> np.ndarray:
        """Desired distance between every pair of slots (N, N) [m]."""
        d = self._offsets[:, None, :] - self._offsets[None, :, :]
        return np.hypot(d[..., 0], d[..., 1])
