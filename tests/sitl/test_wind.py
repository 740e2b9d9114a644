"""The wind field: its statistics, its determinism, its gusts and its place in the plant."""

import dataclasses
import math

import numpy as np
import pytest

from fleetmpc.errors import ConfigError
from fleetmpc.scenario import parse_scenario
from fleetmpc.sitl.plant import TruthParams, TruthPlant
from fleetmpc.sitl.wind import Gust, Turbulence, Wind, WindField, von_karman_correlation

TURBULENT = Wind(turbulence=Turbulence(sigma_m_s=0.15, length_scale_m=20.0, time_scale_s=5.0))
SEEDS = range(300)
"""Realizations over which the ensemble statistics are taken."""


def ensemble(wind: Wind, t_s: float, points: list[tuple[float, float]]) -> np.ndarray:
    """The turbulence at `points` and time t_s in every realization of SEEDS (seeds, points, 2)."""
    xy = np.array(points, dtype=float)
    return np.array([WindField(wind, seed=s).turbulence(t_s, xy) for s in SEEDS])


def test_each_component_has_the_stated_intensity():
    u = ensemble(TURBULENT, 7.0, [(0.0, 0.0), (100.0, -50.0)])
    assert np.std(u) == pytest.approx(0.15, rel=0.1)
    assert abs(float(np.mean(u))) < 0.03


def test_nearby_vehicles_feel_winds_correlated_as_the_von_karman_spectrum_says():
    L = TURBULENT.turbulence.length_scale_m
    for r in (0.25 * L, L, 3 * L):
        u = ensemble(TURBULENT, 3.0, [(0.0, 0.0), (r, 0.0)])
        longitudinal = np.corrcoef(u[:, 0, 0], u[:, 1, 0])[0, 1]
        assert longitudinal == pytest.approx(float(von_karman_correlation(r / L)), abs=0.12), r


def test_a_point_in_the_moving_air_sees_the_wind_decorrelate_over_the_time_scale():
    calm = Wind(turbulence=TURBULENT.turbulence)  # no mean: the air stands still
    T = calm.turbulence.time_scale_s
    u0 = ensemble(calm, 0.0, [(0.0, 0.0)])[:, 0, 0]
    for dt in (1.0, 5.0):
        u = ensemble(calm, dt, [(0.0, 0.0)])[:, 0, 0]
        assert np.corrcoef(u0, u)[0, 1] == pytest.approx(math.exp(-dt / T), abs=0.12), dt


def test_the_turbulence_is_carried_by_the_mean_wind():
    frozen = Wind(mean_m_s=(2.0, -1.0), turbulence=Turbulence(sigma_m_s=0.2, time_scale_s=1e12))
    field = WindField(frozen, seed=4)
    here = np.array([[3.0, 4.0]])
    later = field.turbulence(10.0, here + 10.0 * np.array([2.0, -1.0]))
    np.testing.assert_allclose(later, field.turbulence(0.0, here), atol=1e-9)


def test_one_seed_one_field_and_another_seed_another():
    xy = np.array([[1.0, 2.0], [30.0, -4.0]])
    a, b = WindField(TURBULENT, seed=11), WindField(TURBULENT, seed=11)
    np.testing.assert_array_equal(a.turbulence(12.3, xy), b.turbulence(12.3, xy))
    assert not np.allclose(
        a.turbulence(12.3, xy), WindField(TURBULENT, seed=12).turbulence(12.3, xy)
    )


def test_a_one_minus_cosine_gust_rises_to_its_amplitude_and_passes():
    gust = Gust(onset_s=10.0, amplitude_m_s=(0.0, 0.3), length_m=20.0, front_speed_m_s=4.0)
    assert gust.at(9.9, 0.0, 0.0) == (0.0, 0.0)
    assert gust.at(12.5, 0.0, 0.0) == pytest.approx((0.0, 0.3))  # half its length behind the front
    assert gust.at(15.1, 0.0, 0.0) == (0.0, 0.0)  # length / speed = 5 s later it has passed
    assert gust.at(12.5, 0.0, 10.0) == pytest.approx((0.0, 0.0))  # 10 m down its path: not yet
    assert gust.at(15.0, 0.0, 10.0) == pytest.approx((0.0, 0.3))  # 2.5 s later it peaks there
    assert gust.duration_s == 5.0


def test_a_hovering_plant_is_carried_by_the_gust_by_its_integral():
    gust = Gust(onset_s=1.0, amplitude_m_s=(0.2, 0.0), length_m=40.0, front_speed_m_s=20.0)
    wind = Wind(gusts=(gust,))
    plant = TruthPlant(TruthParams(wind=wind), x_m=0.0, y_m=0.0, yaw_rad=0.0)
    plant.advance(10_000_000, 400)  # 4 s; the gust lasts 2 s, mean 0.1 m/s
    # Carried along at up to 0.2 m/s, the plant stays in it a little longer than 2 s.
    assert plant.position_m[0] == pytest.approx(0.2, rel=0.02)
    assert plant.position_m[1] == 0.0


def test_in_the_same_field_two_plants_at_one_place_drift_alike():
    field = WindField(TURBULENT, seed=3)
    plants = [
        TruthPlant(TruthParams(wind=TURBULENT), x_m=5.0, y_m=5.0, yaw_rad=0.0, wind=field)
        for _ in range(2)
    ]
    for p in plants:
        p.advance(20_000_000, 250)
    assert plants[0].position_m == plants[1].position_m
    assert math.dist(plants[0].position_m, (5.0, 5.0)) > 0.1  # the turbulence moved them


def test_a_plant_booted_later_reads_the_fleets_wind_clock():
    """Two SITL processes of one fleet: the one booted 3 s after the wind's clock started
    (offset 3 s) feels at its own time t what the other feels at t + 3 s."""
    field = WindField(TURBULENT, seed=3)
    first = TruthPlant(TruthParams(wind=TURBULENT), x_m=5.0, y_m=5.0, yaw_rad=0.0, wind=field)
    later = TruthPlant(
        TruthParams(wind=TURBULENT),
        x_m=5.0,
        y_m=5.0,
        yaw_rad=0.0,
        wind=field,
        wind_clock_offset_ns=3_000_000_000,
    )
    assert first.wind_m_s == pytest.approx(field.at(0.0, 5.0, 5.0), abs=1e-12)
    assert later.wind_m_s == pytest.approx(field.at(3.0, 5.0, 5.0), abs=1e-12)
    assert math.dist(later.wind_m_s, first.wind_m_s) > 1e-3
    later.advance(20_000_000, 50)
    assert later.wind_m_s == pytest.approx(field.at(4.0, *later.position_m), abs=1e-12)


def _doc(**wind) -> dict:
    return {
        "name": "w",
        "target": {"kind": "line", "start_m": [0.0, 0.0], "velocity_m_s": [1.0, 0.0]},
        "truth": {"wind": wind},
        "vehicles": [
            {"initial": [0.0, 0.0, 0.0], "slot_m": [0.0, 0.0]},
            {"initial": [0.0, 10.0, 0.0], "slot_m": [0.0, 10.0]},
        ],
    }


def test_a_scenario_describes_turbulence_and_gusts_in_truth_wind():
    sc = parse_scenario(
        _doc(
            mean_m_s=[0.2, 0.0],
            turbulence={"sigma_m_s": 0.1, "length_scale_m": 15.0},
            gusts=[{"onset_s": 20.0, "amplitude_m_s": [0.0, 0.2], "length_m": 30.0}],
        )
    )
    wind = sc.vehicles[0].truth.wind
    assert wind.turbulence.sigma_m_s == 0.1 and wind.turbulence.length_scale_m == 15.0
    assert wind.gusts[0].amplitude_m_s == (0.0, 0.2)
    assert sc.vehicles[1].truth.wind == wind  # one field for the fleet


@pytest.mark.parametrize(
    ("wind", "field"),
    [
        ({"turbulence": {"sigma": 0.1}}, "truth.wind.turbulence.sigma"),
        ({"turbulence": {"sigma_m_s": -0.1}}, "truth.wind.turbulence.sigma_m_s"),
        (
            {"gusts": [{"onset_s": 1.0, "amplitude_m_s": [0.0, 0.0]}]},
            "truth.wind.gusts[0].amplitude_m_s",
        ),
        ({"gusts": {"onset_s": 1.0}}, "truth.wind.gusts"),
    ],
)
def test_a_bad_wind_is_refused_naming_its_field(wind, field):
    with pytest.raises(ConfigError) as err:
        parse_scenario(_doc(**wind))
    assert field in str(err.value)


def test_a_vehicle_cannot_have_turbulence_of_its_own():
    doc = _doc()
    doc["vehicles"][1]["truth"] = {"wind": {"turbulence": {"sigma_m_s": 0.1}}}
    with pytest.raises(ConfigError, match=r"vehicles\[1\].truth.wind.turbulence"):
        parse_scenario(doc)


def test_check_says_what_the_wind_means_at_the_vehicle(paper):
    from fleetmpc.check.feasibility import check_scenario

    gust = Gust(onset_s=20.0, amplitude_m_s=(0.0, 0.2), length_m=40.0)
    wind = Wind(mean_m_s=(0.3, -0.2), turbulence=TURBULENT.turbulence, gusts=(gust,))
    vehicles = tuple(
        dataclasses.replace(v, truth=dataclasses.replace(v.truth, wind=wind))
        for v in paper.vehicles
    )
    text = check_scenario(dataclasses.replace(paper, vehicles=vehicles)).render()
    assert "wind: mean 0.36 m/s toward 326 deg" in text
    # T_c = 1 / (1/5 + 1.4142/20) = 3.7 s; sigma sqrt(2 (1 - exp(-0.2 / 3.7))) = 0.049 m/s.
    assert "a vehicle sees it change over 3.7 s, by 0.049 m/s RMS per control period" in text
    assert "neighbours 10.0 m apart feel it correlated 0.54" in text
    assert "feels it for 20.0 s" in text
    calm = check_scenario(paper).render()
    assert "turbulence" not in calm and "gust" not in calm


def test_the_winds_change_over_a_lag_is_its_structure_function():
    gauss_markov = Wind(turbulence=Turbulence(sigma_m_s=0.15, length_scale_m=1e9, time_scale_s=5.0))
    assert gauss_markov.change_m_s(1.0, 1.0) == pytest.approx(
        0.15 * math.sqrt(2 * (1 - math.exp(-0.2))), rel=1e-5
    )
    sinusoid = Wind(gust_amplitude_m_s=0.2, gust_period_s=20.0)
    assert sinusoid.change_m_s(0.8, 5.0) == pytest.approx(0.2)  # A sqrt(1 - cos(pi / 2))
    assert sinusoid.change_m_s(0.8, 20.0) == pytest.approx(0.0, abs=1e-12)
    assert Wind(mean_m_s=(1.0, 0.0)).change_m_s(1.0, 1.0) == 0.0
    # Flying through the eddies adds the spatial decorrelation: more change at speed.
    frozen = Wind(turbulence=Turbulence(sigma_m_s=0.15, length_scale_m=20.0, time_scale_s=1e9))
    assert 0.0 < frozen.change_m_s(0.5, 1.0) < frozen.change_m_s(2.0, 1.0)


def test_check_says_what_the_wind_costs_the_formation_known_and_learned():
    from fleetmpc.check.feasibility import check_scenario
    from fleetmpc.scenario import load_scenario

    def text(name):
        return check_scenario(load_scenario(f"scenarios/{name}.toml")).render()

    # t_y = 1 / sqrt(0.7 * 1.4142) = 1.0 s; half of it times the wind's change over it; a
    # learned drift lags by 1 / its bandwidth (4.76 rad/s), which adds to t_y.
    moderate = text("turbulence-moderate")
    assert "known, it costs about 0.058 m of slot RMS" in moderate
    assert "cross-track loop answers in 1.0 s at 1.41 m/s" in moderate
    assert "learned (the drift lags it by 0.21 s), about 0.075 m" in moderate
    gust = text("gust-in-turn")
    assert "the gust at t = 38 s puts a vehicle about 0.064 m off its slot" in gust
    assert "known, it costs" not in text("paper")


def test_check_says_how_well_the_learned_drift_can_follow_the_wind():
    from fleetmpc.check.feasibility import check_scenario
    from fleetmpc.scenario import load_scenario

    text = check_scenario(load_scenario("scenarios/turbulence-moderate.toml")).render()
    # The gust part: sigma = 0.15 m/s, T = T_c = 3.7 s; measured at tau = 0.2 s with noise
    # R = 0.05^2. The steady-state prior variance a solves a^2 + a (R (1 - phi^2) - q) - q R = 0
    # (q = sigma^2 (1 - phi^2)), the gain is a / (a + R), the error sqrt(a R / (a + R)).
    sigma, T, R, tau = 0.15, 1.0 / (1.0 / 5.0 + 1.4142 / 20.0), 0.05**2, 0.2
    phi = math.exp(-tau / T)
    q = sigma**2 * (1 - phi**2)
    b = R * (1 - phi**2) - q
    a = (-b + math.sqrt(b * b + 4 * q * R)) / 2
    gain = a / (a + R)
    bandwidth, error = -math.log(phi * (1 - gain)) / tau, math.sqrt(a * R / (a + R))
    assert "gust part is 0.150 m/s over 3.7 s" in text
    assert f"a bandwidth of {bandwidth:.2f} rad/s and an error of about {error:.3f} m/s" in text


def test_check_says_when_the_learner_weighs_the_velocity_sensor_wrongly(paper):
    from fleetmpc.check.feasibility import check_scenario

    def text(noise_m_s):
        vehicles = tuple(
            dataclasses.replace(v, truth=dataclasses.replace(v.truth, velocity_noise_m_s=n))
            for v, n in zip(paper.vehicles, noise_m_s, strict=True)
        )
        return check_scenario(dataclasses.replace(paper, vehicles=vehicles)).render()

    assumed = paper.learning.measurement_velocity_std_m_s
    assert "learner:" not in text([assumed * 1.05] * len(paper.vehicles))
    quieter = text([assumed / 2] + [assumed] * (len(paper.vehicles) - 1))
    assert (
        f"takes the ground velocity's noise as {assumed:.3f} m/s ([learning] "
        f"measurement_velocity_std_m_s), vehicle 1 measures it with {assumed / 2:.3f} m/s"
    ) in quieter
    assert "follows the wind more slowly than the sensor allows" in quieter
    assert "carries more of the sensor's noise" in text([assumed * 2] * len(paper.vehicles))


def test_the_learners_wind_length_is_the_sites_unless_the_scenario_gives_one():
    turbulent = _doc(turbulence={"sigma_m_s": 0.1, "length_scale_m": 15.0})
    assert parse_scenario(turbulent).learning.wind_length_m == 15.0
    swinging = _doc(mean_m_s=[0.2, 0.0], gust_amplitude_m_s=0.1, gust_period_s=30.0)
    assert math.isinf(parse_scenario(swinging).learning.wind_length_m)  # (alike everywhere)
    gusty = _doc(gusts=[{"onset_s": 20.0, "amplitude_m_s": [0.0, 0.2], "length_m": 30.0}])
    assert parse_scenario(gusty).learning.wind_length_m == 30.0
    given = parse_scenario(turbulent | {"learning": {"wind_length_m": 8.0}})
    assert given.learning.wind_length_m == 8.0 and given.learning.gust_std_m_s == 0.1


def test_check_says_the_vehicles_hear_each_others_wind():
    from fleetmpc.check.feasibility import check_scenario

    text = check_scenario(parse_scenario(_doc(turbulence={"sigma_m_s": 0.1}))).render()
    assert "pools the wind its neighbours measure across their headings" in text
    assert "decorrelate over 20 m" in text
    alone = _doc(turbulence={"sigma_m_s": 0.1}) | {"learning": {"fleet_wind": False}}
    assert "neighbours measure" not in check_scenario(parse_scenario(alone)).render()
