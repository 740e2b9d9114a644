"""The maths cores stay pure: the lint ban catches I/O and clocks in them."""

import subprocess
import sys

import pytest


def _ban_check(path: str, source: str) -> subprocess.CompletedProcess:
    """Run ruff's banned-import rule on `source` as if it lived at `path`."""
    return subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--select", "TID251"]
        + ["--stdin-filename", path, "-"],
        input=source,
        capture_output=True,
        text=True,
    )


@pytest.mark.parametrize("module", ["time", "socket", "logging", "zenoh", "rerun", "pymavlink"])
@pytest.mark.parametrize("path", ["onboard/core/probe.py", "sitl/plant.py"])
def test_core_imports_are_banned(module, path):
    out = _ban_check(path, f"import {module}\n")
    assert out.returncode == 1 and "TID251" in out.stdout


def test_runners_may_do_io():
    out = _ban_check("sim/lockstep.py", "import time\n")
    assert out.returncode == 0, out.stdout
