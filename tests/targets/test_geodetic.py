"""The geodetic -> local North-East conversion the target sources use
(`fleetmpc.protocol.local_frame.ned_from_geodetic`: PX4's azimuthal equidistant projection on a
sphere of 6371 km), measured against an exact reference on the WGS-84 ellipsoid: the geodesic's
length and azimuth from home (Vincenty's inverse formula, written out here), as North and East.

The sphere's radius is not the ellipsoid's: at 47.4 deg latitude the meridian's radius of
curvature is 6.370e6 m (North scale error 0.015 %) and the prime vertical's 6.390e6 m (East
scale error 0.29 %). So the conversion adds an error growing with the distance from home, as
measured here: 3 cm at (10, 10) m, 0.15 m at 1 km due North, 2.9 m at 1 km due East, 5.9 m at
(2, -2) km, 14.7 m at 5 km due East. The fleet's own positions pass through the same projection
(its SITL vehicles' fixes, a real autopilot's local origin), so what the formation follows is
placed relative to the vehicles with 0.3 % of their distance from the target as error (3 cm at
10 m).
"""

import math

import pytest

from fleetmpc.protocol.local_frame import geodetic_from_ned, ned_from_geodetic

A = 6378137.0
F = 1 / 298.257223563
B = A * (1 - F)
HOME = (47.397742, 8.545594)


def vincenty_inverse(lat1, lon1, lat2, lon2) -> tuple[float, float]:
    """Geodesic distance [m] and initial azimuth [rad] from point 1 to point 2 on WGS-84."""
    L = math.radians(lon2 - lon1)
    U1 = math.atan((1 - F) * math.tan(math.radians(lat1)))
    U2 = math.atan((1 - F) * math.tan(math.radians(lat2)))
    sU1, cU1, sU2, cU2 = math.sin(U1), math.cos(U1), math.sin(U2), math.cos(U2)
    lam = L
    for _ in range(200):
        sl, cl = math.sin(lam), math.cos(lam)
        s_sigma = math.hypot(cU2 * sl, cU1 * sU2 - sU1 * cU2 * cl)
        if s_sigma == 0.0:
            return 0.0, 0.0
        c_sigma = sU1 * sU2 + cU1 * cU2 * cl
        sigma = math.atan2(s_sigma, c_sigma)
        s_alpha = cU1 * cU2 * sl / s_sigma
        c2_alpha = 1 - s_alpha**2
        c2_sm = c_sigma - 2 * sU1 * sU2 / c2_alpha if c2_alpha else 0.0
        C = F / 16 * c2_alpha * (4 + F * (4 - 3 * c2_alpha))
        previous = lam
        lam = L + (1 - C) * F * s_alpha * (
            sigma + C * s_sigma * (c2_sm + C * c_sigma * (-1 + 2 * c2_sm**2))
        )
        if abs(lam - previous) < 1e-13:
            break
    u2 = c2_alpha * (A * A - B * B) / (B * B)
    AA = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    BB = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    d_sigma = (
        BB
        * s_sigma
        * (
            c2_sm
            + BB
            / 4
            * (
                c_sigma * (-1 + 2 * c2_sm**2)
                - BB / 6 * c2_sm * (-3 + 4 * s_sigma**2) * (-3 + 4 * c2_sm**2)
            )
        )
    )
    distance = B * AA * (sigma - d_sigma)
    azimuth = math.atan2(cU2 * math.sin(lam), cU1 * sU2 - sU1 * cU2 * math.cos(lam))
    return distance, azimuth


def exact_north_east(lat, lon) -> tuple[float, float]:
    s, az = vincenty_inverse(*HOME, lat, lon)
    return s * math.cos(az), s * math.sin(az)


def test_the_reference_knows_a_degree_of_latitude():
    # One degree of latitude about 47.4 deg on WGS-84: 111,178.6 m (the meridian arc, from
    # published tables of the meridian's length per degree).
    s, az = vincenty_inverse(46.9, 8.5, 47.9, 8.5)
    assert s == pytest.approx(111_178.6, abs=1.0) and az == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    ("north_m", "east_m", "error_m"),
    [
        (10.0, 10.0, 0.029),
        (0.0, 1000.0, 2.94),
        (1000.0, 0.0, 0.146),
        (2000.0, -2000.0, 5.89),
        (0.0, 5000.0, 14.70),
        (-3500.0, 3500.0, 10.30),
    ],
)
def test_error_over_a_few_kilometres_is_the_spheres_scale(north_m, east_m, error_m):
    """The error the conversion adds at (North, East) about home, within its stated bound:
    0.3 % of the distance East and 0.015 % North."""
    lat, lon = geodetic_from_ned(north_m, east_m, home_lat_deg=HOME[0], home_lon_deg=HOME[1])
    # A point placed on the ellipsoid at that true North, East (its geodesic from home), read back.
    true_n, true_e = exact_north_east(lat, lon)
    got_n, got_e = ned_from_geodetic(lat, lon, home_lat_deg=HOME[0], home_lon_deg=HOME[1])
    assert (got_n, got_e) == pytest.approx((north_m, east_m), abs=1e-6)  # (its own inverse)
    error = math.hypot(got_n - true_n, got_e - true_e)
    bound = 0.0030 * abs(east_m) + 0.00015 * abs(north_m) + 0.01
    assert error <= bound
    assert error == pytest.approx(error_m, rel=0.02, abs=0.002)
