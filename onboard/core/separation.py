"""Minimum separation as buffered half-planes between plans (docs/design.md, "Safety").

For a pair of vehicles i, k, both know the same positions: where i's previous plan puts i and
where k's previous plan puts k, now (a_0, b_0) and at every step j of the horizon (a_j, b_j),
since each broadcast its plan. At step j each vehicle keeps its predicted position on its own
side of the line through the midpoint (a_j + b_j) / 2 normal to a_0 - b_0 (the direction between
them now, so that two plans that cross do not swap the sides), at least its margin away:
    n' (p_j - (a_j + b_j) / 2) >= d_safe / 2 + r_M + s / 2 + v_max (age - tau),
    n = (a_0 - b_0) / |a_0 - b_0|,   j = 1..M,
with r_M the tube's widest position radius (the true position stays within it of the predicted
one), s the inter-sample allowance (how much two vehicles can close between two control instants
beyond what the instants show) and age the neighbour's plan age beyond the one period a plan
always has (the neighbour may have moved v_max per second of it). Both vehicles compute the same
lines with opposite normals, so while both keep to their sides the true distance is at least
d_safe + s, whatever each of them replans: no vehicle has to trust the other's new plan. Where
the old plans meet, both give way by half the shortfall.

A neighbour whose plan is stale (older than two periods: it may not be getting ours either) is
not trusted to keep to its half: the line then passes through the neighbour's predicted position
itself, and this vehicle keeps the whole distance, d_safe + r_M + s + v_max (age - tau), alone.
"""

import math
from collections.abc import Sequence

__all__ = ["NO_PLANE", "Plane", "intersample_allowance", "plane_slack", "separation_planes"]

Plane = tuple[float, float, float]
"""A half-plane (n_x, n_y, b): positions p with n' p >= b; a non-finite b means none."""

NO_PLANE: Plane = (0.0, 0.0, math.inf)


def intersample_allowance(*, speed_max_m_s: float, period_s: float, d_safe_m: float) -> float:
    """How far two vehicles at least d_safe apart at two control instants can come closer in
    between [m]: their relative position moves at most 2 v_max tau per period, and a chord of that
    length outside a circle of radius d_safe dips at most (2 v_max tau)^2 / (8 d_safe) into it."""
    chord = 2.0 * speed_max_m_s * period_s
    return chord * chord / (8.0 * max(d_safe_m, 1e-9))


def separation_planes(
    own: Sequence[tuple[float, float]],
    neighbour: Sequence[tuple[float, float]],
    margin: float,
    here: tuple[float, float],
    *,
    shared: bool = True,
) -> list[Plane]:
    """The half-planes this vehicle keeps to against one neighbour at j = 1..M (module
    docstring).

    `own` and `neighbour` are where this vehicle's previous plan and the neighbour's plan put
    them at j = 0..M (this vehicle's position throughout when it has no plan); `margin` is the
    distance to keep from each line; `here`, this vehicle's position, gives the normal's
    direction when the two are at one point now. The lines bisect the pair when they `shared`
    the distance, and pass through the neighbour's positions otherwise. A non-finite margin
    gives none.
    """
    M = len(own) - 1
    if not math.isfinite(margin):
        return [NO_PLANE] * M
    (ax, ay), (bx, by) = own[0], neighbour[0]
    nx, ny = ax - bx, ay - by
    dist = math.hypot(nx, ny)
    if dist < 1e-6:
        nx, ny = here[0] - bx, here[1] - by
        dist = math.hypot(nx, ny)
    if dist < 1e-9:
        nx, ny, dist = 1.0, 0.0, 1.0
    nx, ny = nx / dist, ny / dist
    w = 0.5 if shared else 0.0  # the anchor's share of the way from the neighbour to this one
    return [
        (nx, ny, nx * (bx + w * (ax - bx)) + ny * (by + w * (ay - by)) + margin)
        for (ax, ay), (bx, by) in zip(own[1:], neighbour[1:], strict=True)
    ]


def plane_slack(x: float, y: float, plane: Plane) -> float:
    """How far (x, y) is inside the half-plane [m] (negative: outside); inf for no plane."""
    nx, ny, b = plane
    return nx * x + ny * y - b if math.isfinite(b) else math.inf
