"""`fleetmpc check SCENARIO`: can this fleet do what the scenario asks, before anything flies?

Checks, each reported with its numbers:
- the tube-tightened input sets U ⊖ K R_j are non-empty (else the controller cannot start);
- speed: every slot's required airspeed over the run (target motion, the outer vehicle's extra
  speed in turns, and the wind and effectiveness the scenario's truth states) fits inside the
  tightened speed bound — otherwise the target outruns the team;
- turn rate: every slot's required yaw rate fits inside the tightened yaw-rate bound;
- horizon reach: how far a vehicle can close on its slot in one horizon, and how long the worst
  initial gap takes to close at the spare speed.
"""

import argparse
import math
from dataclasses import dataclass

import numpy as np

from onboard.core.errors import InfeasibleError
from onboard.core.formation import Formation
from onboard.core.lbmpc import TubeLbmpc
from protocol.scenario import Scenario, load_scenario

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


def _slot_requirements(sc: Scenario, dt_s: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Peak required airspeed [m/s] and yaw rate [rad/s] of each vehicle's slot over the run."""
    t = np.arange(0.0, sc.duration_s + dt_s, dt_s)
    formation = Formation(sc.formation)
    slots = np.array(
        [
            formation.slots(sc.target.state_at(ti)[0][None, :], sc.target.state_at(ti)[1])[0]
            for ti in t
        ]
    )
    vel = np.gradient(slots, dt_s, axis=0)  # (K, N, 2)
    speeds, rates = [], []
    for i, v in enumerate(sc.vehicles):
        wind = np.array([v.truth.wind.at(ti) for ti in t])
        air = (vel[:, i] - wind) / v.truth.speed_effectiveness
        speeds.append(float(np.max(np.hypot(air[:, 0], air[:, 1]))))
        heading = np.unwrap(np.arctan2(air[:, 1], air[:, 0]))
        rate = np.abs(np.gradient(heading, dt_s)) / v.truth.yaw_rate_effectiveness
        moving = np.hypot(air[:, 0], air[:, 1]) > 0.1
        rates.append(float(np.max(rate[moving])) if moving.any() else 0.0)
    return np.array(speeds), np.array(rates)


def check_scenario(sc: Scenario) -> FeasibilityReport:
    """Feasibility report of a scenario."""
    c = sc.controller
    lines = [
        f"scenario {sc.name!r}: {len(sc.vehicles)} vehicles, M = {c.horizon}, "
        f"tau = {c.period_s} s, "
        f"U = {{|V| <= {c.speed_max_m_s:g} m/s, |omega| <= {c.yaw_rate_max_rad_s:g} rad/s}}"
    ]
    problems: list[str] = []
    try:
        mpc = TubeLbmpc(c, n_neighbours=len(sc.vehicles) - 1)
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
    speeds, rates = _slot_requirements(sc)
    for v, sp, wr in zip(sc.vehicles, speeds, rates, strict=True):
        lines.append(
            f"vehicle {v.id}: slot needs airspeed up to {sp:.3f} m/s, yaw rate up to {wr:.3f} rad/s"
        )
    worst = int(np.argmax(speeds))
    if speeds[worst] > v_bound:
        problems.append(
            f"the target outruns the team: vehicle {sc.vehicles[worst].id}'s slot needs "
            f"{speeds[worst]:.2f} m/s "
            f"(target {t_speed:.2f} m/s, with turns, wind and effectiveness) "
            f"but |V| <= {c.speed_max_m_s:g} m/s "
            f"({v_bound:.2f} m/s after tube tightening); expect a growing lag"
        )
    if rates.max() > w_bound:
        problems.append(
            f"vehicle {sc.vehicles[int(np.argmax(rates))].id}'s slot turns at "
            f"{rates.max():.3f} rad/s, "
            f"beyond |omega| <= {w_bound:.3f} rad/s after tightening"
        )
    spare = v_bound - float(speeds.max())
    reach = c.horizon * c.period_s * c.speed_max_m_s
    formation = Formation(sc.formation)
    p0, v0 = sc.target.state_at(0.0)
    slots0 = formation.slots(p0[None, :], v0)[0]
    gaps = [
        math.hypot(v.initial[0] - s[0], v.initial[1] - s[1])
        for v, s in zip(sc.vehicles, slots0, strict=True)
    ]
    lines.append(f"horizon reach: {reach:.2f} m in {c.horizon * c.period_s:.2f} s at full speed")
    if spare > 0:
        lines.append(
            f"worst initial gap {max(gaps):.2f} m closes in about {max(gaps) / spare:.1f} s "
            f"at the spare {spare:.2f} m/s"
        )
    else:
        lines.append(f"worst initial gap {max(gaps):.2f} m cannot close: no spare speed")
    return FeasibilityReport(not problems, tuple(problems), tuple(lines))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", help="scenario TOML file")


def run(args: argparse.Namespace) -> int:
    report = check_scenario(load_scenario(args.scenario))
    print(report.render())
    return 0 if report.feasible else 1
