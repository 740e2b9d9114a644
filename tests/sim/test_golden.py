"""Golden figures: lockstep runs of a few scenarios against the arrays of an earlier run.

Each case flies a scenario in lockstep, as `fleetmpc sim` does, and compares every numeric field
of its FlightRecord with the array stored for it in ``data/golden.npz`` (keys ``case/field``), at
rtol = atol = 1e-9 with NaN equal to NaN. A change that only reorganizes the code leaves every
figure where it was; a field that is missing from the run or from the file fails the test too.
The per-agent step times (`step_time_ms`) are wall-clock measurements: they are not stored, and
nothing else the simulation computes depends on the clock.

Regenerate the file from the repository with

    .venv/bin/python tests/sim/make_golden.py

and only when a change is meant to change the figures (a model, a tuning, a scenario): the new
file then records the new figures and goes into the same commit as the change that explains
them. Regenerating to make a refactor pass hides exactly what this test is here to catch.
"""

import ctypes
import dataclasses
import json
import platform
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

from fleetmpc.gcs.record import FlightRecord
from fleetmpc.scenario import load_scenario
from fleetmpc.sim.lockstep import run_lockstep

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "data" / "golden.npz"
"""The stored figures, one array per case and field under the key ``case/field``."""

PLATFORM_KEY = "platform"
"""The key of the file's one entry that is no case: where its figures were computed (JSON)."""

RTOL = 1e-9
ATOL = 1e-9

WALL_CLOCK_FIELDS = frozenset({"step_time_ms"})
"""Record fields that measure wall time: they differ from run to run and are not compared."""


@dataclasses.dataclass(frozen=True)
class Case:
    """One lockstep run: a scenario of the repository, learning on or off, for a duration."""

    name: str
    """The case's key in the golden file."""
    scenario: str
    """The scenario file's stem in ``scenarios/``."""
    learning: bool = True
    duration_s: float | None = None
    """Simulated seconds; None: the scenario's own duration."""


CASES = (
    Case("paper", "paper"),
    Case("paper-no-learning", "paper", learning=False),
    Case("square", "square", duration_s=50.0),  # through the first corner (t = 40 s)
    Case("uturn-start", "uturn-start", duration_s=30.0),  # the turn-round and the fleet's reorder
    Case("grid9", "grid9", duration_s=30.0),
)
"""The golden runs, each with its scenario's own seed (about 2 s of flight on one core)."""


def fly(case: Case) -> FlightRecord:
    """The case's lockstep run."""
    scenario = load_scenario(ROOT / "scenarios" / f"{case.scenario}.toml")
    return run_lockstep(scenario, learning=case.learning, duration_s=case.duration_s)


def record_arrays(rec: FlightRecord) -> dict[str, np.ndarray]:
    """The numeric fields of a record as arrays, by field name.

    Its arrays, its numbers (as 0-d arrays) and its vehicle ids; not its scenario name, not its
    wall-clock fields, not its network report (counts, checked by the fault tests) and not an
    optional field the run left as None.
    """
    out: dict[str, np.ndarray] = {}
    for f in dataclasses.fields(rec):
        value = getattr(rec, f.name)
        if f.name in WALL_CLOCK_FIELDS or value is None or isinstance(value, str | dict):
            continue
        array = np.asarray(value)
        if array.dtype.kind not in "biuf":
            raise TypeError(f"FlightRecord.{f.name}: not numeric ({type(value).__name__})")
        out[f.name] = array
    return out


OPENBLAS_CONFIG_SYMBOLS = (
    "scipy_openblas_get_config64_",  # numpy's wheels
    "scipy_openblas_get_config",  # scipy's wheels
    "openblas_get_config",  # a system OpenBLAS
)


def openblas_configs() -> list[str]:
    """The build line of each OpenBLAS loaded in this process, its kernel included ("Haswell",
    "SkylakeX", ...: picked at load time for the CPU); empty where the process's maps cannot
    be read (not Linux)."""
    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split()[-1] for line in maps if "openblas" in line})
    except OSError:
        return []
    configs = set()
    for path in paths:
        lib = ctypes.CDLL(path)
        for symbol in OPENBLAS_CONFIG_SYMBOLS:
            get_config = getattr(lib, symbol, None)
            if get_config is not None:
                get_config.restype = ctypes.c_char_p
                configs.add(get_config().decode().strip())
                break
    return sorted(configs)


def platform_fingerprint() -> dict[str, str]:
    """What the figures' last bits depend on besides the code: the CPU architecture, the numeric
    libraries and the BLAS kernel.

    The lockstep run reads no clock, so a slower or busier machine computes the same figures.
    A BLAS kernel, though, rounds in its own order, and the closed loop carries a last-bit
    difference from period to period: under OpenBLAS's Haswell kernel instead of SkylakeX,
    uturn-start's commands end up 2e-3 apart. The figures hold at 1e-9 only where the stored
    fingerprint is this one; a failure says when it is not.
    """
    return {
        "machine": platform.machine(),
        **{package: version(package) for package in ("numpy", "scipy", "osqp")},
        "blas": "; ".join(openblas_configs()) or "unknown",
    }


def differences(name: str, actual: np.ndarray, expected: np.ndarray) -> str | None:
    """How `actual` differs from the stored `expected` of field `name`; None if it does not.

    Floats compare at RTOL and ATOL (NaN equal to NaN); flags and integers compare exactly.
    """
    if actual.shape != expected.shape:
        return f"{name}: shape {actual.shape}, stored {expected.shape}"
    if actual.dtype.kind != expected.dtype.kind:
        return f"{name}: dtype {actual.dtype}, stored {expected.dtype}"
    try:
        if expected.dtype.kind == "f":
            np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=ATOL, equal_nan=True)
        else:
            np.testing.assert_array_equal(actual, expected)
    except AssertionError as e:
        detail = "\n".join(f"    {line}" for line in str(e).strip().splitlines())
        return f"{name}:\n{detail}"
    return None


@pytest.fixture(scope="module")
def golden() -> dict[str, dict[str, np.ndarray]]:
    """The stored figures by case, then by field."""
    if not GOLDEN.exists():
        pytest.fail(f"{GOLDEN} is missing: write it with tests/sim/make_golden.py")
    by_case: dict[str, dict[str, np.ndarray]] = {}
    with np.load(GOLDEN, allow_pickle=False) as data:
        for key in data.files:
            if key == PLATFORM_KEY:
                continue
            case, field = key.split("/", 1)
            by_case.setdefault(case, {})[field] = data[key]
    return by_case


@pytest.fixture(scope="module")
def stored_platform() -> dict[str, str]:
    """Where the stored figures were computed (empty if the file does not say)."""
    with np.load(GOLDEN, allow_pickle=False) as data:
        return json.loads(str(data[PLATFORM_KEY])) if PLATFORM_KEY in data.files else {}


def test_golden_file_holds_every_case_and_no_other(golden):
    assert sorted(golden) == sorted(c.name for c in CASES)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_lockstep_figures_match_the_golden_file(case, golden, stored_platform):
    expected = golden.get(case.name)
    if expected is None:
        pytest.fail(f"{case.name}: no figures stored in {GOLDEN.name}")
    actual = record_arrays(fly(case))
    problems = [f"{field}: missing from the run" for field in sorted(expected.keys() - actual)]
    problems += [f"{field}: not in {GOLDEN.name}" for field in sorted(actual.keys() - expected)]
    for field in sorted(expected.keys() & actual.keys()):
        diff = differences(field, actual[field], expected[field])
        if diff is not None:
            problems.append(diff)
    if problems:
        here = platform_fingerprint()
        moved = {
            k: (stored_platform.get(k), v) for k, v in here.items() if stored_platform.get(k) != v
        }
        note = "".join(f"\n  {k}: stored {a!r}, here {b!r}" for k, (a, b) in moved.items())
        if note:
            note = (
                "\nThe figures were stored on another platform (see platform_fingerprint):" + note
            )
        pytest.fail(
            f"{case.name}: {len(problems)} field(s) differ from the golden figures\n"
            + "\n".join(f"- {p}" for p in problems)
            + note,
            pytrace=False,
        )
