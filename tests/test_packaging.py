"""The wheel holds one top-level package, o3drbf, with the viewer inside it."""

import subprocess
import sys
import zipfile

import pytest

from conftest import REPO


def test_wheel_installs_the_viewer_inside_the_package(tmp_path):
    pytest.importorskip("setuptools")
    proc = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path), str(REPO)],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = tmp_path.glob("o3drbf-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"o3drbf"}, top
    for module in ("o3drbf/viewers/app.py", "o3drbf/viewers/refit.py", "o3drbf/cli/__main__.py", "o3drbf/solvers/fast.py"):
        assert module in names, module
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("METADATA"))).decode()
    assert "Requires-Dist: pyvista" in meta  # compare and view work after a plain pip install
