"""A bad source's fixes are rejected, each with a line naming its fault, and counted; good ones
are placed about home and stamped on fleet time (`fleetmpc.targets.pipeline`)."""

import math

import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.local_frame import geodetic_from_ned
from fleetmpc.targets.fix import Fix
from fleetmpc.targets.pipeline import RESTART_AFTER, ObservationPipeline
from fleetmpc.targets.screen import ScreenLimits

HOME = (47.397742, 8.545594)


def _fix(t_s: float, north_m: float, east_m: float, *, system_id: int = 4) -> Fix:
    lat, lon = geodetic_from_ned(north_m, east_m, home_lat_deg=HOME[0], home_lon_deg=HOME[1])
    return Fix(system_id, t_s, lat, lon, (1.0, 0.0), "GLOBAL_POSITION_INT")


def _pipeline() -> ObservationPipeline:
    return ObservationPipeline(
        home_lat_deg=HOME[0], home_lon_deg=HOME[1], limits=ScreenLimits(system_id=4), noise_m=0.3
    )


def _warm(p: ObservationPipeline, n: int = 10) -> None:
    """n good fixes at 5 Hz, the source's clock 100 s ahead of fleet time, 30 ms of delay."""
    for k in range(n):
        assert p.take(_fix(100.0 + 0.2 * k, 0.2 * k, 5.0), 0.2 * k + 0.03) is not None


def test_good_fixes_are_placed_about_home_and_stamped_on_fleet_time():
    p = _pipeline()
    _warm(p)
    obs = p.take(_fix(102.0, 2.0, 5.0), 2.05)
    assert (obs.north_m, obs.east_m) == pytest.approx((2.0, 5.0), abs=0.01)
    assert obs.stamp_ns * 1e-9 == pytest.approx(2.03, abs=1e-6)  # (the least-delayed fix's delay)
    assert obs.velocity_m_s == (1.0, 0.0) and obs.noise_std_m == 0.3
    assert p.screen.accepted == 11 and sum(p.screen.rejected.values()) == 0


@pytest.mark.parametrize(
    ("fix", "fault", "named"),
    [
        (_fix(102.0, 2.0, 5.0, system_id=7), "wrong system", "following system 4"),
        (Fix(4, 102.0, math.nan, HOME[1], None, "GLOBAL_POSITION_INT"), "not a number", "lat nan"),
        (Fix(4, 102.0, HOME[0], HOME[1], (math.inf, 0.0), "FOLLOW_TARGET"), "not a number", "inf"),
        (_fix(101.8, 2.0, 5.0), "repeat", "the same time"),
        (_fix(101.0, 2.0, 5.0), "backwards", "0.800 s before"),
        (_fix(160.0, 2.0, 5.0), "future", "ahead of fleet time"),
        (_fix(102.0, 100_000.0, 0.0), "too far", "100.0 km from home"),
        (_fix(102.0, 40.0, 5.0), "jump", "m in 0.200 s"),
    ],
)
def test_a_bad_fix_is_rejected_named_and_counted(fix, fault, named):
    p = _pipeline()
    _warm(p)
    assert p.take(fix, 2.05) is None
    assert p.screen.rejected[fault] == 1 and sum(p.screen.rejected.values()) == 1
    (line,) = p.log
    assert line.startswith(f"rejected ({fault}): system {fix.system_id}") and named in line
    assert p.take(_fix(102.2, 2.2, 5.0), 2.25) is not None  # (and the source goes on)


def test_a_restarted_source_clock_is_estimated_afresh():
    p = _pipeline()
    _warm(p)
    for k in range(RESTART_AFTER):  # (the source rebooted: its time since boot starts again)
        assert p.take(_fix(1.0 + 0.2 * k, 2.0 + 0.2 * k, 5.0), 2.03 + 0.2 * k) is None
    assert p.screen.rejected["backwards"] == RESTART_AFTER
    assert "restarted" in p.log[-1]
    obs = p.take(_fix(1.0 + 0.2 * RESTART_AFTER, 4.0, 5.0), 4.03)
    assert obs is not None and obs.stamp_ns * 1e-9 == pytest.approx(4.03)


def test_a_wrong_system_id_to_follow_is_refused():
    with pytest.raises(ConfigError, match="sysid"):
        ScreenLimits(system_id=0)


def test_a_source_clock_that_jumps_ahead_is_estimated_afresh():
    p = _pipeline()
    _warm(p)
    for k in range(RESTART_AFTER):  # (its clock jumped 60 s ahead, and stays so)
        assert p.take(_fix(162.0 + 0.2 * k, 2.0 + 0.2 * k, 5.0), 2.03 + 0.2 * k) is None
    assert p.screen.rejected["future"] == RESTART_AFTER and "ahead" in p.log[-1]
    obs = p.take(_fix(162.0 + 0.2 * RESTART_AFTER, 4.0, 5.0), 4.03)
    assert obs is not None and obs.stamp_ns * 1e-9 == pytest.approx(4.03)
