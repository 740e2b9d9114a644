"""Simulated time: integer nanoseconds, scaled wall time or a manual clock."""

import pytest

from fleetmpc.clock import Clock, FleetClock, ManualClock, RealTimeClock
from fleetmpc.errors import ConfigError


def test_manual_clock_moves_only_when_told():
    clock: Clock = ManualClock(start_ns=5)
    assert clock.now_ns() == 5 and clock.now_ns() == 5
    assert clock.advance(20_000_000) == 20_000_005
    assert clock.wall_seconds(10**9) == 0.0
    with pytest.raises(ValueError):
        clock.advance(-1)


@pytest.mark.parametrize("speed", [0.5, 1.0, 4.0, 0.3])
def test_real_time_clock_is_integer_monotonic_and_scaled(speed):
    clock: Clock = RealTimeClock(speed=speed)
    readings = [clock.now_ns() for _ in range(1000)]
    assert all(isinstance(t, int) for t in readings)
    assert readings == sorted(readings) and readings[0] >= 0
    assert clock.wall_seconds(2_000_000_000) == pytest.approx(2.0 / speed)
    assert clock.wall_seconds(-5) == 0.0


@pytest.mark.parametrize("speed", [0.0, -1.0, float("nan"), float("inf"), 1e6, "4"])
def test_bad_speeds_are_refused(speed):
    with pytest.raises(ConfigError, match="speed"):
        RealTimeClock(speed=speed)


def test_a_host_offset_moves_fleet_time_by_the_offset_times_the_speed():
    clock = FleetClock(epoch_ns=1_000, speed=4.0, host_offset_ns=300)
    assert clock.fleet_ns(2_000) == round((2_000 + 300 - 1_000) * 4.0)
    with pytest.raises(ConfigError, match="host_offset_ns"):
        FleetClock(host_offset_ns=0.5)
