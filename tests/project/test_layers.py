"""The import contracts of pyproject.toml ([tool.importlinter]) hold.

Layers (each package imports only from the layers below it), the
independence of the fitting/meshing/picture stages, the pipeline's modules
in the data's order, camera readers independent of each other, and that
only tests, samples and benchmarks import ``o3drbf.synthetic``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _lint_imports() -> str:
    exe = shutil.which("lint-imports") or str(Path(sys.executable).with_name("lint-imports"))
    if not Path(exe).exists():
        pytest.skip("import-linter is not installed (pip install import-linter)")
    return exe


def _run(exe: str, config: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    args = [exe, "--no-cache"] + (["--config", str(config)] if config else [])
    return subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


def test_import_contracts_are_kept():
    out = _run(_lint_imports())
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout
    for name in ("Layers", "independent stages", "o3drbf.synthetic", "pipeline's stages", "Camera formats"):
        assert name in out.stdout


def test_an_upward_import_breaks_the_layers(tmp_path):
    # The same contracts, with the library's real `validation` at the top
    # instead of the bottom: its users now import upward and the tool says so.
    text = (ROOT / "pyproject.toml").read_text()
    moved = text.replace('"o3drbf.cli",\n', '"o3drbf.validation",\n    "o3drbf.cli",\n', 1).replace(
        '"o3drbf.validation | o3drbf.progress | o3drbf.startup"', '"o3drbf.progress | o3drbf.startup"', 1
    )
    assert moved != text
    config = tmp_path / "pyproject.toml"
    config.write_text(moved)
    out = _run(_lint_imports(), config)
    assert out.returncode != 0
    assert "is not allowed to import o3drbf.validation" in out.stdout


def test_every_package_folder_is_installed():
    # setuptools installs only the packages pyproject.toml lists: a new subpackage left out of the
    # list imports in the checkout and fails in a wheel.
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "o3drbf").rglob("__init__.py")}
    assert folders - listed == set(), f"add to [tool.setuptools] packages in pyproject.toml: {sorted(folders - listed)}"
