"""The known-model run: every agent told its vehicle's truth, the limit a learner is measured by."""

import dataclasses
import json

import numpy as np

from fleetmpc.cli import main
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.sitl.wind import Turbulence


def turbulent(scenario, sigma_m_s=0.15):
    """`scenario` with every vehicle in turbulence of `sigma_m_s`."""
    turbulence = Turbulence(sigma_m_s=sigma_m_s, length_scale_m=20.0, time_scale_s=5.0)
    vehicles = tuple(
        dataclasses.replace(
            v,
            truth=dataclasses.replace(
                v.truth, wind=dataclasses.replace(v.truth.wind, turbulence=turbulence)
            ),
        )
        for v in scenario.vehicles
    )
    return dataclasses.replace(scenario, vehicles=vehicles)


def test_a_known_model_run_flies_on_the_truth_every_period(paper):
    rec = run_lockstep(turbulent(paper), duration_s=6.0, known_model=True)
    # From the second period on (the first only starts the filters), the agents' beta is the
    # truth of the period: effectiveness, and the wind where each vehicle is.
    np.testing.assert_array_equal(rec.beta[1:], rec.beta_truth[1:])
    assert np.ptp(rec.beta_truth[:, 0, 2]) > 0.01  # the wind it was told changed


def test_sim_reports_the_learned_run_over_the_known_model_run(tmp_path, paper):
    out = tmp_path / "m.json"
    code = main(
        ["sim", "scenarios/paper.toml", "--known-model", "--quiet"] + ["--metrics", str(out)]
    )
    assert code == 0
    m = json.loads(out.read_text())
    assert 0.0 < m["known_model_formation_rms_m"] < 0.1
    assert m["learned_over_known"] == m["formation_rms_m"] / m["known_model_formation_rms_m"]


SEEDS = range(1, 9)


def _settled_slot_rms(scenario, seeds) -> float:
    """Slot RMS of known-model runs over every vehicle, from t = 20 s on [m]."""
    squares = []
    for seed in seeds:
        rec = run_lockstep(scenario, known_model=True, seed=seed)
        error = np.linalg.norm(rec.truth[:, :, :2] - rec.slots, axis=2)
        squares.append(np.mean(error[rec.t_s >= 20.0] ** 2))
    return float(np.sqrt(np.mean(squares)))


def test_checks_wind_limit_is_what_the_known_model_run_loses_to_the_wind():
    """docs/design.md, "What the controller leaves of the wind": a case that did not fix the
    cross-track gain (five vehicles on a circle at 1 m/s, turbulence of other scales)."""
    from fleetmpc.check.wind_report import cross_track_time_s
    from fleetmpc.scenario import load_scenario

    calm = load_scenario("scenarios/wedge-circle.toml")
    turbulence = Turbulence(sigma_m_s=0.12, length_scale_m=15.0, time_scale_s=4.0)
    windy_vehicles, calm_vehicles = [], []
    for v in calm.vehicles:
        wind = dataclasses.replace(v.truth.wind, gust_amplitude_m_s=0.0)
        for out, w in (
            (calm_vehicles, wind),
            (windy_vehicles, dataclasses.replace(wind, turbulence=turbulence)),
        ):
            out.append(dataclasses.replace(v, truth=dataclasses.replace(v.truth, wind=w)))
    windy = dataclasses.replace(calm, vehicles=tuple(windy_vehicles))
    calm = dataclasses.replace(calm, vehicles=tuple(calm_vehicles))
    t_y = cross_track_time_s(1.0)
    predicted = 0.5 * t_y * windy.vehicles[0].truth.wind.change_m_s(1.0, t_y)
    flown = np.sqrt(_settled_slot_rms(windy, SEEDS) ** 2 - _settled_slot_rms(calm, SEEDS) ** 2)
    assert abs(predicted - 0.061) < 0.001
    print(f"wind share flown {flown:.4f} m, check {predicted:.4f} m")
    assert 0.8 < flown / predicted < 1.2, (flown, predicted)
