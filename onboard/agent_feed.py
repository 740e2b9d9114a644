"""What every runner of an agent does alike, the live fleet runner (`fleetmpc.onboard.runner`)
and the lockstep simulation: build the agent from its scenario, hand it each target observation
once, and narrow its plan bus to the neighbourhood it plans against.
"""

import dataclasses

import numpy as np

from fleetmpc.bus.planbus import PlanBus
from fleetmpc.onboard.core.agent import Agent
from fleetmpc.scenario import Scenario, VehicleSpec

__all__ = ["TargetFeed", "agent_for", "listen_for"]


def agent_for(scenario: Scenario, vehicle: VehicleSpec, *, learning: bool = True) -> Agent:
    """The agent of one vehicle of a scenario, as every runner builds it (the live agent and the
    lockstep simulation); `learning` False turns the scenario's learning off."""
    enabled = learning and scenario.learning.enabled
    return Agent(
        vehicle.id,
        fleet_ids=scenario.vehicle_ids,
        controller=scenario.controller,
        learning=dataclasses.replace(scenario.learning, enabled=enabled),
        formation=scenario.formation,
        target_observation_std_m=scenario.target.observation_noise_m,
        response_delay_s=vehicle.response_delay_s,
    )


class TargetFeed:
    """Each target observation on a plan bus once: `take` hands over the newest one no older
    than `max_age_ns`, if it is newer than the last one handed over (the live runner's and the
    lockstep simulation's, for each agent)."""

    def __init__(self, bus: PlanBus, *, max_age_ns: int) -> None:
        self._bus = bus
        self._max_age_ns = max_age_ns
        self._last_stamp_ns = -1

    def take(self, now_ns: int) -> tuple[np.ndarray | None, int | None]:
        """(North, East) [m] of a new observation and its stamp [ns], or (None, None)."""
        target = self._bus.latest_target(now_ns, self._max_age_ns)
        if target is None or target.stamp_ns <= self._last_stamp_ns:
            return None, None
        self._last_stamp_ns = target.stamp_ns
        return np.array([target.north_m, target.east_m]), target.stamp_ns


def listen_for(agent: Agent, bus: PlanBus) -> None:
    """Narrow the plan bus to what the agent now needs to hear (`Agent.interest`)."""
    interest = agent.interest()
    if interest is not None:
        bus.listen_near(*interest)
