"""Shared fixtures: scenarios from the repository's scenarios/ folder, supervised processes.

The suite runs on whatever BLAS kernel and CPU the machine has: no test depends on their last
bits (docs/testing.md).
"""

from collections.abc import Iterator
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
