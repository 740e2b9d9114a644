"""Make a folder where `fleetmpc` is one package tree, for tools that walk a package's folder.

pyproject.toml maps each part of `fleetmpc` to a top-level folder of the repository
(`[tool.setuptools.package-dir]`); import-linter finds a package's modules by walking its one
folder. This writes VIEW/fleetmpc/ with links to the root package's files and to each part's
folder, as the mapping says, so that `PYTHONPATH=VIEW lint-imports` sees the whole package.

    python tools/import_view.py build/import-view
"""

import shutil
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make_view(view: Path) -> None:
    """(Re)create VIEW/fleetmpc from pyproject.toml's package-dir mapping."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"
    ]
    package = view / "fleetmpc"
    shutil.rmtree(view, ignore_errors=True)
    package.mkdir(parents=True)
    for source in sorted((ROOT / mapping["fleetmpc"]).glob("*.py")):
        (package / source.name).symlink_to(source)
    for name, folder in mapping.items():
        if name != "fleetmpc":
            (package / name.removeprefix("fleetmpc.")).symlink_to(ROOT / folder)


if __name__ == "__main__":
    make_view(Path(sys.argv[1]))
