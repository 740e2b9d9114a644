"""Write ``data/golden.npz`` and ``data/golden_tolerances.json``: the figures `test_golden.py`
compares the lockstep runs with, and how closely (docs/testing.md).

Run from the repository:

    .venv/bin/python tests/lockstep/make_golden.py

Only when a change is meant to change the figures: see docs/testing.md. It flies every case of
`golden.CASES` once for its figures, then again under each nudge of its arithmetic, and stores
per field `golden.MARGIN` times the largest difference a nudge made. The nudges: every vehicle's
initial state one ulp up and one down, the target's start one ulp up, and, on x86-64 with
OpenBLAS, every other BLAS kernel of `KERNELS`
(another rounding order in every product; a kernel the CPU cannot run is skipped). The archive is
written byte for byte the same from the same figures (sorted keys, a fixed timestamp), so
regenerating it after a change that moves no figure leaves it unchanged in git.
"""

import argparse
import dataclasses
import io
import json
import os
import platform
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from golden import (
    CASES,
    GOLDEN,
    MARGIN,
    PLATFORM_KEY,
    RELATIVE_FLOOR,
    TOLERANCES,
    Case,
    case_scenario,
    fly,
    largest_difference,
    platform_fingerprint,
    record_arrays,
    tolerance,
)

from fleetmpc.scenario import Scenario

ZIP_TIMESTAMP = (1980, 1, 1, 0, 0, 0)
"""The archive's member timestamp: the earliest a zip file holds, the same every time."""

KERNELS = ("Haswell", "Sandybridge", "Prescott")
"""OpenBLAS kernels (OPENBLAS_CORETYPE) that round differently from one another on x86-64."""

Figures = dict[str, dict[str, np.ndarray]]
"""Arrays by case, then by field."""


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write `arrays` as a compressed ``.npz`` that `numpy.load` reads, reproducibly."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for key in sorted(arrays):
            member = zipfile.ZipInfo(f"{key}.npy", date_time=ZIP_TIMESTAMP)
            member.compress_type = zipfile.ZIP_DEFLATED
            with archive.open(member, "w") as f:
                np.lib.format.write_array(f, arrays[key], allow_pickle=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buffer.getvalue())


def flat(figures: Figures) -> dict[str, np.ndarray]:
    return {f"{case}/{field}": a for case, fields in figures.items() for field, a in fields.items()}


def unflat(arrays) -> Figures:
    figures: Figures = {}
    for key in arrays.files:
        case, field = key.split("/", 1)
        figures.setdefault(case, {})[field] = arrays[key]
    return figures


def _ulp(values, toward: float) -> tuple[float, ...]:
    return tuple(float(np.nextafter(x, toward)) for x in values)


def initial_states_one_ulp(toward: float):
    """A nudge: every vehicle's initial position and heading one ulp toward `toward`."""

    def nudge(scenario: Scenario) -> Scenario:
        vehicles = tuple(
            dataclasses.replace(v, initial=_ulp(v.initial, toward)) for v in scenario.vehicles
        )
        return dataclasses.replace(scenario, vehicles=vehicles)

    return nudge


def target_start_one_ulp_up(scenario: Scenario) -> Scenario:
    """A nudge: the target's start one ulp up."""
    target = dataclasses.replace(scenario.target, start_m=_ulp(scenario.target.start_m, np.inf))
    return dataclasses.replace(scenario, target=target)


def fly_all(nudge=None) -> Figures:
    """Every case's arrays, each scenario passed through `nudge` first if given."""
    figures: Figures = {}
    for case in CASES:
        scenario = case_scenario(case)
        figures[case.name] = record_arrays(fly(case, nudge(scenario) if nudge else scenario))
    return figures


def fly_under_kernel(kernel: str) -> Figures | None:
    """Every case's arrays in a process on OpenBLAS kernel `kernel`; None if it cannot run."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "figures.npz"
        env = {**os.environ, "OPENBLAS_CORETYPE": kernel}
        done = subprocess.run(
            [sys.executable, __file__, "--figures-to", str(out)], env=env, capture_output=True
        )
        if done.returncode != 0 or not out.exists():
            print(f"  kernel {kernel}: skipped (exit {done.returncode})")
            return None
        with np.load(out) as arrays:
            return unflat(arrays)


def nudged_runs() -> dict[str, Figures]:
    """Every case flown under each nudge, by the nudge's description."""
    runs = {
        "every vehicle's initial state one ulp up": fly_all(initial_states_one_ulp(np.inf)),
        "every vehicle's initial state one ulp down": fly_all(initial_states_one_ulp(-np.inf)),
        "the target's start one ulp up": fly_all(target_start_one_ulp_up),
    }
    if platform.machine() in ("x86_64", "AMD64"):
        here = os.environ.get("OPENBLAS_CORETYPE")
        for kernel in KERNELS:
            if kernel != here and (figures := fly_under_kernel(kernel)) is not None:
                runs[f"OpenBLAS kernel {kernel}"] = figures
    return runs


def tolerances(figures: Figures, runs: dict[str, Figures]) -> dict:
    """Per case and float field: the largest difference any nudge made, and the tolerance."""
    cases: dict[str, dict] = {}
    for case in CASES:
        fields = {}
        for field, stored in sorted(figures[case.name].items()):
            if stored.dtype.kind != "f":
                continue
            moved = max(largest_difference(r[case.name][field], stored) for r in runs.values())
            fields[field] = {"sensitivity": moved, "tolerance": tolerance(stored, moved)}
        cases[case.name] = fields
    return {
        "margin": MARGIN,
        "relative_floor": RELATIVE_FLOOR,
        "nudges": sorted(runs),
        "platform": platform_fingerprint(),
        "cases": cases,
    }


def report(case: Case, fields: dict) -> str:
    worst = max(fields.items(), key=lambda kv: kv[1]["sensitivity"])
    return f"{case.name}: most sensitive field {worst[0]} ({worst[1]['sensitivity']:.2g})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--figures-to", type=Path, help="only fly the cases and write them here")
    args = parser.parse_args()
    if args.figures_to:
        write_npz(args.figures_to, flat(fly_all()))
        return
    figures = fly_all()
    print(f"flew {len(CASES)} cases; now under nudges of their arithmetic")
    table = tolerances(figures, nudged_runs())
    arrays = flat(figures)
    arrays[PLATFORM_KEY] = np.array(json.dumps(platform_fingerprint(), sort_keys=True))
    write_npz(GOLDEN, arrays)
    TOLERANCES.write_text(json.dumps(table, indent=1, sort_keys=True) + "\n")
    for case in CASES:
        print(report(case, table["cases"][case.name]))
    print(f"nudges: {'; '.join(table['nudges'])}")
    print(f"wrote {GOLDEN} and {TOLERANCES.name}")


if __name__ == "__main__":
    main()
