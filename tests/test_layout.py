"""The layers hold: import-linter's contracts (pyproject.toml) pass on the tree and catch a
module that breaks them."""

import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def _package_copy(tmp_path: Path) -> Path:
    """A copy of the package as one folder (tmp/fleetmpc), as pyproject's package-dir maps it."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        from import_view import make_view
    finally:
        sys.path.remove(str(ROOT / "tools"))
    return make_view(tmp_path, copy=True)


def _lint_imports(where: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache", str(ROOT / "pyproject.toml")],
        cwd=where,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_tree_keeps_every_contract(tmp_path):
    _package_copy(tmp_path)
    done = _lint_imports(tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.parametrize(
    ("module", "source", "contract"),
    [
        ("onboard/core/probe.py", "import time\n", "the maths core does no I/O"),
        ("onboard/core/probe.py", "import zenoh\n", "the maths core does no I/O"),
        ("sitl/plant.py", "import socket\n", "the truth plant and the target script"),
        ("sitl/vehicle_server.py", "from fleetmpc.onboard.core import dekf\n", "knows nothing"),
        ("protocol/probe.py", "from fleetmpc.onboard.core import agent\n", "protocol holds"),
        ("gcs/probe.py", "from fleetmpc.launch import up\n", "layers"),
    ],
)
def test_a_module_that_breaks_a_layer_is_caught(tmp_path, module, source, contract):
    package = _package_copy(tmp_path)
    with (package / module).open("a") as f:  # added to the module (or a new one)
        f.write(source)
    done = _lint_imports(tmp_path)
    assert done.returncode == 1, done.stdout
    assert contract in done.stdout.split("Broken contracts")[-1], done.stdout


def test_a_wheel_installs_only_the_fleetmpc_import_name(tmp_path):
    """`pip install .` puts one top-level name in site-packages: `fleetmpc`."""
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q"]
        + ["-w", str(tmp_path), str(ROOT)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    (wheel,) = tmp_path.glob("fleetmpc-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        top = {name.split("/")[0] for name in archive.namelist()}
    assert {t for t in top if not t.endswith(".dist-info")} == {"fleetmpc"}
    assert any(name.startswith("fleetmpc/onboard/core/") for name in archive.namelist())


MODULE_LINES_MAX = 600
"""No module of the product is longer than this. A prompt to look, not a rule to split by: a
module this long may hold more than one concept, and then it is split where the concepts part
(docs/design.md, "Layout"), never at a line count. The MAVLink autopilot link, with the engage
sequence that retries each step with the autopilot's reasons, is one concept at 573 lines."""


def test_no_module_of_the_product_is_over_600_lines():
    """Every module of every folder the package is installed from (pyproject's package-dir)."""
    with (ROOT / "pyproject.toml").open("rb") as f:
        folders = set(tomllib.load(f)["tool"]["setuptools"]["package-dir"].values())
    modules = [m for folder in sorted(folders) for m in sorted((ROOT / folder).rglob("*.py"))]
    assert len(modules) > 50, modules  # (the folders were found)
    long = {str(m.relative_to(ROOT)): n for m in modules if (n := _lines(m)) > MODULE_LINES_MAX}
    assert long == {}, f"over {MODULE_LINES_MAX} lines: {long}"


def _lines(path: Path) -> int:
    with path.open(encoding="utf-8") as f:
        return sum(1 for _ in f)


def test_the_docker_image_copies_every_package_folder():
    """The image installs the project from the folders it copies: a folder of the package-dir
    mapping left out fails the compose build ("package directory ... does not exist")."""
    folders = tomllib.loads(Path("pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    copied = {
        line.split()[1].rstrip("/")
        for line in Path("docker/Dockerfile").read_text().splitlines()
        if line.startswith("COPY ")
    }
    assert set(folders.values()) - copied == set()
