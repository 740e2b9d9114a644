"""The known-model run: every agent told its vehicle's truth, the limit a learner is measured by."""

import dataclasses
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fleetmpc.check.wind_report import drift_filter, wind_share_m
from fleetmpc.cli import main
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import parse_scenario
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


def _settled_slot_rms(scenario, seeds, known: bool) -> float:
    """Slot RMS over every vehicle, from t = 20 s on [m]."""
    squares = []
    for seed in seeds:
        rec = run_lockstep(scenario, known_model=known, seed=seed)
        error = np.linalg.norm(rec.truth[:, :, :2] - rec.slots, axis=2)
        squares.append(np.mean(error[rec.t_s >= 20.0] ** 2))
    return float(np.sqrt(np.mean(squares)))


def _wedge_circle(wind: dict):
    """scenarios/wedge-circle.toml in `wind` (its learner set for that wind, as on loading)."""
    doc = tomllib.loads(Path("scenarios/wedge-circle.toml").read_text())
    doc["truth"]["wind"] = wind
    return parse_scenario(doc)


@pytest.mark.slow  # (about 50 s of two cores: two 110 s flights of five vehicles)
@pytest.mark.parametrize(("known", "expected_m"), [(True, 0.061), (False, 0.078)])
def test_checks_wind_share_is_what_a_run_loses_to_the_wind(known, expected_m):
    """docs/design.md, "What the controller leaves of the wind": a case that did not fix the
    cross-track gain (five vehicles on a circle at 1 m/s, turbulence of other scales), known
    and learned (whose drift lags the wind by 1 / its filter's bandwidth)."""
    turbulence = {"sigma_m_s": 0.12, "length_scale_m": 15.0, "time_scale_s": 4.0}
    windy = _wedge_circle({"mean_m_s": [0.2, 0.2], "turbulence": turbulence})
    calm = _wedge_circle({"mean_m_s": [0.2, 0.2]})
    lag = 0.0 if known else 1.0 / drift_filter(windy).bandwidth_rad_s
    predicted = wind_share_m(windy.vehicles[0].truth.wind, 1.0, lag)
    assert abs(predicted - expected_m) < 0.001
    rms = [_settled_slot_rms(sc, SEEDS, known) for sc in (windy, calm)]
    flown = np.sqrt(rms[0] ** 2 - rms[1] ** 2)
    print(f"wind share flown {flown:.4f} m, check {predicted:.4f} m")
    assert 0.8 < flown / predicted < 1.2, (flown, predicted)
