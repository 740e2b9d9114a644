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


def make_view(view: Path, *, copy: bool = False) -> Path:
    """(Re)create VIEW/fleetmpc from pyproject.toml's package-dir mapping, of links (or, with
    `copy`, of copies that can be changed without touching the tree); the package's folder."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-dir"
    ]
    package = view / "fleetmpc"
    shutil.rmtree(view, ignore_errors=True)
    package.mkdir(parents=True)
    root_files = sorted((ROOT / mapping["fleetmpc"]).glob("*.py"))
    parts = [(source, package / source.name) for source in root_files]
    parts += [
        (ROOT / folder, package / name.removeprefix("fleetmpc."))
        for name, folder in mapping.items()
        if name != "fleetmpc"
    ]
    for source, target in parts:
        if not copy:
            target.symlink_to(source)
        elif source.is_dir():
            shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(source, target)
    return package


if __name__ == "__main__":
    make_view(Path(sys.argv[1]))
