"""Shared fixtures: scenarios from the repository's scenarios/ folder, supervised processes.

The suite runs numpy on one OpenBLAS kernel whatever the CPU (x86-64 with AVX2), set here before
anything loads numpy: the golden figures (tests/sim/test_golden.py) are compared to 1e-9, and
another kernel rounds the QP's linear algebra differently (a few 1e-3 after a sharp corner).
Child processes inherit it.
"""

import os
import sys

if "numpy" in sys.modules:  # pragma: no cover - a plugin loaded numpy first
    raise RuntimeError("numpy was loaded before tests/conftest.py could pick its BLAS kernel")
os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

from collections.abc import Iterator  # noqa: E402
from pathlib import Path

import pytest
from helpers import ProcessGroup

from fleetmpc.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def paper() -> Scenario:
    return load_scenario(ROOT / "scenarios" / "paper.toml")


@pytest.fixture(scope="session")
def paper_strict() -> Scenario:
    return load_scenario(ROOT / "scenarios" / "paper-strict.toml")


@pytest.fixture
def processes(tmp_path) -> Iterator[ProcessGroup]:
    """Start child processes (logs in ``tmp_path/logs``); every one is stopped by PID at the end."""
    group = ProcessGroup(tmp_path / "logs")
    try:
        yield group
    finally:
        group.stop_all()
