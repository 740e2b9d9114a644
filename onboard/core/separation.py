"""Minimum separation as buffered half-planes between plans (docs/design.md, "Safety").

For a pair of vehicles i, k, both know the same two positions now: where i's previous plan puts
i (a) and where k's previous plan puts k (b), since each broadcast its plan. The line through
their midpoint, normal to a - b, splits the plane between them (a buffered Voronoi cell); over
the horizon each vehicle keeps its predicted positions on its own side, at least its margin away
from the line:
    n' (p_j - (a + b) / 2 - d j tau) >= d_safe / 2 + r_M + s / 2 + v_max (age - tau),
    n = (a - b) / |a - b|,   j = 1..M,
with d the learned drift (the wind carries both vehicles and their line alike), r_M the tube's
widest position radius (the true position stays within it of the predicted one), s the
inter-sample allowance (how much two vehicles can close between two control instants beyond
what the instants show) and age the neighbour's plan age beyond the one period a plan always has
(the neighbour may have moved v_max per second of it). Both vehicles compute the same line with
opposite normals, so while both keep to their sides the true distance is at least d_safe + s,
whatever each of them replans: no vehicle has to trust the other's new plan. The cells move
with the vehicles every period, so two vehicles slide past each other over several periods.

A vehicle found inside its margin (pushed there by what the model does not know, beyond the
tube's W) keeps to the line through where it is: it may not close further, rather than being
asked for a jump out that no plan can make. (A vehicle still closing on the line at speed may
not be able to stop within the speed-rate limit; its problem is then infeasible and the
fallback takes over.) Its goal is drawn back onto the margin's line meanwhile
(`fleetmpc.onboard.core.neighbourhood`), so the cost takes it out again.

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

NO_PLANE: Plane = (0.0, 0.0, math.inf)


def intersample_allowance(*, speed_max_m_s: float, period_s: float, d_safe_m: float) -> float:
    """How far two vehicles at least d_safe apart at two control instants can come closer in
    between [m]: their relative position moves at most 2 v_max tau per period, and a chord of that
    length outside a circle of radius d_safe dips at most (2 v_max tau)^2 / (8 d_safe) into it."""
    chord = 2.0 * speed_max_m_s * period_s
    return chord * chord / (8.0 * max(d_safe_m, 1e-9))


def separation_lines(
    own: tuple[float, float],
    neighbour: tuple[float, float],
    margin: float,
    here: tuple[float, float],
    drift_steps: Sequence[tuple[float, float]],
    *,
    shared: bool = True,
) -> list[Plane]:
    """The margin's lines this vehicle keeps to against one neighbour at j = 1..M (module
    docstring), before `held_inside` holds a vehicle inside its margin where it is.

    `own` and `neighbour` are where this vehicle's previous plan (its position when it has none)
    and the neighbour's plan put them now; `margin` is the distance to keep from the line; `here`
    is this vehicle's position (its direction from the neighbour gives the normal when the two
    plans meet at a point); `drift_steps` the drift's displacement d j tau at j = 1..M. The line
    bisects the pair when they `shared` the distance and passes through the neighbour's position
    otherwise. A non-finite margin gives none.
    """
    if not math.isfinite(margin):
        return [NO_PLANE] * len(drift_steps)
    (ax, ay), (bx, by) = own, neighbour
    nx, ny = ax - bx, ay - by
    dist = math.hypot(nx, ny)
    if dist < 1e-6:
        nx, ny = here[0] - bx, here[1] - by
        dist = math.hypot(nx, ny)
    if dist < 1e-9:
        nx, ny, dist = 1.0, 0.0, 1.0
    nx, ny = nx / dist, ny / dist
    if shared:
        bx, by = 0.5 * (ax + bx), 0.5 * (ay + by)
    line = nx * bx + ny * by + margin
    return [(nx, ny, line + nx * dx + ny * dy) for dx, dy in drift_steps]


def held_inside(
    lines: Sequence[Plane], here: tuple[float, float], drift_steps: Sequence[tuple[float, float]]
) -> list[Plane]:
    """The half-planes kept to along the margin's `lines` (`separation_lines`): where the vehicle
    at `here` is inside its margin, the line through where it is, drifting as the margin's does
    (module docstring)."""
    hx, hy = here
    out = []
    for (nx, ny, b), (dx, dy) in zip(lines, drift_steps, strict=True):
        if math.isfinite(b):
            b = min(b, nx * hx + ny * hy + nx * dx + ny * dy)
        out.append((nx, ny, b))
    return out


def plane_slack(x: float, y: float, plane: Plane) -> float:
    """How far (x, y) is inside the half-plane [m] (negative: outside); inf for no plane."""
    nx, ny, b = plane
    return nx * x + ny * y - b if math.isfinite(b) else math.inf
