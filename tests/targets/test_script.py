"""The scripted target's figure eight: analytic velocity, turns both ways, varying speed."""

import math

import numpy as np
import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.scenario import parse_scenario
from fleetmpc.targets.script import TargetScript

EIGHT = TargetScript(
    kind="figure_eight", center_m=(10.0, -20.0), radius_m=60.0, period_s=410.0, start_angle_rad=0.3
)
A_W_M_S = 60.0 * 2.0 * math.pi / 410.0
"""a w: the eight's speed scale [m/s]."""
T_S = np.linspace(0.0, 410.0, 8201)  # one period, every 0.05 s


def _states(script: TargetScript) -> tuple[np.ndarray, np.ndarray]:
    states = [script.state_at(float(t)) for t in T_S]
    return np.array([p for p, _ in states]), np.array([v for _, v in states])


def test_velocity_is_the_derivative_of_the_position():
    h = 1e-3
    for t in np.linspace(0.0, 410.0, 97):
        (x1, y1), _ = EIGHT.state_floats(t + h)
        (x0, y0), _ = EIGHT.state_floats(t - h)
        vx, vy = EIGHT.state_floats(t)[1]
        # central difference: error a w^3 h^2 / 6 ~ 1e-10 m/s here
        assert vx == pytest.approx((x1 - x0) / (2 * h), abs=1e-8)
        assert vy == pytest.approx((y1 - y0) / (2 * h), abs=1e-8)


def test_state_at_and_state_floats_agree_and_start_where_phi_0_says():
    for t in (0.0, 17.3, 205.0, 409.9):
        pos, vel = EIGHT.state_at(t)
        (x, y), (vx, vy) = EIGHT.state_floats(t)
        assert (pos[0], pos[1], vel[0], vel[1]) == (x, y, vx, vy)
    (x, y), _ = EIGHT.state_floats(0.0)
    assert x == pytest.approx(10.0 + 60.0 * math.sin(0.3), abs=1e-12)
    assert y == pytest.approx(-20.0 + 60.0 * math.sin(0.3) * math.cos(0.3), abs=1e-12)
    (x, y), _ = EIGHT.state_floats(410.0)  # one period later: back where it started
    assert (x, y) == pytest.approx(EIGHT.state_floats(0.0)[0], abs=1e-9)


def test_it_turns_both_ways_and_its_speed_varies():
    pos, vel = _states(EIGHT)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    # a w sqrt(cos^2 phi + cos^2 2 phi): from a w sqrt(7/16) in the lobes to a w sqrt(2) at the
    # centre, more than twice as fast
    assert speed.min() == pytest.approx(A_W_M_S * math.sqrt(7 / 16), rel=1e-4)
    assert speed.max() == pytest.approx(A_W_M_S * math.sqrt(2), rel=1e-4)
    assert speed.max() > 1.2 * speed.min()
    turn = np.gradient(np.unwrap(np.arctan2(vel[:, 1], vel[:, 0])), T_S)  # course rate [rad/s]
    # positive = clockwise from above with North up = right in NED; the tightest turn of a
    # Gerono lemniscate has radius 0.209 a, at speed 0.80 a w
    assert turn.max() > 0.04 and turn.min() < -0.04
    radius = speed / np.maximum(np.abs(turn), 1e-12)
    assert radius.min() == pytest.approx(0.2088 * 60.0, rel=2e-3)
    # it stays within a by a / 2 of its centre
    assert np.abs(pos[:, 0] - 10.0).max() == pytest.approx(60.0, abs=1e-3)
    assert np.abs(pos[:, 1] + 20.0).max() == pytest.approx(30.0, abs=1e-3)


@pytest.mark.parametrize("period", [0.0, -5.0, math.inf])
def test_period_must_be_positive_and_the_error_names_it(period):
    with pytest.raises(ConfigError, match="target.period_s"):
        TargetScript(kind="figure_eight", period_s=period)
    doc = {
        "name": "t",
        "target": {"kind": "figure_eight", "period_s": period},
        "vehicles": [{"id": 1, "initial": [0.0, 0.0, 0.0], "slot_m": [0.0, 0.0]}],
    }
    with pytest.raises(ConfigError, match=r"^target\.period_s: must be"):
        parse_scenario(doc)
