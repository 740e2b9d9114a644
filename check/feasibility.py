"""`fleetmpc check SCENARIO`: can this fleet do what the scenario asks, before anything flies?

Checks, each reported with its numbers:
- the tube-tightened input sets U ⊖ K R_j are non-empty (else the controller cannot start);
- speed: every slot's required airspeed over the run (target motion, the outer vehicle's extra
  speed in turns, and the wind and effectiveness the scenario's truth states) fits inside the
  tightened speed bound — otherwise the target outruns the team. The slots are the ones the agents
  fly: the formation at its rate-limited reference course (`fleetmpc.onboard.core.formation`);
- turn rate: every slot's required yaw rate (its turn over YAW_RATE_WINDOW_S) fits inside the
  tightened yaw-rate bound, except at
  the target's sharp corners (a waypoint), where the slots' velocities turn at once and no
  vehicle can: each corner is reported as a transient instead (how long the worst vehicle takes
  to turn, how far it falls behind, how long until it is back);
- horizon reach: how far a vehicle can close on its slot in one horizon, and how long the worst
  initial gap takes to close at the spare speed.
"""

import argparse
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fleetmpc.check.track_report import track_lines
from fleetmpc.check.wind_report import learner_noise_lines, wind_lines
from fleetmpc.errors import InfeasibleError
from fleetmpc.gcs.metrics import corner_indices
from fleetmpc.onboard.core.agent import reference_course_limit, vehicle_mpc
from fleetmpc.onboard.core.formation import CourseRateLimit, Formation, true_reference
from fleetmpc.onboard.core.lbmpc import TubeLbmpc
from fleetmpc.onboard.core.neighbourhood import safety_radius, shared_margin_m
from fleetmpc.onboard.core.target_path import CHORD_HALF_M
from fleetmpc.onboard.core.unicycle import wrap
from fleetmpc.scenario import Scenario, VehicleSpec, load_scenario
from fleetmpc.targets.track import RecordedTrack

__all__ = ["FeasibilityReport", "add_arguments", "check_scenario", "run"]


@dataclass(frozen=True)
class FeasibilityReport:
    """The verdict and the numbers behind it."""

    feasible: bool
    problems: tuple[str, ...]
    lines: tuple[str, ...]

    def render(self) -> str:
        verdict = "FEASIBLE" if self.feasible else "INFEASIBLE"
        out = [*self.lines, "", f"verdict: {verdict}"]
        out += [f"  - {p}" for p in self.problems]
        return "\n".join(out)


_CHECK_STEP_S = 0.05
"""Sampling step of the check's slot trajectories [s]."""

YAW_RATE_WINDOW_S = 2.0
"""A slot's yaw rate is judged as its turn over this window [s]: a slot that turns faster than the
bound for a moment but not over the window costs its vehicle a heading lag of at most the excess
rate times the window (about a degree at the end of a corner's sweep), not the formation."""

SLOT_JUMP_M_S = 0.1
"""A slot whose velocity changes by more than this from one check step to the next (2 m/s^2)
jumps: a transient, as a corner is, not a steady need."""

COURSE_LAG_REPORT_RAD = math.radians(2.0)
"""A course-frame formation's reference course falling this far behind the target's on a turn
it may not follow as fast (docs/design.md, "Formation reference") is reported."""

TURN_LAG_MAX_M = 0.1
"""A slot that turns faster than the bound over the window is infeasible only if the heading lag
costs its vehicle more than this much position: about its air speed x the excess rate x the
window^2 / 2 [m]. A slot that nearly stops can turn fast at little cost: a world-frame formation
sweeping after a corner, its trail's swing nearly cancelling the target's velocity."""


@dataclass(frozen=True)
class _Requirements:
    """What the slots ask of each vehicle over the run, away from the target's corners."""

    speeds_m_s: np.ndarray
    """Peak airspeed command of each vehicle's slot (N,) [m/s]."""
    yaw_rates_rad_s: np.ndarray
    """Peak yaw-rate command of each vehicle's slot (N,) [rad/s]."""
    turn_lags_m: np.ndarray
    """Largest position lag each vehicle's slot's turns beyond the yaw-rate bound would cost it
    (TURN_LAG_MAX_M) (N,) [m]."""
    corners: list["_Corner"]
    """The formation's transient at each of the target's corners."""
    course_lag_rad: float
    """How far a course-frame formation's reference course falls behind the target's where the
    target turns steadily faster than the reference may (outside corners) [rad]."""
    course_lag_for_s: float
    """How long that turn lasts [s]."""


@dataclass(frozen=True)
class _Corner:
    """How the formation goes round one of the target's corners (the worst vehicle's)."""

    target_s: float
    """When the target turns the corner [s]."""
    start_s: float
    """When the formation's centre starts round it [s]."""
    duration_s: float
    """How long its centre takes round it (its smoothing window crossing the corner) [s]."""
    turn_rad: float
    """The largest turn of a slot's velocity over that time [rad]."""
    behind_m: float
    """How far that slot's vehicle falls behind, turning at the tightened yaw-rate bound [m]."""
    back_s: float
    """When that vehicle is back on its slot, after the target's corner [s] (inf: never)."""


def _corner_lag(
    air: np.ndarray, first: int, last: int, yaw_rate_bound: float, speed_bound: float, dt: float
) -> tuple[float, float]:
    """A vehicle flying its slot's air velocity `air` (K, 2) round a corner (steps first..last)
    with its heading turning at most at `yaw_rate_bound`: how far behind its slot it falls [m],
    and how long after `first` it is back on it [s] (closing the gap at its spare speed)."""
    course = np.unwrap(np.arctan2(air[:, 1], air[:, 0]))
    heading, gap, worst, caught = course[first], np.zeros(2), 0.0, first
    for k in range(first, len(air)):
        turn = course[k] - heading
        heading += max(-yaw_rate_bound * dt, min(turn, yaw_rate_bound * dt))
        speed = float(np.hypot(*air[k]))
        flown = speed * np.array((math.cos(heading), math.sin(heading)))
        gap += (air[k] - flown) * dt
        worst = max(worst, float(np.hypot(*gap)))
        if abs(course[k] - heading) > 0.02:
            caught = k
        elif k > last:
            break
    spare = speed_bound - float(np.hypot(*air[min(caught, len(air) - 1)]))
    closing = worst / spare if spare > 0 else math.inf
    return worst, (caught - first) * dt + closing


def _slot_requirements(
    sc: Scenario, course_limit: CourseRateLimit, dt_s: float = _CHECK_STEP_S
) -> _Requirements:
    """The slots' airspeed and yaw-rate needs, and the corners' transients, over the run, for a
    reference course turning at most as `course_limit` allows."""
    t = np.arange(0.0, sc.duration_s + dt_s, dt_s)
    formation = Formation(sc.formation)
    states = [sc.target.state_at(ti) for ti in t]
    target = np.array([p for p, _ in states])
    target_vel = np.array([v for _, v in states])
    centres, courses = true_reference(formation, course_limit, target, target_vel, dt_s)
    slots = formation.slots(centres, courses)  # (K, N, 2)
    vel = np.diff(slots, axis=0) / dt_s  # over each step (K - 1, N, 2)
    steady, windows = _transients(sc, target, target_vel, vel)
    needs = [
        _vehicle_needs(v, vel[:, i], t, steady, course_limit, dt_s)
        for i, v in enumerate(sc.vehicles)
    ]
    airs = [n.air for n in needs]
    corners = [_worst_corner(airs, window, t, course_limit, dt_s) for window in windows]
    lag_rad, lag_for_s = 0.0, 0.0
    if sc.formation.frame == "course":
        lag_rad, lag_for_s = _course_lag(target_vel, steady, course_limit, dt_s)
    return _Requirements(
        np.array([n.speed_m_s for n in needs]),
        np.array([n.rate_rad_s for n in needs]),
        np.array([n.lag_m for n in needs]),
        corners,
        lag_rad,
        lag_for_s,
    )


class _Needs(NamedTuple):
    """What one vehicle's slot asks of it over the run."""

    air: np.ndarray
    """Its airspeed vector over each step (K - 1, 2) [m/s]."""
    speed_m_s: float
    """Its largest airspeed."""
    rate_rad_s: float
    """Its largest yaw rate away from the corners."""
    lag_m: float
    """The furthest it lags behind a turn it cannot keep up with, away from the corners."""


def _transients(
    sc: Scenario, target: np.ndarray, target_vel: np.ndarray, vel: np.ndarray
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Which steps are steady (K - 1,), and each corner's (its step, the first and the last
    step of its transient).

    A corner of the target's (a change of course or speed at once) is a transient, not a
    steady need: its speed change reaches the slots at once (the centre moves along the path
    at the target's speed), and its turn while the formation's centre goes round it, that is
    while the centre's smoothing window (CHORD_HALF_M either side of it, d_s of path behind
    the target) lies across it; the slots turn faster there than elsewhere. So is a slot's
    velocity that jumps (a sweep that ends: its turn rate stops at once)."""
    k_steps = len(vel)
    arc = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(target, axis=0).T))))[:-1]
    behind = arc - sc.formation.trail_m
    steady = np.ones(k_steps, dtype=bool)
    windows = []
    for k in corner_indices(target_vel):
        if k >= len(arc):
            continue  # (a corner at the run's last instant: no transient within the run)
        steady[max(k - 2, 0) : k + 2] = False
        across = np.flatnonzero(np.abs(behind - arc[k]) <= CHORD_HALF_M + 0.5)
        across = across[across >= k] if sc.formation.trail_m >= 0 else across
        if across.size == 0:
            continue
        first, last = int(across[0]), min(int(across[-1]), k_steps - 1)
        steady[first : last + 1] = False
        windows.append((k, first, last))
    jumps = np.max(np.hypot(*np.diff(vel, axis=0).transpose(2, 0, 1)), axis=1)
    for k in np.flatnonzero(jumps > SLOT_JUMP_M_S):
        steady[max(k - 1, 0) : k + 3] = False
    return steady, windows


def _vehicle_needs(
    v: VehicleSpec,
    vel: np.ndarray,
    t: np.ndarray,
    steady: np.ndarray,
    course_limit: CourseRateLimit,
    dt_s: float,
) -> "_Needs":
    """What one vehicle's slot, of velocity `vel` (K - 1, 2), asks of it."""
    wind = np.array([v.truth.wind.at(ti) for ti in t[:-1]])
    air = (vel - wind) / v.truth.speed_effectiveness
    speed = np.hypot(air[:, 0], air[:, 1])
    heading = np.unwrap(np.arctan2(air[:, 1], air[:, 0]))
    # The turn over a window: a vehicle lags a heading it cannot follow for a moment by a
    # fraction of a degree, and what it must keep up with is the turn over the window.
    half = max(1, round(0.5 * YAW_RATE_WINDOW_S / dt_s))
    turn = np.zeros_like(heading)
    turn[half:-half] = (heading[2 * half :] - heading[: -2 * half]) / (2 * half * dt_s)
    rate = np.abs(turn) / v.truth.yaw_rate_effectiveness
    judged = (speed > 0.1) & steady
    for k in np.flatnonzero(~steady):  # no window reaching over a corner
        judged[max(k - half, 0) : k + half + 1] = False
    excess = np.maximum(rate - course_limit.yaw_rate_bound_rad_s, 0.0)
    lag = speed * excess * YAW_RATE_WINDOW_S**2 / 2.0
    if not judged.any():
        return _Needs(air, float(np.max(speed)), 0.0, 0.0)
    return _Needs(
        air, float(np.max(speed)), float(np.max(rate[judged])), float(np.max(lag[judged]))
    )


def _worst_corner(
    airs: list[np.ndarray],
    window: tuple[int, int, int],
    t: np.ndarray,
    course_limit: CourseRateLimit,
    dt_s: float,
) -> "_Corner | None":
    """How the vehicle furthest behind goes round one corner (its step, the first and the
    last step of its transient), from each vehicle's airspeed vectors `airs`."""
    k, first, last = window
    worst = None
    for air in airs:
        a, b = air[max(first - 1, 0)], air[min(last + 1, len(air) - 1)]
        angle = abs(wrap(math.atan2(b[1], b[0]) - math.atan2(a[1], a[0])))
        behind_m, back_s = _corner_lag(
            air, first, last, course_limit.yaw_rate_bound_rad_s, course_limit.speed_bound_m_s, dt_s
        )
        lateness = (first - k) * dt_s + back_s
        if worst is None or (behind_m, lateness) > (worst.behind_m, worst.back_s):
            worst = _Corner(
                float(t[k]), float(t[first]), (last - first) * dt_s, angle, behind_m, lateness
            )
    return worst


def _course_lag(
    target_vel: np.ndarray, steady: np.ndarray, course_limit: CourseRateLimit, dt_s: float
) -> tuple[float, float]:
    """Outside corners, the longest stretch the target turns faster than r_max at its speed:
    what the reference course loses to it there [rad], and how long it lasts [s]."""
    speed = np.hypot(target_vel[:-1, 0], target_vel[:-1, 1])
    course = np.unwrap(np.arctan2(target_vel[:, 1], target_vel[:, 0]))
    rate = np.abs(np.diff(course)) / dt_s
    limit = np.array([course_limit.at(v) for v in speed.tolist()])
    excess = np.where(steady & (speed > 0.1), rate - limit, 0.0)
    best, best_for, run, run_for = 0.0, 0.0, 0.0, 0.0
    for e in excess.tolist():
        run, run_for = (run + e * dt_s, run_for + dt_s) if e > 0.0 else (0.0, 0.0)
        if run > best:
            best, best_for = run, run_for
    return best, best_for


def check_scenario(sc: Scenario) -> FeasibilityReport:
    """Feasibility report of a scenario."""
    c = sc.controller
    lines = [
        f"scenario {sc.name!r}: {len(sc.vehicles)} vehicles, M = {c.horizon}, "
        f"tau = {c.period_s} s, "
        f"U = {{0 <= V <= {c.speed_max_m_s:g} m/s, |omega| <= {c.yaw_rate_max_rad_s:g} rad/s}}"
    ]
    problems: list[str] = []
    try:
        mpc = vehicle_mpc(c, Formation(sc.formation))
    except InfeasibleError as e:
        return FeasibilityReport(False, (str(e),), (*lines, "tightened input sets: EMPTY"))
    v_bound = c.speed_max_m_s - float(mpc.tightening[-1, 0])
    w_bound = c.yaw_rate_max_rad_s - float(mpc.tightening[-1, 1])
    lines.append(
        f"tightened input sets: non-empty; at step M-1 |V| <= {v_bound:.3f} m/s, "
        f"|omega| <= {w_bound:.3f} rad/s"
    )
    t_speed = max(
        float(np.hypot(*sc.target.state_at(t)[1])) for t in np.linspace(0, sc.duration_s, 200)
    )
    lines.append(f"target speed: up to {t_speed:.3f} m/s")
    lines += wind_lines(sc)
    lines += learner_noise_lines(sc)
    course_limit = reference_course_limit(sc.controller, sc.formation)
    if isinstance(sc.target, RecordedTrack):
        more, trouble = track_lines(
            sc, sc.target, speed_bound_m_s=v_bound, course_limit=course_limit
        )
        lines += more
        problems += trouble
    needs = _slot_requirements(sc, course_limit)
    lines += _needs_lines(sc, needs, (v_bound, w_bound), t_speed, problems)
    lines += _course_lines(sc, needs, course_limit, t_speed)
    formation = Formation(sc.formation)
    lines += _neighbourhood_lines(sc, mpc, formation, problems)
    lines += _start_lines(sc, formation, course_limit, v_bound - float(needs.speeds_m_s.max()))
    return FeasibilityReport(not problems, tuple(problems), tuple(lines))


def _needs_lines(
    sc: Scenario,
    needs: _Requirements,
    bounds: tuple[float, float],
    t_speed: float,
    problems: list[str],
) -> list[str]:
    """What each vehicle's slot asks of it; a problem where that is beyond the tightened
    `bounds` (speed, yaw rate) by more than a transient."""
    v_bound, w_bound = bounds
    speeds, rates, lags = needs.speeds_m_s, needs.yaw_rates_rad_s, needs.turn_lags_m
    lines = []
    for v, sp, wr, lag in zip(sc.vehicles, speeds, rates, lags, strict=True):
        beyond = f"; beyond the bound, a heading lag worth {lag:.2f} m" if wr > w_bound else ""
        lines.append(
            f"vehicle {v.id}: slot needs airspeed up to {sp:.3f} m/s, yaw rate up to {wr:.3f} "
            f"rad/s (over {YAW_RATE_WINDOW_S:g} s{beyond})"
        )
    worst = int(np.argmax(speeds))
    if speeds[worst] > v_bound:
        problems.append(
            f"the target outruns the team: vehicle {sc.vehicles[worst].id}'s slot needs "
            f"{speeds[worst]:.2f} m/s "
            f"(target {t_speed:.2f} m/s, with turns, wind and effectiveness) "
            f"but |V| <= {sc.controller.speed_max_m_s:g} m/s "
            f"({v_bound:.2f} m/s after tube tightening); expect a growing lag"
        )
    if lags.max() > TURN_LAG_MAX_M:
        late = int(np.argmax(lags))
        problems.append(
            f"vehicle {sc.vehicles[late].id}'s slot turns at up to {rates[late]:.3f} rad/s, "
            f"beyond |omega| <= {w_bound:.3f} rad/s after tightening, at a speed where the "
            f"heading lag costs about {lags[late]:.2f} m (more than {TURN_LAG_MAX_M:g} m)"
        )
    return lines


def _course_lines(
    sc: Scenario, needs: _Requirements, course_limit: CourseRateLimit, t_speed: float
) -> list[str]:
    """Where the reference course falls behind the target's, and how the formation goes round
    each of its corners."""
    lines = []
    if needs.course_lag_rad > COURSE_LAG_REPORT_RAD:
        lines.append(
            f"reference course: for {needs.course_lag_for_s:.0f} s the target turns faster than "
            f"the formation may (r_max, {course_limit.at(t_speed):.3f} rad/s at "
            f"{t_speed:.2f} m/s): the formation's course falls up to "
            f"{math.degrees(needs.course_lag_rad):.0f} deg behind the target's"
        )
    for corner in needs.corners:
        sweep = "a world-frame formation does not turn"
        if sc.formation.frame == "course":
            speed = float(np.hypot(*sc.target.state_at(corner.target_s)[1]))
            sweep = f"the formation itself sweeps round at {course_limit.at(speed):.3f} rad/s"
        back = (
            f"back on its slot about {corner.back_s:.0f} s after the target's corner"
            if math.isfinite(corner.back_s)
            else "no spare speed to catch up"
        )
        lines.append(
            f"corner at t = {corner.target_s:.1f} s: the formation's centre goes round it from "
            f"t = {corner.start_s:.1f} s for {corner.duration_s:.1f} s; a slot's velocity turns "
            f"{math.degrees(corner.turn_rad):.0f} deg, its vehicle falls up to about "
            f"{corner.behind_m:.1f} m behind, {back} ({sweep})"
        )
    return lines


def _neighbourhood_lines(
    sc: Scenario, mpc: TubeLbmpc, formation: Formation, problems: list[str]
) -> list[str]:
    """How many neighbours a vehicle keeps its separation against, and the closest slots'
    slack; a problem where a slot has more of them within the safety radius than it keeps."""
    c = sc.controller
    radius = safety_radius(c, float(mpc.tube_radius_m[-1]))
    within = (formation.desired_distances() <= radius).sum(axis=1) - 1  # (not itself)
    crowded = int(np.argmax(within))
    lines = [
        f"neighbourhood: separation against at most K = {mpc.n_neighbours} vehicles within the"
        f" safety radius {radius:.2f} m; up to {within[crowded]} other slots lie within it of a"
        " slot"
    ]
    lines += _slack_lines(sc, formation, float(mpc.tube_radius_m[-1]), problems)
    if within[crowded] > mpc.n_neighbours:
        problems.append(
            f"vehicle {sc.vehicles[crowded].id}'s slot has {within[crowded]} other slots within"
            f" the safety radius {radius:.2f} m, more than controller.neighbours_max ="
            f" {c.neighbours_max}: the farthest of them would get no separation constraint;"
            f" raise controller.neighbours_max to {within[crowded]} or space the formation out"
        )
    return lines


def _start_lines(
    sc: Scenario, formation: Formation, course_limit: CourseRateLimit, spare: float
) -> list[str]:
    """How far the horizon reaches, and how long the worst gap between a vehicle and its slot
    at the start takes to close at the `spare` speed [m/s]."""
    c = sc.controller
    reach = c.horizon * c.period_s * c.speed_max_m_s
    p0, v0 = sc.target.state_at(0.0)
    centre0, course0 = true_reference(formation, course_limit, p0[None, :], v0[None, :], 1.0)
    slots0 = formation.slots(centre0, course0)[0]
    gap = max(
        math.hypot(v.initial[0] - s[0], v.initial[1] - s[1])
        for v, s in zip(sc.vehicles, slots0, strict=True)
    )
    lines = [f"horizon reach: {reach:.2f} m in {c.horizon * c.period_s:.2f} s at full speed"]
    if spare > 0:
        lines.append(
            f"worst initial gap {gap:.2f} m closes in about {gap / spare:.1f} s "
            f"at the spare {spare:.2f} m/s"
        )
    else:
        lines.append(f"worst initial gap {gap:.2f} m cannot close: no spare speed")
    return lines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario TOML file")


def run(args: argparse.Namespace) -> int:
    report = check_scenario(load_scenario(args.scenario))
    print(report.render())
    return 0 if report.feasible else 1


def _slack_lines(
    sc: Scenario, formation: Formation, tube_radius_m: float, problems: list[str]
) -> list[str]:
    """How far each vehicle of the closest pair of slots is from its separation margin there
    (docs/design.md, "What the lines leave a compact formation"); a problem if negative."""
    if len(sc.vehicles) < 2:
        return []
    a, b, apart, slack = _closest_slack(sc, formation, tube_radius_m)
    keeps = apart - 2.0 * slack
    if slack < 0.0:
        problems.append(
            f"the slots of vehicles {sc.vehicles[a].id} and {sc.vehicles[b].id} are "
            f"{apart:.2f} m apart, closer than a pair keeps ({keeps:.2f} m: d_safe_m, the "
            f"inter-sample allowance and the tube): they can never both be on their slots"
        )
    return [
        f"separation: the closest slots, {apart:.2f} m apart, leave each vehicle {slack:.2f} m"
        f" to its margin (a pair keeps {keeps:.2f} m): how far either may stray toward the other"
        " from its slot"
    ]


def _closest_slack(
    sc: Scenario, formation: Formation, tube_radius_m: float
) -> tuple[int, int, float, float]:
    """(a, b, distance, slack): the closest pair of slots (fleet indices), how far apart they
    are [m], and how far each vehicle on its slot is from its separation margin toward the
    other [m] (inf for a lone vehicle)."""
    if len(sc.vehicles) < 2:
        return 0, 0, math.inf, math.inf
    keeps = 2.0 * shared_margin_m(sc.controller, tube_radius_m)
    a, b, apart = formation.closest_slots()
    return a, b, apart, 0.5 * (apart - keeps)
