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
