"""One run of a sweep, in a worker: the scenario built from its spec, flown, its row.

The row is `fleetmpc.lockstep.suite.fly_row`'s (the suite's runs are flown the same way) with the
run's identity, the values set, its status and the code's version added; `fleetmpc.lockstep.
sweep_store` gives its columns and their types.
"""

import functools
import importlib.metadata
import json
import subprocess
from pathlib import Path

from fleetmpc.lockstep.suite import flew, fly_row
from fleetmpc.lockstep.sweep_grid import RunSpec, build_run

__all__ = ["code_version", "fly_spec", "spec_row"]


@functools.cache
def code_version() -> str:
    """The package's version, with the commit of its checkout when it runs from one (``+g`` and
    12 hex digits, ``.dirty`` when files differ from it): what a row was flown with."""
    try:
        version = importlib.metadata.version("fleetmpc")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    try:
        commit = _git("rev-parse", "--short=12", "HEAD")
        dirty = _git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return version
    return f"{version}+g{commit}{'.dirty' if dirty else ''}"


def _git(*args: str) -> str:
    """What git says, run in the checkout this module is in."""
    here = Path(__file__).resolve().parent
    done = subprocess.run(
        ["git", "-C", str(here), *args], capture_output=True, text=True, timeout=10, check=True
    )
    return done.stdout.strip()


def spec_row(spec: RunSpec) -> dict:
    """What a run's row takes from its spec: identity and inputs; "values" holds the values set
    by path (a column each in the table)."""
    return {
        "run_id": spec.run_id,
        "file": spec.file,
        "seed": spec.seed,
        "learning": spec.learning,
        "faults": spec.fault_file,
        "overrides": json.dumps(spec.values, sort_keys=True),
        "values": spec.values,
    }


def fly_spec(spec: RunSpec) -> dict:
    """Fly one run of a sweep: its row (the numbers, or its error), status "ok" or "failed"."""
    row = fly_row(
        lambda: build_run(spec),
        file=spec.file,
        seed=spec.seed,
        learning=spec.learning,
    )
    status = "ok" if flew(row) else "failed"
    return {**row, **spec_row(spec), "status": status, "version": code_version()}
