"""What passes between the stages of a control period, and the stages' pure pieces
(docs/design.md, "The control period").

A period is `Agent.step`: learn (DEKF) -> observe the target -> reference (the formation over the
horizon) -> gather (the neighbourhood) -> build the QP -> solve, or fall back -> emit. Each stage
hands the next a frozen record: `Estimate`, `Reference`, `Surroundings`, the QP's `QpData`,
`Decision`. Per-horizon quantities (M + 2 points at most) are plain-float tuples and lists, and
reach the QP as such (it reads them as floats).
"""

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from fleetmpc.onboard.core.separation import Plane, plane_slack
from fleetmpc.onboard.core.tube import InputBox
from fleetmpc.onboard.core.unicycle import advance
from fleetmpc.protocol.plan import Plan, WindSample

__all__ = [
    "Decision",
    "Estimate",
    "Reference",
    "Surroundings",
    "plan_ages",
    "safe_fallback",
]

Point = tuple[float, float]


@dataclass(frozen=True)
class Estimate:
    """The learned model's belief this period (the learn stage's output)."""

    z_now: tuple[float, float, float]
    """The DEKF's state estimate now (x_m, y_m, yaw_rad)."""
    z0: tuple[float, float, float]
    """The state where the plan starts: z_now advanced through the commands sent and not yet
    flown (none unless the autopilot responds late)."""
    beta: tuple[float, float, float, float]
    """The learned (a_V, a_w, d_x, d_y)."""
    start_ns: int
    """When the plan's first input will be flown [ns]: everything downstream is placed then."""
    wind: WindSample | None = None
    """The wind measured this period, for the neighbours (`DualEkf.wind_sample`)."""


@dataclass(frozen=True)
class Reference:
    """The formation over the horizon, j = 0..M+1, and the steady inputs that keep this vehicle
    in its slot under the learned model (the reference stage's output)."""

    track: list[Point]
    """The target's predicted positions [m]."""
    centres: list[Point]
    """The formation's centre [m]."""
    offsets: list[list[Point]]
    """Every slot's offset from the centre at each step [m]."""
    slots: list[Point]
    """This vehicle's slot [m]."""
    u_s: list[Point]
    """Steady inputs (speed_m_s, yaw_rate_rad_s), j = 0..M-1."""
    headings: list[float]
    """Steady headings, j = 0..M [rad] (unwrapped)."""


@dataclass(frozen=True)
class Surroundings:
    """This vehicle's neighbourhood this period (the gather stage's output)."""

    ages: dict[int, float]
    """Age of each neighbour's plan [s]."""
    neighbours: tuple[int, ...] = ()
    """The vehicles it keeps its separation from, nearest first."""
    formation_terms: int = 0
    """Neighbours whose formation term enters the cost."""
    planes: list[list[Plane]] | None = None
    """Per neighbour, a separation half-plane per step j = 1..M."""
    goal: list[Point] | None = None
    """Where the cost pulls this vehicle, j = 1..M [m]."""


@dataclass(frozen=True, eq=False)
class Decision:
    """The inputs the vehicle will fly and the states they lead to (the solve stage's output)."""

    inputs: np.ndarray
    """Planned inputs (M, 2), inside U."""
    states: np.ndarray
    """Predicted states (M + 1, 3), headings wrapped."""
    c: np.ndarray
    """The QP's decision variables (M, 2) (zeros on fallback)."""
    ok: bool
    """False when the fallback law stands in for a QP that failed or did not pass its checks
    (a waiting period's standing plan is no fallback: True)."""
    status: str
    """"solved", the failure behind a fallback, or why the agent is waiting."""
    standing: bool = False
    """A standing plan while the agent waits: no incumbent for the next period's seed."""


def plan_ages(stamp_ns: int, plans: Mapping[int, Plan], ids: frozenset[int]) -> dict[int, float]:
    """Age [s] of each neighbour's plan (of the vehicles in `ids`) at stamp_ns."""
    return {k: (stamp_ns - p.stamp_ns) * 1e-9 for k, p in plans.items() if k in ids}


def safe_fallback(
    z0: tuple[float, ...],
    u: np.ndarray,
    beta: tuple[float, ...],
    planes: list[list[Plane]],
    *,
    box: InputBox,
    horizon: int,
    tau: float,
) -> np.ndarray:
    """The fallback input: the tube law `u` if, held over the horizon, it keeps every
    separation half-plane; otherwise, of `u` and the corners and mid-points of U
    (`InputBox.corners`), the input whose rollout leaves the half-planes least (the largest
    smallest slack over steps and neighbours)."""
    candidates = [tuple(u.tolist()), *box.corners()]
    best, best_slack = candidates[0], -math.inf
    for v, w in candidates:
        z, slack = tuple(z0), math.inf
        for j in range(horizon):
            z = advance(*z, v, w, beta, tau)
            slack = min(slack, min((plane_slack(z[0], z[1], p[j]) for p in planes), default=slack))
        if slack >= 0.0 and (v, w) == candidates[0]:
            return u
        if slack > best_slack:
            best, best_slack = (v, w), slack
    return np.array(best)
