"""The neighbours' plans by age: a plan from a sender whose clock runs ahead is kept."""

import math

import numpy as np

from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.neighbourhood import Neighbourhood
from fleetmpc.protocol.plan import Plan

SETTINGS = ControllerSettings()
PERIOD_NS = SETTINGS.period_ns
M = SETTINGS.horizon


def _plan(vehicle_id: int, stamp_ns: int, x: float) -> Plan:
    states = np.array([(x + 0.2 * j, 10.0, 0.0) for j in range(M + 1)])
    return Plan(vehicle_id, stamp_ns, PERIOD_NS, states, np.tile((1.0, 0.0), (M, 1)))


def _inflations(age_s: float) -> list[float]:
    hood = Neighbourhood(1, fleet_ids=(1, 2), controller=SETTINGS, tube_radius_m=0.1)
    now = 20 * 10**9
    plan = _plan(2, now - round(age_s * 1e9), 0.0)
    centres = [(0.0, 0.0)] * (M + 2)
    offsets = [[(0.0, 0.0), (0.0, 10.0)]] * (M + 2)
    inflations, _, _ = hood.inflations_and_pull(now, {2: plan}, {2: age_s}, centres, offsets)
    return inflations


def test_a_plan_stamped_in_the_future_is_kept_without_inflation():
    assert _inflations(-0.5) == [0.0]  # a clock 0.5 s fast: kept, as fresh
    assert _inflations(0.2) == [0.0]
    assert _inflations(1.2) == [SETTINGS.speed_max_m_s * 1.0]


def test_a_plan_beyond_the_forget_age_either_way_is_ignored():
    assert math.isinf(_inflations(SETTINGS.plan_forget_s + 1.0)[0])
    assert math.isinf(_inflations(-SETTINGS.plan_forget_s - 1.0)[0])
