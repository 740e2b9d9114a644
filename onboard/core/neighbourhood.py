"""One vehicle's neighbours as its agent sees them each period (docs/design.md, "Safety" and
"Formation reference"; the plan ages of "The plan bus").

From the neighbours' latest plans and their ages: the margin inflation of each (v_max x the age
beyond one period; a forgotten plan drops its neighbour), and where a silent one may be (between
its last plan and its slot); the formation terms of the linked vehicles (the formation graph)
whose plans are fresh, and their pull on this vehicle's goal; the nearest vehicles within the
safety radius, at most K (a neighbourhood whose size does not grow with the fleet), and the
separation half-planes against each (`fleetmpc.onboard.core.separation` places them), the
give-way rule that breaks a deadlock between two vehicles stopped nose to nose, and the goal
kept in the vehicle's own cell. Plain floats throughout: the horizon is a handful of points.
"""

import math
from collections.abc import Mapping

from fleetmpc.onboard.core.config import ControllerSettings
from fleetmpc.onboard.core.separation import (
    NO_PLANE,
    Plane,
    held_inside,
    intersample_allowance,
    separation_lines,
)
from fleetmpc.protocol.plan import Plan

__all__ = ["Neighbourhood", "safety_radius", "shared_margin_m"]


def shared_margin_m(controller: ControllerSettings, tube_radius_m: float) -> float:
    """Distance a vehicle keeps from a line it shares with a fresh neighbour, before the
    plan-age inflation: half of d_safe and the inter-sample allowance, and its tube's widest
    radius (`fleetmpc.onboard.core.separation`) [m]. A pair keeps twice this apart."""
    between = intersample_allowance(
        speed_max_m_s=controller.speed_max_m_s,
        period_s=controller.period_s,
        d_safe_m=controller.d_safe_m,
    )
    return 0.5 * (controller.d_safe_m + between) + tube_radius_m


def safety_radius(controller: ControllerSettings, tube_radius_m: float) -> float:
    """R [m]: a vehicle farther than this cannot come within the alone margin (d_safe, the
    inter-sample allowance and the tube) of this one before the end of the horizon and the next
    period's choice, both flying at v_max toward each other, each within the tube of its
    prediction (docs/design.md, "Safety")."""
    between = intersample_allowance(
        speed_max_m_s=controller.speed_max_m_s,
        period_s=controller.period_s,
        d_safe_m=controller.d_safe_m,
    )
    closing = 2.0 * controller.speed_max_m_s * (controller.horizon + 1) * controller.period_s
    return controller.d_safe_m + between + 2.0 * tube_radius_m + closing


def _carried(
    point: tuple[float, float], drift: tuple[float, float], period_s: float, horizon: int
) -> list[tuple[float, float]]:
    """`point` carried by `drift` at j = 0..horizon."""
    (x, y), (dx, dy) = point, drift
    return [(x + dx * j * period_s, y + dy * j * period_s) for j in range(horizon + 1)]


class Neighbourhood:
    """A vehicle's neighbours in the fleet `fleet_ids` (its own id among them): the vehicles it
    is linked to in the formation graph (`formation_links`, fleet indices), whose plans pull its
    goal, and the nearest vehicles within its safety radius, at most `controller.neighbours_max`,
    whose plans bound it. `tube_radius_m` (the tube's widest position radius) widens every
    separation margin."""

    def __init__(
        self,
        *,
        fleet_ids: tuple[int, ...],
        formation_links: tuple[int, ...],
        controller: ControllerSettings,
        tube_radius_m: float,
    ) -> None:
        self.settings = controller
        self.formation_ids = tuple(fleet_ids[k] for k in formation_links)
        """The vehicles whose slots this vehicle's slot is linked to."""
        self.size = min(controller.neighbours_max, len(fleet_ids) - 1)
        """K: how many neighbours the QP has separation rows for."""
        M = controller.horizon
        self._no_planes = [NO_PLANE] * M
        between = intersample_allowance(
            speed_max_m_s=controller.speed_max_m_s,
            period_s=controller.period_s,
            d_safe_m=controller.d_safe_m,
        )
        self.margin_m = shared_margin_m(controller, tube_radius_m)
        """Distance kept from a shared separation line before the plan-age inflation [m]."""
        self._alone_margin_m = controller.d_safe_m + between + tube_radius_m
        """Distance kept from a stale neighbour's position before the plan-age inflation [m]."""
        self.radius_m = safety_radius(controller, tube_radius_m)
        """The safety radius (`safety_radius`), which a vehicle's distance less its plan's
        inflation must be within for it to be planned against."""
        self._fleet_index = {vid: i for i, vid in enumerate(fleet_ids)}
        self.crowded = 0
        """Periods in which more than K vehicles were within the safety radius (the farthest
        of them were left out)."""

    def inflations(self, ages: Mapping[int, float], late_s: float) -> dict[int, float]:
        """The margin inflation of each neighbour (by its plan's age, `ages` holding only the
        fleet's other vehicles) whose plan is not forgotten [m]: v_max x (its plan's age beyond
        one period, plus how late this step runs); for a silent one (`silent`) only the
        lateness, its region standing for its age."""
        s = self.settings
        return {
            nid: s.speed_max_m_s
            * (late_s + (0.0 if self.silent(age) else max(0.0, age - s.period_s)))
            for nid, age in ages.items()
            if abs(age) <= s.plan_forget_s
        }

    def silent(self, age_s: float) -> bool:
        """True for a neighbour whose plan is older than plan_stale_s: it is heard no more."""
        return age_s > self.settings.plan_stale_s

    def _closest(
        self,
        nid: int,
        stamp_ns: int,
        neighbour_plans: Mapping[int, Plan],
        ages: Mapping[int, float],
        centre: tuple[float, float],
        offsets: list[tuple[float, float]],
        here: tuple[float, float],
    ) -> tuple[float, float]:
        """Where a neighbour may be that is closest to `here`: its plan's position now, or for a
        silent one the point nearest `here` of the segment from there to its slot now (`centre`
        plus its entry of `offsets`, the formation's now; docs/design.md, "Silent
        neighbours")."""
        held = neighbour_plans[nid].position_at(stamp_ns)
        if not self.silent(ages[nid]):
            return held
        ox, oy = offsets[self._fleet_index[nid]]
        (ax, ay), (bx, by) = held, (centre[0] + ox, centre[1] + oy)
        dx, dy = bx - ax, by - ay
        length2 = dx * dx + dy * dy
        if length2 < 1e-12:
            return held
        t = ((here[0] - ax) * dx + (here[1] - ay) * dy) / length2
        t = 0.0 if t < 0.0 else min(t, 1.0)
        return ax + t * dx, ay + t * dy

    def nearest(
        self,
        stamp_ns: int,
        neighbour_plans: Mapping[int, Plan],
        here: tuple[float, float],
        inflations: Mapping[int, float],
        ages: Mapping[int, float],
        centre: tuple[float, float],
        offsets: list[tuple[float, float]],
    ) -> dict[int, tuple[float, float]]:
        """The vehicles within the safety radius of `here`, nearest first (by distance less
        inflation, then id), at most K of them, each with where it is taken to be (`_closest`);
        `centre` and `offsets` place the formation's slots now."""
        hx, hy = here
        near = []
        for nid, inflation in inflations.items():
            px, py = self._closest(nid, stamp_ns, neighbour_plans, ages, centre, offsets, here)
            gap = math.hypot(px - hx, py - hy) - inflation
            if gap <= self.radius_m:
                near.append((gap, nid, (px, py)))
        near.sort()
        if len(near) > self.size:
            self.crowded += 1
        return {nid: position for _, nid, position in near[: self.size]}

    def pull(
        self,
        stamp_ns: int,
        neighbour_plans: Mapping[int, Plan],
        ages: Mapping[int, float],
        centres: list[tuple[float, float]],
        offsets: list[list[tuple[float, float]]],
    ) -> tuple[list[tuple[float, float]] | None, int]:
        """The formation neighbours' pull on this vehicle's goal: sum_k (p_kj - slot_kj) at
        j = 1..M over the linked vehicles whose plan is fresh (None if there is none), and their
        count. `centres` and `offsets` are the formation's centre and every vehicle's offset at
        j = 0..M+1."""
        s, M = self.settings, self.settings.horizon
        pull: list[tuple[float, float]] | None = None
        n_terms = 0
        steps = list(zip(centres[1 : M + 1], offsets[1 : M + 1], strict=True))
        for nid in self.formation_ids:
            plan, age = neighbour_plans.get(nid), ages.get(nid, math.inf)
            if plan is None or abs(age) > s.plan_forget_s or age > s.plan_stale_s:
                continue
            positions = plan.position_list(
                stamp_ns + s.period_ns, M, max_extrapolation_s=s.plan_extrapolation_s
            )
            k = self._fleet_index[nid]
            terms = [
                (px - (cx + o[k][0]), py - (cy + o[k][1]))
                for (px, py), ((cx, cy), o) in zip(positions, steps, strict=True)
            ]
            pull = (
                terms
                if pull is None
                else [(a + b, c + d) for (a, c), (b, d) in zip(pull, terms, strict=True)]
            )
            n_terms += 1
        return pull, n_terms

    def planes(
        self,
        stamp_ns: int,
        neighbours: Mapping[int, tuple[float, float]],
        neighbour_plans: Mapping[int, Plan],
        last_plan: Plan | None,
        here: tuple[float, float],
        drift: tuple[float, float],
        ages: Mapping[int, float],
        inflations: Mapping[int, float],
    ) -> tuple[list[list[Plane]], list[list[Plane]]]:
        """Separation half-planes against each of `neighbours` at j = 1..M (`separation_lines`,
        `held_inside`). Against a neighbour whose plan is the latest (at most a period old),
        each step's line lies between where this vehicle's previous plan `last_plan` (or,
        without one, the vehicle) and the neighbour's plan put them then. Against an older
        plan, the line lies between where they put them now, and drifts with `drift` as the
        wind carries both vehicles, except against a neighbour the wind does not carry: a
        silent one (taken to be at the point of its region nearest this vehicle, `nearest`,
        and kept silent_allowance_m farther from) and one whose plan `holds`. The distance is
        shared while the neighbour's plan is at most two periods old. Padded to K neighbours
        with no planes. With them, the margins' own lines (the same where the vehicle is not
        inside its margin), which `draw_out` keeps the goal behind."""
        s, M = self.settings, self.settings.horizon
        own = self._steps(last_plan, stamp_ns) if last_plan is not None else [here] * (M + 1)
        planes, lines = [], []
        for nid in sorted(neighbours, key=self._fleet_index.__getitem__):  # (in fleet order)
            age, plan = ages[nid], neighbour_plans[nid]
            shared = age <= 2.0 * s.period_s + 1e-9
            margin = (self.margin_m if shared else self._alone_margin_m) + inflations[nid]
            if self.silent(age):
                margin += s.silent_allowance_m
            if age <= s.period_s + 1e-9 and not plan.holds:
                mine, theirs = own, self._steps(plan, stamp_ns)
            else:
                carried = (0.0, 0.0) if self.silent(age) or plan.holds else drift
                mine, theirs = (
                    _carried(p, carried, s.period_s, M) for p in (own[0], neighbours[nid])
                )
            steps = separation_lines(mine, theirs, margin, here, shared=shared)
            lines.append(steps[1:])
            planes.append(held_inside(steps, here))
        planes.extend([self._no_planes] * (self.size - len(planes)))
        lines.extend([self._no_planes] * (self.size - len(lines)))
        return planes, lines

    def _steps(self, plan: Plan, stamp_ns: int) -> list[tuple[float, float]]:
        """Where `plan` puts its vehicle at j = 0..M from `stamp_ns`, extrapolated past its end
        as every vehicle extrapolates it (plan_extrapolation_s)."""
        s = self.settings
        return plan.position_list(
            stamp_ns, s.horizon + 1, max_extrapolation_s=s.plan_extrapolation_s
        )

    @staticmethod
    def draw_out(
        goal: list[tuple[float, float]], lines: list[list[Plane]]
    ) -> list[tuple[float, float]]:
        """The goal kept on this vehicle's side of every margin line (`planes`' second list):
        each goal point beyond a line is moved onto it, along its normal, so the cost draws a
        vehicle found inside its margin back out instead of pressing it against the line
        through where it is (where each period's model error would be kept)."""
        out = []
        for j, (x, y) in enumerate(goal):
            for line in lines:
                nx, ny, b = line[j]
                if not math.isfinite(b):
                    continue
                short = b - (nx * x + ny * y)
                if short > 0.0:
                    x, y = x + short * nx, y + short * ny
            out.append((x, y))
        return out

    def goal(
        self,
        slots: list[tuple[float, float]],
        pull: list[tuple[float, float]] | None,
        n_terms: int,
        weight: float,
    ) -> list[tuple[float, float]]:
        """Position targets at j = 1..M: the slot pulled toward where the neighbours' plans put
        it, (q_p slot + q_f (n slot + pull)) / (q_p + n q_f)."""
        q_p, q_f = self.settings.q_position, self.settings.q_formation
        if pull is None:
            return [(q_p * x / weight, q_p * y / weight) for x, y in slots]
        return [
            (
                (q_p * x + q_f * (n_terms * x + px)) / weight,
                (q_p * y + q_f * (n_terms * y + py)) / weight,
            )
            for (x, y), (px, py) in zip(slots, pull, strict=True)
        ]

    def give_way(
        self,
        goal: list[tuple[float, float]],
        planes: list[list[Plane]],
        here: tuple[float, float],
        speed_now_m_s: float,
    ) -> list[tuple[float, float]]:
        """The goal moved to the right of every neighbour it lies behind: the rule of the road
        that breaks a deadlock.

        Two vehicles whose goals lie beyond each other's separation lines would stop nose to
        nose, each holding its side. When the vehicle has (nearly) stopped (commanded slower than
        min_linearization_speed_m_s), its goal's last point lies beyond a neighbour's line and
        it is within its margin of that line, every goal point moves along the line, to the
        right of the way toward the neighbour, by twice the margin; both vehicles do so, each to
        its own right, and they slide past each other as two ships keep to starboard.
        """
        if speed_now_m_s >= self.settings.min_linearization_speed_m_s:
            return goal  # (still under way: not stuck)
        shift_x = shift_y = 0.0
        (gx, gy), (hx, hy) = goal[-1], here
        for plane in planes:
            nx, ny, b = plane[-1]
            if not math.isfinite(b):
                continue
            beyond = nx * gx + ny * gy < b
            pressed = nx * hx + ny * hy - b < self.margin_m
            if beyond and pressed:
                # Toward the neighbour is -n; its right (NED: a positive rotation) is (n_y, -n_x).
                shift_x += 2.0 * self.margin_m * ny
                shift_y -= 2.0 * self.margin_m * nx
        if shift_x == shift_y == 0.0:
            return goal
        return [(x + shift_x, y + shift_y) for x, y in goal]
