import math

import pytest

from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.seeding import Seeder

SETTINGS = ControllerSettings(horizon=5)


def _seeder() -> Seeder:
    return Seeder(SETTINGS, TubeLbmpc(SETTINGS, n_neighbours=1).box)


def test_steady_inputs_keep_the_model_on_slots_that_fly_a_straight_line():
    seeder = _seeder()
    slots = [(0.3 * j, 0.0) for j in range(SETTINGS.horizon + 2)]  # 1.5 m/s North
    u_s, headings = seeder.steady_inputs(slots, [1.0, 1.0, 0.0, 0.0], 0.0)
    assert u_s == [pytest.approx((1.5, 0.0))] * SETTINGS.horizon
    assert headings == pytest.approx([0.0] * (SETTINGS.horizon + 1))


def test_steady_inputs_across_slots_that_jump_ask_for_no_more_than_the_box():
    """The period a formation's first course is known its slots jump within the horizon (21 m
    at once in a 25 m circle's wedge); unclipped, u_s asked for 106 m/s."""
    seeder = _seeder()
    slots = [(0.0, 0.2 * j) for j in range(3)] + [(21.0, 5.0 + 0.2 * j) for j in range(4)]
    u_s, _ = seeder.steady_inputs(slots, [1.0, 1.0, 0.0, 0.0], math.pi / 2)
    for (v, w), (v_lo, w_lo, v_hi, w_hi) in zip(u_s, seeder.box.steps, strict=True):
        assert v_lo <= v <= v_hi
        assert w_lo <= w <= w_hi
    assert u_s[2][0] == pytest.approx(seeder.box.steps[2][2])  # (the jump: at the bound)
