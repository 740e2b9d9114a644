"""Recorded tracks read from a CSV or a MAVLink telemetry log, and what `check` reports of them."""

import struct

import numpy as np
import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.protocol.local_frame import geodetic_from_ned
from fleetmpc.targets.track import RecordedTrack, noise_estimate, track_stats
from fleetmpc.targets.track_file import load_track, read_fixes

HOME = (47.397742, 8.545594)


def _latlon(n: float, e: float) -> tuple[float, float]:
    return geodetic_from_ned(n, e, home_lat_deg=HOME[0], home_lon_deg=HOME[1])


def test_csv_with_header_comments_and_velocities(tmp_path):
    rows = ["time_s,lat_deg,lon_deg,alt_m,vn_m_s,ve_m_s", "# a comment"]
    for k in range(20):
        lat, lon = _latlon(1.0 * k, 2.0)
        rows.append(f"{500.0 + k:.1f},{lat:.7f},{lon:.7f},10.0,1.0,0.0")
    path = tmp_path / "t.csv"
    path.write_text("\n".join(rows) + "\n")
    track = load_track(path, home_lat_deg=HOME[0], home_lon_deg=HOME[1], noise_m=0.2)
    assert track.times_s[0] == 0.0 and track.duration_s == pytest.approx(19.0)
    assert np.abs(track.positions_m - [[k, 2.0] for k in range(20)]).max() < 0.02  # (1e-7 deg)
    (x, y), (vx, vy) = track.state_floats(3.5)
    assert (x, y, vx, vy) == pytest.approx((3.5, 2.0, 1.0, 0.0), abs=0.02)
    assert track.state_floats(99.0)[1] == (0.0, 0.0)  # (stopped after its last fix)
    assert track.observation_noise_m == 0.2 and track.observation_rate_hz == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0,47.3,8.5\n1,47.3\n", "expected time,lat,lon"),
        ("0,47.3,8.5\n1,north,8.5\n", ":2: not numbers"),
        ("0,47.3,8.5\n1,47.3,8.5\n1,47.3,8.5\n", "fix 2's time does not increase"),
        ("0,47.3,8.5\n1,nan,8.5\n", "fix 1 is not a number"),
        ("0,47.3,8.5\n", "needs at least 2 fixes"),
    ],
)
def test_a_bad_csv_is_an_error_naming_where(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_track(path, home_lat_deg=HOME[0], home_lon_deg=HOME[1])


def _tlog(path, systems: dict[int, float]) -> None:
    """A telemetry log: each system's GLOBAL_POSITION_INT at 5 Hz for 10 s, moving North at the
    given speed, and a FOLLOW_TARGET of system 255's; each message after its 8-byte time."""
    from pymavlink.dialects.v20 import common as mavlink

    with path.open("wb") as f:
        for k in range(50):
            for sysid, speed in systems.items():
                mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
                lat, lon = _latlon(speed * 0.2 * k, 3.0)
                msg = mavlink.MAVLink_global_position_int_message(
                    1000 + 200 * k, round(lat * 1e7), round(lon * 1e7), 0, 0,
                    round(speed * 100), 0, 0, 0,
                )  # fmt: skip
                f.write(struct.pack(">Q", 1_700_000_000_000_000 + 200_000 * k) + msg.pack(mav))


def test_tlog_picks_the_system_followed(tmp_path):
    path = tmp_path / "flight.tlog"
    _tlog(path, {1: 0.0, 4: 2.0})
    with pytest.raises(ConfigError, match=r"holds systems \[1, 4\]"):
        read_fixes(path)
    track = load_track(path, home_lat_deg=HOME[0], home_lon_deg=HOME[1], system_id=4)
    assert len(track.times_s) == 50 and track.times_s[-1] == pytest.approx(9.8)
    assert track.positions_m[-1] == pytest.approx((2.0 * 9.8, 3.0), abs=0.02)
    assert track.velocities_m_s[10] == pytest.approx((2.0, 0.0))
    with pytest.raises(ConfigError, match="no positions of system 9"):
        load_track(path, home_lat_deg=HOME[0], home_lon_deg=HOME[1], system_id=9)


def test_noise_estimate_and_stats_of_a_noisy_track_with_a_gap():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 60.0, 0.2)
    t = t[(t < 20.0) | (t >= 26.0)]  # (a 6 s gap)
    radius, speed = 20.0, 1.5  # (a circle: turn rate 0.075 rad/s)
    a = speed * t / radius
    p = radius * np.column_stack([np.sin(a), 1 - np.cos(a)]) + 0.1 * rng.standard_normal(
        (t.size, 2)
    )
    assert noise_estimate(p) == pytest.approx(0.1, rel=0.15)
    st = track_stats(RecordedTrack(times_s=t, positions_m=p))
    assert st.gaps == (pytest.approx((19.8, 6.2)),)
    assert st.speed_p95_m_s == pytest.approx(speed, rel=0.1)
    # (The 95th percentile has the noise's course jitter on top of the turn.)
    assert speed / radius <= st.turn_rate_p95_rad_s <= speed / radius + 0.05
