"""``python -m build`` makes a wheel and an sdist that install into a fresh venv and work there.

The build runs on a copy of the repository's tracked files (nothing is written
into the checkout).  Each fresh venv (``--without-pip``) gets o3drbf from the
wheel or the sdist with ``pip --python VENV install --no-deps``; the
dependencies (Open3D, NumPy, ...) come from this interpreter's site-packages
through a ``.pth`` file pointing at a folder of links to them, leaving out
the editable o3drbf, so the smoke test can only import the installed copy.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO

pytest.importorskip("build")
pytest.importorskip("setuptools")

#: Site-packages entries of the editable o3drbf install, hidden from the fresh venvs.
EDITABLE = ("o3drbf", "__editable__", "_o3drbf", "__pycache__")


def run(cmd, timeout=300, **kw):
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=timeout, **kw)
    assert proc.returncode == 0, f"{cmd}: exit {proc.returncode}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc


def source_copy(dest: Path) -> Path:
    """The repository's tracked files as they are in the working tree (no untracked links, no build output)."""
    try:
        listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("needs a git checkout (git ls-files) to copy the tracked files")
    for name in filter(None, listed.decode().split("\0")):
        src = REPO / name
        if src.is_file() and not src.is_symlink():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


@pytest.fixture(scope="module")
def dist(tmp_path_factory):
    """(wheel, sdist) built by ``python -m build --no-isolation`` (the wheel is built from the sdist)."""
    root = tmp_path_factory.mktemp("build")
    src = source_copy(root / "src")
    run([sys.executable, "-m", "build", "--no-isolation", "--outdir", root / "dist", src])
    (wheel,) = (root / "dist").glob("o3drbf-*.whl")
    (sdist,) = (root / "dist").glob("o3drbf-*.tar.gz")
    return wheel, sdist


@pytest.fixture(scope="module")
def deps(tmp_path_factory) -> Path:
    """A folder of links to this interpreter's installed packages, without the editable o3drbf."""
    folder = tmp_path_factory.mktemp("deps")
    for site in {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}:
        for entry in Path(site).iterdir():
            if entry.name.startswith(EDITABLE) or entry.suffix == ".pth" or (folder / entry.name).exists():
                continue
            (folder / entry.name).symlink_to(entry)
    return folder


def fresh_venv(path: Path, package: Path, deps: Path) -> Path:
    """A venv without pip holding only ``package`` (wheel or sdist); the dependencies exposed after the install."""
    run([sys.executable, "-m", "venv", "--without-pip", path])
    python = path / "bin" / "python"
    site = Path(run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    pth = site / "o3drbf_test_dependencies.pth"
    if package.name.endswith(".tar.gz"):
        pth.write_text(f"{deps}\n")  # the sdist's build needs setuptools in that venv (--no-build-isolation)
    # no PYTHONPATH: with the repository on it, pip would find o3drbf "already satisfied" and install nothing
    run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", "--no-index", "--no-build-isolation", package],
        cwd=path, env={k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")})
    pth.write_text(f"{deps}\n")
    return path


def reuse_numba_cache(site: Path) -> int:
    """Copy the checkout's Numba cache next to the installed sources; returns the files copied.

    Numba keys its cache on a hash of the source file's bytes, so an entry is
    used only where the installed file is identical to the checkout's, and
    anything else is compiled as usual.  Without this the smoke
    reconstruction spends 30-40 s compiling (measured at load 5-7).
    """
    copied = 0
    for cached in (REPO / "o3drbf").rglob("__pycache__/*.nb[ic]"):
        target = site / "o3drbf" / cached.relative_to(REPO / "o3drbf")
        if target.parent.parent.is_dir():
            target.parent.mkdir(exist_ok=True)
            shutil.copy2(cached, target)
            copied += 1
    return copied


def smoke_env(venv: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", O3DRBF_NO_PROGRESS="1", OMP_NUM_THREADS="2")
    return env


def test_wheel_installs_the_viewer_inside_the_package(dist):
    wheel, _ = dist
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"o3drbf"}, top
    for module in ("o3drbf/viewers/app.py", "o3drbf/viewers/refit.py", "o3drbf/cli/__main__.py", "o3drbf/solvers/fast/__init__.py"):
        assert module in names, module
    meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("METADATA"))).decode()
    assert "Requires-Dist: pyvista" in meta  # compare and view work after a plain pip install
    entry = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith("entry_points.txt"))).decode()
    assert "o3drbf = o3drbf.cli:run" in entry


def test_sdist_holds_the_sources_the_wheel_is_built_from(dist):
    _, sdist = dist
    names = {n.split("/", 1)[1] for n in tarfile.open(sdist).getnames() if "/" in n}
    for name in ("pyproject.toml", "README.md", "viewers/app.py", "o3drbf/__init__.py", "o3drbf/cli/commands.py", "o3drbf/rbf/compiled.py"):
        assert name in names, name


@pytest.fixture(scope="module")
def tiny_sample(tmp_path_factory) -> Path:
    """800 points on the unit sphere with their normals, as .xyzn text (no o3drbf involved)."""
    d = np.random.default_rng(7).normal(size=(800, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    path = tmp_path_factory.mktemp("sample") / "sphere.xyzn"
    np.savetxt(path, np.hstack([d, d]), fmt="%.6f")
    return path


@pytest.mark.parametrize("kind", ["wheel", "sdist"])
def test_installed_package_runs_from_the_fresh_venv(kind, dist, deps, tiny_sample, tmp_path):
    import open3d as o3d

    package = dist[0] if kind == "wheel" else dist[1]
    venv = fresh_venv(tmp_path / "venv", package, deps)
    python, env = venv / "bin" / "python", smoke_env(venv)
    site = run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], env=env).stdout.strip()
    where = run([python, "-c", "import o3drbf, o3drbf.viewers.app as app; print(o3drbf.__file__); print(app.__file__); print(o3drbf.__version__)"],
                env=env, cwd=tmp_path).stdout.split()
    assert where[0] == str(Path(site) / "o3drbf" / "__init__.py"), where  # the installed copy, not the repository
    assert where[1] == str(Path(site) / "o3drbf" / "viewers" / "app.py"), where
    assert where[2] in package.name
    assert "reconstruct" in run([venv / "bin" / "o3drbf", "--help"], env=env, cwd=tmp_path).stdout
    assert "--methods" in run([venv / "bin" / "o3drbf", "compare", "--help"], env=env, cwd=tmp_path).stdout
    if kind == "sdist":
        return  # the same code as the wheel's (built from this sdist): one reconstruction is enough
    reuse_numba_cache(Path(site))
    out = tmp_path / "sphere.ply"
    proc = run([venv / "bin" / "o3drbf", "reconstruct", tiny_sample, "-o", out, "--surface-count", "300", "--resolution", "24"],
               env=env, cwd=tmp_path)
    assert "watertight       yes" in proc.stdout, proc.stdout
    mesh = o3d.io.read_triangle_mesh(str(out))
    radius = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert len(mesh.triangles) > 500 and np.abs(radius - 1.0).max() < 0.05, (len(mesh.triangles), radius.min(), radius.max())
