"""The maths cores stay pure: the lint ban catches I/O and clocks in them."""

import subprocess
import sys

import pytest


@pytest.mark.parametrize("module", ["time", "socket", "logging", "zenoh", "rerun", "pymavlink"])
@pytest.mark.parametrize("path", ["onboard/core/probe.py", "sitl/plant.py"])
def test_core_imports_are_banned(module, path):
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "ruff",
            "check",
            "--no-cache",
            "--select",
            "TID251",
            "--stdin-filename",
            path,
            "-",
        ],
        input=f"import {module}\n",
        capture_output=True,
        text=True,
    )
    assert out.returncode == 1 and "TID251" in out.stdout


def test_runners_may_do_io():
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "ruff",
            "check",
            "--no-cache",
            "--select",
            "TID251",
            "--stdin-filename",
            "gcs/lockstep.py",
            "-",
        ],
        input="import time\n",
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout
