"""The fleet-level series the viewer shows by default, against the per-vehicle and per-pair
values they summarize."""

import dataclasses

import numpy as np
import pytest

from fleetmpc.gcs.fleet_series import FLEET_SERIES, fleet_rows, stale_plan_count
from fleetmpc.gcs.metrics import pair_indices
from fleetmpc.gcs.record import LiveRows
from fleetmpc.lockstep.flight import run_lockstep


@pytest.fixture(scope="module")
def run(paper):
    return run_lockstep(paper, duration_s=4.0)


def _separations(rec) -> np.ndarray:
    pos = rec.truth[:, :, :2]
    return np.stack(
        [np.linalg.norm(pos[:, a] - pos[:, b], axis=1) for a, b in pair_indices(pos.shape[1])],
        axis=1,
    )


def test_stale_plans_count_those_past_the_agents_limit():
    nan = np.nan
    ages = np.array(
        [
            [[nan, nan], [nan, nan], [nan, nan]],  # nobody reported: no count
            [[0.2, 1.5], [nan, 0.1], [3.0, 0.3]],  # two too old; one not reported (not counted)
            [[1.0, 1.0], [0.0, 0.0], [0.2, 0.2]],  # at the limit is not past it
        ]
    )
    count = stale_plan_count(ages, plan_stale_s=1.0)
    assert np.isnan(count[0]) and count[1:].tolist() == [2, 0]
    assert np.isnan(stale_plan_count(ages, plan_stale_s=None)).all()


def test_the_fleet_rows_summarize_every_vehicle_and_pair(run):
    rec = run
    k = len(rec.t_s)
    live = LiveRows.blank(k, len(rec.vehicle_ids))
    rows = fleet_rows(rec, live, separation_m=_separations(rec), plan_stale_s=1.0)
    assert list(rows) == list(FLEET_SERIES)
    for name, (_, lines) in FLEET_SERIES.items():
        assert rows[name].shape == (k, len(lines)), name
    np.testing.assert_array_equal(rows["min_separation"][:, 0], _separations(rec).min(axis=1))
    assert (rows["min_separation"][:, 1] == rec.d_safe_m).all()
    # The run's minimum, at plant rate, is at most the closest of the periods.
    assert rec.min_separation_m <= rows["min_separation"][:, 0].min()
    slot_error = np.linalg.norm(rec.truth[:, :, :2] - rec.slots, axis=2)
    np.testing.assert_array_equal(rows["formation_error"][:, 0], slot_error.max(axis=1))
    np.testing.assert_array_equal(rows["formation_error"][:, 1], np.median(slot_error, axis=1))
    np.testing.assert_allclose(
        rows["step_time_ms"], np.percentile(rec.step_time_ms, [50, 99], axis=1).T
    )
    relative = np.abs(rec.beta[..., :2] / rec.beta_truth[..., :2] - 1)
    np.testing.assert_allclose(rows["learning_error"][:, 0], relative.max(axis=(1, 2)))
    drift = np.linalg.norm(rec.beta[..., 2:] - rec.beta_truth[..., 2:], axis=2)
    np.testing.assert_array_equal(rows["learning_error"][:, 1], drift.max(axis=1))
    assert np.isnan(rows["stale_plans"]).all()  # (a record alone: no plan ages)


def test_a_vehicle_without_a_truth_or_a_step_time_is_left_out_not_made_nan(run):
    rec = run
    beta_truth = rec.beta_truth.copy()
    beta_truth[:, 0] = np.nan  # (a real autopilot: no truth to judge its learning by)
    step = rec.step_time_ms.copy()
    step[:, 1] = np.nan
    partial = dataclasses.replace(rec, beta_truth=beta_truth, step_time_ms=step)
    live = LiveRows.blank(len(rec.t_s), len(rec.vehicle_ids))
    rows = fleet_rows(partial, live, separation_m=_separations(rec), plan_stale_s=1.0)
    assert np.isfinite(rows["learning_error"]).all() and np.isfinite(rows["step_time_ms"]).all()
    drift = np.linalg.norm(rec.beta[:, 1:, 2:] - rec.beta_truth[:, 1:, 2:], axis=2)
    np.testing.assert_array_equal(rows["learning_error"][:, 1], drift.max(axis=1))
