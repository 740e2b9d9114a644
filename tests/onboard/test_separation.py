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


@given(ax=coord, ay=coord, bx=coord, by=coord, margin=st.floats(0.5, 3.0))
def test_a_pair_computes_one_line_and_keeping_to_it_keeps_them_apart(ax, ay, bx, by, margin):
    a, b = (ax, ay), (bx, by)
    if math.hypot(ax - bx, ay - by) < 2.0 * margin + 1e-3:
        return  # (inside the margins: each keeps to where it is, the next test)
    (mine,) = separation_lines([a], [b], margin, a)
    (theirs,) = separation_lines([b], [a], margin, b)
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


def test_a_stale_neighbour_is_kept_at_the_whole_distance_and_each_step_has_its_line():
    here = (0.0, 0.0)
    ((nx, ny, b),) = separation_lines([here], [(10.0, 0.0)], 3.0, here, shared=False)
    assert (nx, ny) == pytest.approx((-1.0, 0.0)) and b == pytest.approx(-7.0)
    own = [(0.0, 0.5 * j) for j in range(4)]  # flying East, abreast of a neighbour
    theirs = [(10.0, 0.5 * j) for j in range(4)]
    lines = separation_lines(own, theirs, 1.0, here)
    assert np.array([p[:2] for p in lines]) == pytest.approx(np.tile((-1.0, 0.0), (4, 1)))
    assert [p[2] for p in lines] == pytest.approx([-4.0] * 4)  # x <= 4 at every step
    turning = [(0.0, 0.0), (0.0, 0.0), (10.0, -10.0), (10.0, 10.0)]  # it swings round us
    normals = np.array([p[:2] for p in separation_lines([here] * 4, turning, 1.0, here)])
    half = 0.5**0.5
    assert normals[2:] == pytest.approx(np.array([(-half, half), (-half, -half)]))
    assert normals[:2] == pytest.approx(np.tile((1.0, 0.0), (2, 1)))  # (met: fixed normal)


@pytest.mark.parametrize(
    ("own", "theirs", "bounds"),
    [
        # A column flying North together, the neighbour 4 m behind: the line moves with them.
        ([(1.0 * j, 0.0) for j in range(3)], [(-4.0 + j, 0.0) for j in range(3)], [-1, 0, 1]),
        # The neighbour closing on a vehicle that stands: the line of now holds.
        ([(0.0, 0.0)] * 3, [(-4.0 + j, 0.0) for j in range(3)], [-1, -1, -1]),
        # Chased: the line follows this vehicle's retreat (0.5 m a step), not the chaser (1 m).
        ([(0.5 * j, 0.0) for j in range(3)], [(-4.0 + j, 0.0) for j in range(3)], [-1, -0.5, 0]),
    ],
)
def test_a_shared_line_moves_with_the_pair_never_toward_one_faster_than_its_plan_retreats(
    own, theirs, bounds
):
    mine = separation_lines(own, theirs, 1.0, own[0])
    assert np.array([p[:2] for p in mine]) == pytest.approx(np.tile((1.0, 0.0), (3, 1)))
    assert [p[2] for p in mine] == pytest.approx(bounds)
    # The neighbour places the same lines with the opposite normals: 2 margins between sides.
    other = separation_lines(theirs, own, 1.0, theirs[0])
    assert [p[2] + q[2] for p, q in zip(mine, other, strict=True)] == pytest.approx([2.0] * 3)


def test_a_vehicle_inside_its_margin_keeps_to_the_line_through_where_it_is():
    here = (0.0, 0.0)
    lines = separation_lines([here] * 3, [(1.0, 0.0)] * 3, 2.0, here)
    assert len(held_inside(lines, here)) == 2  # j = 1..M of the lines at j = 0..M
    (nx, ny, b), _ = held_inside(lines, here)
    assert b == pytest.approx(0.0)  # not -0.5 + 2.0: it may not close, it is not thrown out
    assert plane_slack(0.0, 0.0, (nx, ny, b)) == pytest.approx(0.0)
    assert lines[1][2] == pytest.approx(-0.5 + 2.0)  # the margin's own line, drawn back to
    moving = separation_lines([here, here, here], [(1.0, 0.0), (1.5, 0.0), (2.0, 0.0)], 2.0, here)
    assert [p[2] for p in held_inside(moving, here)] == pytest.approx([-0.25, -0.5])


def test_intersample_allowance():
    assert intersample_allowance(speed_max_m_s=2.0, period_s=0.2, d_safe_m=2.0) == pytest.approx(
        0.8**2 / 16.0
    )
