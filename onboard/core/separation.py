"""Minimum separation as buffered half-planes between plans (docs/design.md, "Safety").

For a pair of vehicles i, k, both know the same two plans, i's previous plan and k's, since each
broadcast its plan. At each step j of the horizon a line normal to a_j - b_j, where the two plans
put the pair then, splits the plane between them (a buffered Voronoi cell of that step): through
the midpoint of where they are now, moved along the normal by sigma_j, the mean of the two plans'
moves along it where they part or keep their distance (the midpoint of a_j and b_j), but where
they close never toward either faster than that one's own plan retreats. Each vehicle keeps its
predicted position of step j on its own side, at least its margin away from the line:
    n_j' (p_j - (a_0 + b_0) / 2) - sigma_j >= d_safe / 2 + r_M + s / 2 + v_max (age - tau),
    n_j = (a_j - b_j) / |a_j - b_j|,   j = 1..M,
with r_M the tube's widest position radius (the true position stays within it of the predicted
one), s the inter-sample allowance (how much two vehicles can close between two control instants
beyond what the instants show) and age the neighbour's plan age beyond the one period a plan
always has (the neighbour may have moved v_max per second of it). Both vehicles compute the same
lines with opposite normals, so while both keep to their sides the true distance is at least
d_safe + s, whatever each of them replans: no vehicle has to trust the other's new plan. The
caller chooses the positions: against an older plan, where the two may not hold the same plans,
it passes where they are now, carried by the wind (`fleetmpc.onboard.core.neighbourhood`).

A vehicle found inside its margin of the line now (pushed there by what the model does not know,
beyond the tube's W) is allowed that shortfall at every step: it keeps to the line through where
it is as the line moves, rather than being asked for a jump out that no plan can make. (A vehicle
still closing on the line at speed may not be able to stop within the speed-rate limit; its
problem is then infeasible and the fallback takes over.) Its goal is drawn back onto the
margin's line meanwhile (`fleetmpc.onboard.core.neighbourhood`), so the cost takes it out again.

A neighbour whose plan is stale (older than two periods: it may not be getting ours either) is
not trusted to keep to its half: the line then passes through the neighbour's position itself,
and this vehicle keeps the whole distance, d_safe + r_M + s + v_max (age - tau), alone.
"""

import math
from collections.abc import Sequence

__all__ = [
    "NO_PLANE",
    "Plane",
    "held_inside",
    "intersample_allowance",
    "plane_slack",
    "separation_lines",
]

Plane = tuple[float, float, float]
"""A half-plane (n_x, n_y, b): positions p with n' p >= b; a non-finite b means none."""

Point = tuple[float, float]

NO_PLANE: Plane = (0.0, 0.0, math.inf)


def intersample_allowance(*, speed_max_m_s: float, period_s: float, d_safe_m: float) -> float:
    """How far two vehicles at least d_safe apart at two control instants can come closer in
    between [m]: their relative position moves at most 2 v_max tau per period, and a chord of that
    length outside a circle of radius d_safe dips at most (2 v_max tau)^2 / (8 d_safe) into it."""
    chord = 2.0 * speed_max_m_s * period_s
    return chord * chord / (8.0 * max(d_safe_m, 1e-9))


def separation_lines(
    own: Sequence[Point],
    neighbour: Sequence[Point],
    margin: float,
    here: Point,
    *,
    shared: bool = True,
) -> list[Plane]:
    """The margin's lines this vehicle keeps to against one neighbour at j = 0..M (module
    docstring), before `held_inside` holds a vehicle inside its margin where it is.

    `own[j]` and `neighbour[j]` are where this vehicle's previous plan (its position when it has
    none) and the neighbour's plan put them at step j; `margin` is the distance to keep from the
    line; `here` is this vehicle's position (its direction from the neighbour gives the normal
    where the two plans meet at a point). Each step's line lies between the pair when they
    `shared` the distance (`_line`) and passes through the neighbour's position otherwise. A
    non-finite margin gives none.
    """
    if not math.isfinite(margin):
        return [NO_PLANE] * len(own)
    return [
        _line(own[0], neighbour[0], a, b, margin, here, shared)
        for a, b in zip(own, neighbour, strict=True)
    ]


def _line(
    a0: Point, b0: Point, a: Point, b: Point, margin: float, here: Point, shared: bool
) -> Plane:
    """The margin's line at one step, where this vehicle is at `a` (at `a0` now) and the
    neighbour at `b` (`b0` now): normal to a - b; through the neighbour's position, or, shared,
    moved from the midpoint now along the normal by as much as the two move apart along it
    (`_shift`)."""
    (ax, ay), (bx, by) = a, b
    nx, ny = ax - bx, ay - by
    dist = math.hypot(nx, ny)
    if dist < 1e-6:
        nx, ny = here[0] - bx, here[1] - by
        dist = math.hypot(nx, ny)
    if dist < 1e-9:
        nx, ny, dist = 1.0, 0.0, 1.0
    nx, ny = nx / dist, ny / dist
    if not shared:
        return nx, ny, nx * bx + ny * by + margin
    mine = nx * (ax - a0[0]) + ny * (ay - a0[1])  # (how far each plan moves along the normal)
    theirs = nx * (bx - b0[0]) + ny * (by - b0[1])
    mid = 0.5 * (nx * (a0[0] + b0[0]) + ny * (a0[1] + b0[1]))
    return nx, ny, mid + _shift(mine, theirs) + margin


def _shift(mine: float, theirs: float) -> float:
    """How far a shared line moves from the midpoint now along its normal (toward this vehicle)
    when this vehicle's plan moves `mine` along it and the neighbour's `theirs`: with the two
    (the midpoint of where they are then) where they move apart or together, but never toward
    either faster than that vehicle's own plan retreats where they close (docs/design.md, "The
    half-planes")."""
    if mine >= theirs:
        return 0.5 * (mine + theirs)
    return min(max(0.0, mine), theirs)


def held_inside(lines: Sequence[Plane], here: Point) -> list[Plane]:
    """The half-planes kept to at j = 1..M along the margin's `lines` at j = 0..M
    (`separation_lines`): a vehicle at `here` that is inside its margin of the line now (j = 0)
    is allowed that shortfall at every step, so it keeps to the line through where it is as the
    line moves (module docstring)."""
    nx, ny, b = lines[0]
    short = max(b - (nx * here[0] + ny * here[1]), 0.0) if math.isfinite(b) else 0.0
    return [(mx, my, c - short) for mx, my, c in lines[1:]]


def plane_slack(x: float, y: float, plane: Plane) -> float:
    """How far (x, y) is inside the half-plane [m] (negative: outside); inf for no plane."""
    nx, ny, b = plane
    return nx * x + ny * y - b if math.isfinite(b) else math.inf
