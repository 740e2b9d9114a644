"""The per-period fields of a flight record that depend only on the scenario.

The true target's position and velocity, the formation slots around it and the vehicles' truth
parameters (speed and yaw-rate effectiveness, wind) are what the scenario knows, not what a
ground station receives: `ScenarioRows` computes them once per period, in period order.
"""

import numpy as np

from fleetmpc.gcs.growable import Growable
from fleetmpc.onboard.core.agent import reference_course_limit
from fleetmpc.onboard.core.formation import Formation, FormationReference
from fleetmpc.scenario import Scenario

__all__ = ["FIELDS", "ScenarioRows", "formation_reference"]

FIELDS = ("target", "target_velocity", "slots", "slot_offsets_world", "beta_truth")
"""The FlightRecord fields `ScenarioRows` holds."""


def formation_reference(
    formation: Formation,
    reference: FormationReference,
    target_m: np.ndarray,
    target_velocity_m_s: np.ndarray,
    period_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Slots (K, N, 2) of the true target over K consecutive periods and each slot's offset from
    the formation centre (K, N, 2), for target positions and velocities (K, 2).

    The reference is stateful (the target's path, a rate-limited course), so the periods go
    through `reference` in order, continuing where its previous call stopped.
    """
    centres, courses = reference.follow_run(target_m, target_velocity_m_s, period_s)
    slots = formation.slots(centres, courses)
    return slots, slots - centres[:, None, :]


class ScenarioRows:
    """The scenario's per-period fields (`FIELDS`) of its first `count` periods."""

    def __init__(self, scenario: Scenario) -> None:
        self.scenario = scenario
        self.formation = Formation(scenario.formation)
        self._reference = FormationReference(
            self.formation, reference_course_limit(scenario.controller, scenario.formation)
        )
        """The formation reference of the true target, advanced as the periods are."""
        self._rows = {name: Growable() for name in FIELDS}

    @property
    def count(self) -> int:
        """Periods computed."""
        return self._rows["target"].count

    def extend(self, k_n: int) -> None:
        """Compute the fields up to `k_n` periods (none if they are)."""
        sc = self.scenario
        k0 = self.count
        if k_n <= k0:
            return
        period_s = sc.controller.period_ns * 1e-9
        times = (np.arange(k0, k_n) * sc.controller.period_ns * 1e-9).tolist()
        state_at = sc.target.state_floats
        truths = [sc.vehicle(vid).truth for vid in sc.vehicle_ids]
        flat: list[float] = []
        for t in times:
            position, velocity = state_at(t)
            flat += position
            flat += velocity
            for truth in truths:
                flat += (truth.speed_effectiveness, truth.yaw_rate_effectiveness, *truth.wind.at(t))
        n = len(truths)
        values = np.array(flat, dtype=float).reshape(len(times), 4 + 4 * n)
        target, target_vel = values[:, 0:2], values[:, 2:4]
        slots, offsets = formation_reference(
            self.formation, self._reference, target, target_vel, period_s
        )
        new = {
            "target": target,
            "target_velocity": target_vel,
            "slots": slots,
            "slot_offsets_world": offsets,
            "beta_truth": values[:, 4:].reshape(len(times), n, 4),
        }
        for name, rows in new.items():
            self._rows[name].put(k0, rows)

    def rows(self, first: int, k_n: int) -> dict[str, np.ndarray]:
        """The fields of periods `first` .. `k_n` - 1 (computed before: `extend`), as views
        valid until the next `extend`."""
        return {name: self._rows[name].array[first:k_n] for name in FIELDS}
