import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from fleetmpc.onboard.core.separation import (
    held_inside,
    intersample_allowance,
    plane_slack,
    separation_lines,
)

coord = st.floats(-50.0, 50.0)
NO_DRIFT = [(0.0, 0.0)] * 3


@given(ax=coord, ay=coord, bx=coord, by=coord, margin=st.floats(0.5, 3.0))
def test_a_pair_computes_one_line_and_keeping_to_it_keeps_them_apart(ax, ay, bx, by, margin):
    a, b = (ax, ay), (bx, by)
    if math.hypot(ax - bx, ay - by) < 2.0 * margin + 1e-3:
        return  # (inside the margins: each keeps to where it is, the next test)
    mine = separation_lines(a, b, margin, a, NO_DRIFT)[0]
    theirs = separation_lines(b, a, margin, b, NO_DRIFT)[0]
    # Opposite normals, one bisecting line: the two sides are 2 margin apart.
    assert mine[0] == pytest.approx(-theirs[0]) and mine[1] == pytest.approx(-theirs[1])
    assert mine[2] + theirs[2] == pytest.approx(2.0 * margin, abs=1e-6)
    # Any two points on their sides are at least 2 margin apart.
    n = np.array(mine[:2])
    p = np.array(a) + 7.0 * np.array([-n[1], n[0]])  # slid along the line, on my side
    p = p + (mine[2] - n @ p) * n  # onto my boundary
    q = p - 2.0 * margin * n
    assert plane_slack(*p, mine) == pytest.approx(0.0, abs=1e-6)
    assert plane_slack(*q, theirs) == pytest.approx(0.0, abs=1e-6)


def test_a_stale_neighbour_is_kept_at_the_whole_distance_and_drift_moves_the_line():
    here = (0.0, 0.0)
    (nx, ny, b), *_ = separation_lines(here, (10.0, 0.0), 3.0, here, NO_DRIFT, shared=False)
    assert (nx, ny) == pytest.approx((-1.0, 0.0)) and b == pytest.approx(-7.0)
    drift = [(0.1 * j, 0.0) for j in range(1, 4)]
    planes = separation_lines(here, (10.0, 0.0), 1.0, here, drift)
    assert [p[2] for p in planes] == pytest.approx([-4.0 - 0.1 * j for j in range(1, 4)])


def test_a_vehicle_inside_its_margin_keeps_to_the_line_through_where_it_is():
    here = (0.0, 0.0)
    lines = separation_lines(here, (1.0, 0.0), 2.0, here, NO_DRIFT)
    (nx, ny, b), *_ = held_inside(lines, here, NO_DRIFT)
    assert b == pytest.approx(0.0)  # not -0.5 + 2.0: it may not close, it is not thrown out
    assert plane_slack(0.0, 0.0, (nx, ny, b)) == pytest.approx(0.0)
    (_, _, line), *_ = separation_lines(here, (1.0, 0.0), 2.0, here, NO_DRIFT)
    assert line == pytest.approx(-0.5 + 2.0)  # the margin's own line, where it is drawn back to


def test_intersample_allowance():
    assert intersample_allowance(speed_max_m_s=2.0, period_s=0.2, d_safe_m=2.0) == pytest.approx(
        0.8**2 / 16.0
    )
