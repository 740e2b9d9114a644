"""A source's clock mapped onto fleet time: offset and drift recovered from arrival times."""

import numpy as np
import pytest

from fleetmpc.targets.clock_map import DRIFT_SPAN_S, SourceClock


def test_offset_and_drift_are_recovered_under_random_delays():
    rng = np.random.default_rng(1)
    clock = SourceClock()
    offset_s, drift = -3456.789, 200e-6  # (the source booted an hour ago; its clock runs fast)
    source = 3500.0 + np.arange(0.0, 100.0, 0.2)
    delays = 0.01 + rng.exponential(0.02, source.size)  # (10 ms at least, 20 ms more on average)
    for s, d in zip(source, delays, strict=True):
        clock.add(float(s), offset_s + (1 + drift) * float(s) + float(d))
    e = clock.estimate
    assert e.drift == pytest.approx(drift, abs=20e-6)
    # Each fix's fleet time within a few milliseconds of when it was taken.
    taken = offset_s + (1 + drift) * source
    mapped = np.array([clock.fleet_s(float(s)) for s in source])
    assert np.abs(mapped - taken).max() < 0.015
    assert "drift +" in e.describe() and "ppm" in e.describe()


def test_no_drift_before_the_pairs_span_enough_source_time():
    clock = SourceClock()
    for k in range(int(DRIFT_SPAN_S / 0.2) - 5):
        clock.add(10.0 + 0.2 * k, 0.2 * k * 1.01 + 0.05)
    assert clock.estimate.drift == 0.0
    assert clock.fleet_s(10.0) == pytest.approx(0.05)
