"""The golden runs, what of their records is compared, and how closely (docs/testing.md).

A lockstep run reads no clock, so on one machine it computes the same figures every time, bit
for bit. Across machines it does not: a BLAS kernel, numpy's SIMD loops or a CPU round in their
own order, and the closed loop carries a last-bit difference from period to period. How far it
carries one is a property of each run (its *sensitivity*): a few 1e-11 m over the paper's
straight line, 1e-4 in the commands of a fleet that turns round, where a QP's iteration count
changes with its last bits. `make_golden.py` measures it by flying each case again with its
arithmetic nudged, and stores, beside the figures, a tolerance per field of `MARGIN` times the
largest difference it saw. The test then compares every float within that tolerance, and flags
and integers exactly.
"""

import ctypes
import dataclasses
import json
import platform
from importlib.metadata import version
from pathlib import Path

import numpy as np

from fleetmpc.gcs.record import FlightRecord
from fleetmpc.lockstep.flight import run_lockstep
from fleetmpc.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).resolve().parent / "data"
GOLDEN = DATA / "golden.npz"
"""The stored figures, one array per case and field under the key ``case/field``."""
TOLERANCES = DATA / "golden_tolerances.json"
"""Per case and field: the measured sensitivity and the tolerance the test compares with."""

PLATFORM_KEY = "platform"
"""The key of the golden file's one entry that is no case: where its figures were computed."""

MARGIN = 1000.0
"""Tolerance over measured sensitivity. A nudge on the machine that writes the file perturbs
some of the operations another machine rounds differently, not all of them, so the margin is
wide; it stays narrow enough that a change of the control code by one part in 1e6 (a weight of
the QP, say) moves the smooth cases' figures 30-230 times past their tolerance
(`test_golden.py` checks that it does)."""

RELATIVE_FLOOR = 1e-13
"""Smallest tolerance, relative to the field's largest magnitude: a field that no nudge moved
may still differ by a few ulps elsewhere."""

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


def case_named(name: str) -> Case:
    """The case of `CASES` called `name`."""
    return next(c for c in CASES if c.name == name)


def case_scenario(case: Case) -> Scenario:
    """The case's scenario as the repository holds it."""
    return load_scenario(ROOT / "scenarios" / f"{case.scenario}.toml")


def fly(case: Case, scenario: Scenario | None = None) -> FlightRecord:
    """The case's lockstep run, of `scenario` if given (a variant of the case's own)."""
    scenario = case_scenario(case) if scenario is None else scenario
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


def largest_difference(a: np.ndarray, b: np.ndarray) -> float:
    """max |a - b| over the elements, NaN equal to NaN (inf where a NaN meets a number)."""
    if a.size == 0:
        return 0.0
    both_nan = np.isnan(a) & np.isnan(b)
    diff = np.abs(np.where(both_nan, 0.0, a - b))
    return float(np.max(np.where(np.isnan(diff), np.inf, diff)))


def tolerance(field: np.ndarray, sensitivity: float) -> float:
    """The tolerance of a stored float field whose nudged runs moved it by `sensitivity`."""
    scale = float(np.nanmax(np.abs(field))) if field.size and not np.isnan(field).all() else 0.0
    return max(MARGIN * sensitivity, RELATIVE_FLOOR * max(scale, 1.0))


def differences(
    name: str, actual: np.ndarray, expected: np.ndarray, atol: float | None
) -> str | None:
    """How `actual` differs from the stored `expected` of field `name`; None if it does not.

    Floats compare within `atol` (NaN equal to NaN); flags and integers compare exactly.
    """
    if actual.shape != expected.shape:
        return f"{name}: shape {actual.shape}, stored {expected.shape}"
    if actual.dtype.kind != expected.dtype.kind:
        return f"{name}: dtype {actual.dtype}, stored {expected.dtype}"
    if expected.dtype.kind != "f":
        if np.array_equal(actual, expected):
            return None
        return f"{name}: {int(np.sum(actual != expected))} element(s) differ"
    if atol is None:
        return f"{name}: no tolerance stored in {TOLERANCES.name}"
    worst = largest_difference(actual, expected)
    if worst <= atol:
        return None
    return f"{name}: differs by up to {worst:.3g}, tolerance {atol:.3g}"


def compare(
    actual: dict[str, np.ndarray], expected: dict[str, np.ndarray], atol: dict[str, float]
) -> list[str]:
    """Every way a run's arrays differ from the stored ones (empty: they match)."""
    problems = [f"{field}: missing from the run" for field in sorted(expected.keys() - actual)]
    problems += [f"{field}: not in {GOLDEN.name}" for field in sorted(actual.keys() - expected)]
    for field in sorted(expected.keys() & actual.keys()):
        diff = differences(field, actual[field], expected[field], atol.get(field))
        if diff is not None:
            problems.append(diff)
    return problems


def load_golden() -> dict[str, dict[str, np.ndarray]]:
    """The stored figures by case, then by field."""
    by_case: dict[str, dict[str, np.ndarray]] = {}
    with np.load(GOLDEN, allow_pickle=False) as data:
        for key in data.files:
            if key == PLATFORM_KEY:
                continue
            case, field = key.split("/", 1)
            by_case.setdefault(case, {})[field] = data[key]
    return by_case


def load_stored_platform() -> dict[str, str]:
    """Where the stored figures were computed (empty if the file does not say)."""
    with np.load(GOLDEN, allow_pickle=False) as data:
        return json.loads(str(data[PLATFORM_KEY])) if PLATFORM_KEY in data.files else {}


def load_tolerances() -> dict[str, dict[str, float]]:
    """The stored tolerances by case, then by field."""
    cases = json.loads(TOLERANCES.read_text())["cases"]
    return {case: {f: v["tolerance"] for f, v in fields.items()} for case, fields in cases.items()}


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
    libraries and the BLAS kernel (reported when a comparison fails, never required)."""
    return {
        "machine": platform.machine(),
        **{package: version(package) for package in ("numpy", "scipy", "osqp")},
        "blas": "; ".join(openblas_configs()) or "unknown",
    }
