"""Shared fixtures: scenarios are loaded from the repository's scenarios/ folder."""

from pathlib import Path

import pytest

from protocol.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def paper() -> Scenario:
    return load_scenario(ROOT / "scenarios" / "paper.toml")


@pytest.fixture(scope="session")
def paper_strict() -> Scenario:
    return load_scenario(ROOT / "scenarios" / "paper-strict.toml")
