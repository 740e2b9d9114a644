"""Golden figures: lockstep runs of a few scenarios against the arrays of an earlier run.

Each case flies a scenario in lockstep, as `fleetmpc sim` does, and compares every numeric field
of its FlightRecord with the array stored for it in ``data/golden.npz``: floats within the
tolerance ``data/golden_tolerances.json`` holds for the field (a wide margin over how far a
last-bit difference of the arithmetic carries through that run: `golden.py`), flags and
integers exactly. A change that only reorganizes the code leaves every figure within it; a
change of the control code by one part in 1e6 does not (tested here); a field missing from the
run or from the file fails too. On the machine that runs the suite, the same run twice is the
same bit for bit (tested here; `--jobs` and the recording read back: tests/lockstep/test_scale.py,
tests/gcs/test_live.py).

Regenerate the files with ``.venv/bin/python tests/lockstep/make_golden.py``, and only when a change
is meant to change the figures (docs/testing.md).
"""

import dataclasses

import numpy as np
import pytest
from golden import (
    CASES,
    GOLDEN,
    TOLERANCES,
    case_named,
    case_scenario,
    compare,
    fly,
    load_golden,
    load_stored_platform,
    load_tolerances,
    platform_fingerprint,
    record_arrays,
)


@pytest.fixture(scope="module")
def golden() -> dict[str, dict[str, np.ndarray]]:
    for path in (GOLDEN, TOLERANCES):
        if not path.exists():
            pytest.fail(f"{path} is missing: write it with tests/lockstep/make_golden.py")
    return load_golden()


@pytest.fixture(scope="module")
def tolerances() -> dict[str, dict[str, float]]:
    return load_tolerances()


def platform_note() -> str:
    """Where the stored figures were computed and where these were, where the two differ."""
    stored = load_stored_platform()
    moved = {k: (stored.get(k), v) for k, v in platform_fingerprint().items() if stored.get(k) != v}
    lines = "".join(f"\n  {k}: stored {a!r}, here {b!r}" for k, (a, b) in moved.items())
    return f"\nThe figures were stored on another platform:{lines}" if lines else ""


def test_golden_files_hold_every_case_and_no_other(golden, tolerances):
    assert sorted(golden) == sorted(c.name for c in CASES)
    assert sorted(tolerances) == sorted(golden)
    for case, fields in golden.items():
        floats = {f for f, a in fields.items() if a.dtype.kind == "f"}
        assert sorted(tolerances[case]) == sorted(floats), case


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_lockstep_figures_match_the_golden_file(case, golden, tolerances):
    expected = golden.get(case.name)
    if expected is None:
        pytest.fail(f"{case.name}: no figures stored in {GOLDEN.name}")
    problems = compare(record_arrays(fly(case)), expected, tolerances[case.name])
    if problems:
        pytest.fail(
            f"{case.name}: {len(problems)} field(s) differ from the golden figures\n"
            + "\n".join(f"- {p}" for p in problems)
            + platform_note(),
            pytrace=False,
        )


@pytest.mark.parametrize("weight", ["q_position", "r_yaw_rate"])
def test_a_weight_changed_by_one_part_in_a_million_is_caught(weight, golden, tolerances):
    """The tolerances are no blanket: nudging one QP weight by 1e-6 fails the paper case."""
    case = case_named("paper")
    scenario = case_scenario(case)
    changed = getattr(scenario.controller, weight) * (1 + 1e-6)
    controller = dataclasses.replace(scenario.controller, **{weight: changed})
    record = fly(case, dataclasses.replace(scenario, controller=controller))
    problems = compare(record_arrays(record), golden[case.name], tolerances[case.name])
    assert any(p.startswith("command:") for p in problems), problems


def test_the_same_run_twice_is_the_same_bit_for_bit():
    """What must be identical on one machine is: the lockstep reads no clock and no global
    random state, so the turn-round that carries a last bit furthest repeats exactly."""
    case = case_named("uturn-start")
    first, second = record_arrays(fly(case)), record_arrays(fly(case))
    assert first.keys() == second.keys()
    for field, a in first.items():
        assert np.array_equal(a, second[field], equal_nan=a.dtype.kind == "f"), field
