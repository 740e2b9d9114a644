"""A vehicle's neighbourhood: plan ages, the formation graph, the safety radius and its cap K."""

import math

import numpy as np
import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.onboard.core.config import ControllerSettings, FormationSettings
from fleetmpc.onboard.core.formation import Formation
from fleetmpc.onboard.core.neighbourhood import Neighbourhood
from fleetmpc.protocol.plan import Plan
from fleetmpc.scenario import pattern_slots

SETTINGS = ControllerSettings()
PERIOD_NS = SETTINGS.period_ns
M = SETTINGS.horizon
NOW = 20 * 10**9


def _plan(vehicle_id: int, stamp_ns: int, x: float, y: float = 10.0) -> Plan:
    states = np.array([(x + 0.2 * j, y, 0.0) for j in range(M + 1)])
    return Plan(vehicle_id, stamp_ns, PERIOD_NS, states, np.tile((1.0, 0.0), (M, 1)))


def _hood(fleet_ids: tuple[int, ...], settings: ControllerSettings = SETTINGS) -> Neighbourhood:
    return Neighbourhood(
        fleet_ids=fleet_ids,
        formation_links=tuple(range(1, len(fleet_ids))),
        controller=settings,
        tube_radius_m=0.1,
    )


def _inflation(age_s: float) -> float:
    inflations = _hood((1, 2)).inflations({2: age_s}, 0.0)
    return inflations.get(2, math.inf)


def test_a_plan_stamped_in_the_future_is_kept_without_inflation():
    assert _inflation(-0.5) == 0.0  # a clock 0.5 s fast: kept, as fresh
    assert _inflation(0.2) == 0.0
    assert _inflation(0.9) == pytest.approx(SETTINGS.speed_max_m_s * 0.7)


def test_a_plan_beyond_the_forget_age_either_way_is_ignored():
    assert math.isinf(_inflation(SETTINGS.plan_forget_s + 1.0))
    assert math.isinf(_inflation(-SETTINGS.plan_forget_s - 1.0))


def test_a_late_step_inflates_every_neighbour_by_v_max_times_its_lateness():
    inflations = _hood((1, 2, 3, 4)).inflations({2: 0.2, 3: 0.9, 4: 3.0}, 0.5)
    assert inflations[2] == pytest.approx(SETTINGS.speed_max_m_s * 0.5)
    assert inflations[3] == pytest.approx(SETTINGS.speed_max_m_s * 1.2)
    assert inflations[4] == pytest.approx(SETTINGS.speed_max_m_s * 0.5)  # silent: its region


def test_the_safety_radius_covers_both_vehicles_closing_at_v_max_over_the_horizon():
    hood = _hood((1, 2))
    closing = 2.0 * SETTINGS.speed_max_m_s * (M + 1) * SETTINGS.period_s
    assert hood.radius_m >= SETTINGS.d_safe_m + closing


def test_only_vehicles_within_the_radius_are_planned_against_nearest_first_at_most_k():
    settings = ControllerSettings(neighbours_max=3)
    ids = tuple(range(1, 8))
    hood = _hood(ids, settings)
    r = hood.radius_m
    gaps = {2: 0.5 * r, 3: 0.9 * r, 4: 0.3 * r, 5: 1.1 * r, 6: 3.0 * r, 7: 0.99 * r}
    plans = {k: _plan(k, NOW, gap, 0.0) for k, gap in gaps.items()}
    inflations = hood.inflations(dict.fromkeys(gaps, 0.2), 0.0)
    ages = dict.fromkeys(gaps, 0.2)
    near = hood.nearest(NOW, plans, (0.0, 0.0), inflations, ages, (0.0, 0.0), [])
    assert list(near) == [4, 2, 3]  # within the radius: 4, 2, 3, 7; K = 3 keeps the nearest 3
    assert near[4] == pytest.approx((gaps[4], 0.0))  # (each where its plan puts it)
    assert hood.crowded == 1
    planes, _ = hood.planes(NOW, near, plans, None, (0.0, 0.0), (0.0, 0.0), ages, inflations)
    assert len(planes) == hood.size == 3
    assert all(math.isfinite(p[0][2]) for p in planes)


def test_a_stale_plans_inflation_brings_its_vehicle_into_the_radius():
    hood = _hood((1, 2))
    far = hood.radius_m + 1.0
    plans = {2: _plan(2, NOW, far, 0.0)}
    fresh = hood.inflations({2: 0.2}, 0.0)
    stale = hood.inflations({2: 0.9}, 0.0)  # 0.9 s old: it may be 1.4 m nearer
    assert list(hood.nearest(NOW, plans, (0.0, 0.0), fresh, {2: 0.2}, (0.0, 0.0), [])) == []
    assert list(hood.nearest(NOW, plans, (0.0, 0.0), stale, {2: 0.9}, (0.0, 0.0), [])) == [2]


def test_a_silent_neighbour_is_kept_clear_of_between_its_last_plan_and_its_slot():
    """Heard no more (its plan older than plan_stale_s), a neighbour is somewhere between where
    its last plan put it and its slot now: the line is placed from the point of that segment
    nearest this vehicle, at the whole distance plus silent_allowance_m, with no inflation by
    its age. It is not forgotten while the agent keeps it (plan_forget_s)."""
    hood = _hood((1, 2))
    age = 5.0
    plans = {2: _plan(2, NOW - int(age * 1e9), 0.0, 10.0)}  # held at (1.6, 10) by now
    centre, offsets = (1.0, 0.0), [(7.0, 0.0), (8.0, 10.0)]  # slots (8, 0) and (9, 10)
    here = (5.0, 4.0)
    inflations = hood.inflations({2: age}, 0.0)
    assert inflations == {2: 0.0}
    near = hood.nearest(NOW, plans, here, inflations, {2: age}, centre, offsets)
    assert list(near) == [2]
    ((plane, *_), *_), _ = hood.planes(
        NOW, near, plans, None, here, (0.0, 0.0), {2: age}, inflations
    )
    nx, ny, b = plane
    assert (nx, ny) == pytest.approx((0.0, -1.0))  # from (5, 10) on the segment, toward here
    alone = 2.0 * hood.margin_m - 0.1  # d_safe + s + r_M, the tube radius being 0.1 m
    assert b - (nx * 5.0 + ny * 10.0) == pytest.approx(alone + SETTINGS.silent_allowance_m)
    assert 2 in hood.inflations({2: SETTINGS.plan_forget_s - 1.0}, 0.0)


def test_planes_are_padded_to_k_with_no_planes():
    hood = _hood((1, 2, 3, 4))
    plans = {2: _plan(2, NOW, 3.0, 0.0)}
    inflations = hood.inflations({2: 0.2}, 0.0)
    near = {2: plans[2].position_at(NOW)}
    planes, _ = hood.planes(NOW, near, plans, None, (0.0, 0.0), (0.0, 0.0), {2: 0.2}, inflations)
    assert len(planes) == 3
    assert all(math.isinf(b) for _, _, b in planes[1] + planes[2])


def test_a_vehicle_inside_its_margin_is_held_at_where_it_is_and_drawn_back_out():
    """Found 0.3 m inside its margin of a neighbour 2 m away, the vehicle's plane passes through
    where it is (it may not close further), and its goal, which lies beyond the neighbour, is
    put back on the margin's own line: the cost draws the vehicle out, where pressing it against
    the plane through where it is would keep every period's model error."""
    hood = _hood((1, 2))
    here, theirs = (0.0, 0.0), (2.0, 0.0)
    near, plans = {2: theirs}, {2: _held(2, NOW, *theirs)}
    inflations = hood.inflations({2: 0.2}, 0.0)
    planes, lines = hood.planes(NOW, near, plans, None, here, (0.0, 0.0), {2: 0.2}, inflations)
    (nx, ny, b), line = planes[0][0], lines[0][0]
    assert (nx, ny) == pytest.approx((-1.0, 0.0))
    assert b == pytest.approx(0.0)  # through where it is
    assert line[2] == pytest.approx(-(1.0 - hood.margin_m))  # the margin's line, x = 1 - margin
    goal = [(3.0, 0.5 * j) for j in range(M)]  # beyond the neighbour
    drawn = hood.draw_out(goal, lines)
    expected = [(1.0 - hood.margin_m, 0.5 * j) for j in range(M)]
    assert np.array(drawn) == pytest.approx(np.array(expected))
    behind = [(-3.0, 1.0)] * M  # already on its side: untouched
    assert hood.draw_out(behind, lines) == behind


def test_the_formation_graph_links_each_grid_slot_to_its_eight_nearest():
    slots = tuple(pattern_slots("grid", 25, 5.0, 5))
    shape = Formation(FormationSettings(slots_m=slots))
    centre = 12  # the middle of the 5 x 5 grid: its 8 surrounding slots
    assert shape.links[centre] == (6, 7, 8, 11, 13, 16, 17, 18)
    assert {1, 5, 6} <= set(shape.links[0])  # a corner: its three neighbours among them
    assert all(len(linked) == 8 and i not in linked for i, linked in enumerate(shape.links))
    assert shape.max_degree == 8


def test_a_small_formation_is_linked_all_to_all():
    shape = Formation(FormationSettings(slots_m=((0.0, 0.0), (5.0, 0.0), (0.0, 5.0))))
    assert shape.links == ((1, 2), (0, 2), (0, 1))


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: ControllerSettings(neighbours_max=0), "controller.neighbours_max"),
        (lambda: FormationSettings(slots_m=((0.0, 0.0),), neighbours=0), "formation.neighbours"),
    ],
)
def test_neighbourhood_settings_are_validated(make, field):
    with pytest.raises(ConfigError, match=field):
        make()


def _held(vehicle_id: int, stamp_ns: int, x: float, y: float) -> Plan:
    """What a runner broadcasts while its autopilot holds the vehicle: its pose over the horizon."""
    return Plan(vehicle_id, stamp_ns, PERIOD_NS, np.tile((x, y, 0.0), (M + 1, 1)), np.zeros((M, 2)))


def test_a_plan_that_stands_still_holds_and_a_planned_stop_in_a_wind_does_not():
    assert _held(2, NOW, 3.0, 0.0).holds
    assert not _plan(2, NOW, 3.0).holds  # moving
    drifting = np.array([(3.0 + 0.03 * j, 0.0, 0.0) for j in range(M + 1)])  # stopped, drifting
    assert not Plan(2, NOW, PERIOD_NS, drifting, np.zeros((M, 2))).holds


def _steps(plan: Plan) -> list[tuple[float, float]]:
    return plan.position_list(NOW, M + 1, max_extrapolation_s=SETTINGS.plan_extrapolation_s)


def _bisector_offset(plane, a, b) -> float:
    """How far `plane`'s boundary lies beyond the midpoint of a and b along its normal [m]."""
    nx, ny, bound = plane
    return bound - (nx * 0.5 * (a[0] + b[0]) + ny * 0.5 * (a[1] + b[1]))


def test_against_the_latest_plan_each_steps_line_bisects_where_the_plans_put_the_pair_then():
    """Against a neighbour's latest plan (a period old), the line of step j lies between where
    this vehicle's previous plan and the neighbour's put them at step j, so a formation flying
    abreast is not held back by a line that stands still (docs/design.md, "The half-planes")."""
    hood = _hood((1, 2))
    mine = _plan(1, NOW - PERIOD_NS, 0.0, 0.0)  # flying North at 1 m/s
    plans = {2: _plan(2, NOW - PERIOD_NS, 0.0, 3.0)}  # abreast, 3 m to the East
    inflations = hood.inflations({2: 0.2}, 0.0)
    here = mine.position_at(NOW)
    near = hood.nearest(NOW, plans, here, inflations, {2: 0.2}, here, [])
    drift = (0.3, 0.2)  # (not used: the plans carry it)
    planes, lines = hood.planes(NOW, near, plans, mine, here, drift, {2: 0.2}, inflations)
    assert planes == lines  # (nobody inside a margin)
    own, abreast = _steps(mine), _steps(plans[2])
    for j, plane in enumerate(planes[0]):
        assert plane[:2] == pytest.approx((0.0, -1.0))
        assert _bisector_offset(plane, own[j + 1], abreast[j + 1]) == pytest.approx(hood.margin_m)


def test_against_an_older_plan_the_line_drifts_with_the_wind_except_where_the_wind_cannot():
    """Against an older plan (or none but a silent vehicle's region) the line lies between
    where the plans put the pair now, and drifts with the learned drift, as the wind carries two
    vehicles flying velocity commands alike; a held vehicle (its plan `holds`) and a silent one
    stay where they are, and so does the line against them (docs/design.md, "Held neighbours
    do not drift")."""
    hood = _hood((1, 2, 3, 4))
    drift = (0.3, 0.2)
    plans = {
        2: _plan(2, NOW - 2 * PERIOD_NS, 3.0, 0.0),  # flying, its plan two periods old
        3: _held(3, NOW - PERIOD_NS, -3.0, 0.0),  # held by its autopilot
        4: _plan(4, NOW - 5 * 10**9, 0.0, 3.0),  # silent for 5 s
    }
    ages = {2: 0.4, 3: 0.2, 4: 5.0}
    inflations = hood.inflations(ages, 0.0)
    near = {nid: plans[nid].position_at(NOW) for nid in plans}
    planes, _ = hood.planes(NOW, near, plans, None, (0.0, 0.0), drift, ages, inflations)
    still = {3, 4}  # held, and silent
    by_id = dict(zip(sorted(near), planes, strict=True))
    for nid, lines in by_id.items():
        offsets = [b - lines[0][2] for _, _, b in lines]  # each step's bound less the first's
        nx, ny, _ = lines[0]
        moved = [nx * drift[0] * j * SETTINGS.period_s + ny * drift[1] * j * SETTINGS.period_s
                 for j in range(M)]  # fmt: skip
        expected = [0.0] * M if nid in still else moved
        assert offsets == pytest.approx(expected, abs=1e-12), nid
