"""Fault injection: bad inputs and failures never lose data nor pass silently (issue 14).

Every case asserts the exception type or exit status, that the message names
the problem, that no file in the working folder changed (SHA-256 before and
after) and that no temporary file was left behind.
"""

from __future__ import annotations

import gc
import hashlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from o3drbf.cameras.model import load_cameras, load_range_scans, referenced_files
from o3drbf.cli.commands import main
from o3drbf.io.files import (
    MESH_FORMATS,
    atomic_path,
    check_mesh_precision,
    check_output,
    check_outputs,
    live_temporary_files,
    read_points,
    signal_cleanup,
    write_mesh,
    write_points,
)
from o3drbf.prep.duplicates import merge_duplicates
from o3drbf.rbf import compiled
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.surface import ImplicitSurface
from o3drbf.synthetic.shapes import Sphere

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable


# -- helpers ----------------------------------------------------------------------------


def snapshot(folder: Path) -> dict:
    """SHA-256 (or 'dir') of every entry under ``folder``."""
    out = {}
    for p in sorted(folder.rglob("*")):
        out[str(p.relative_to(folder))] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def temporaries(folder: Path) -> list[str]:
    """Files left by atomic_path (``.stem.XXXX.suffix``) or the precision probe."""
    return [p.name for p in folder.rglob(".*") if p.is_file()]


def sphere_mesh(offset: float = 0.0, resolution: int = 8) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) + offset)
    return m


def tiny_surface() -> ImplicitSurface:
    rng = np.random.default_rng(3)
    c = rng.normal(size=(12, 3)) * 0.5
    return ImplicitSurface(MultiOrder(), c, rng.normal(size=12), np.array([0.1]))


PLY_HEAD = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"


def ply_text(points) -> str:
    return PLY_HEAD.format(n=len(points)) + "".join(f"{x} {y} {z}\n" for x, y, z in points)


def put(path: Path, data) -> Path:
    """Write ``data`` (str or bytes) to ``path``; return ``path``."""
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


GOOD_PTS = np.random.default_rng(0).normal(size=(20, 3))


# -- 1. input point files ---------------------------------------------------------------


def _binary_ply(tmp, cut):
    p = tmp / "cut.ply"
    write_points(p, GOOD_PTS)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - cut])
    return p


def _ascii_ply_cut(tmp, keep=12):
    """An ASCII PLY with normals announcing 20 vertices, cut inside vertex line ``keep + 1``."""
    head = PLY_HEAD.replace("property float z\n", "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n")
    rows = "".join(f"{x} {y} {z} 0 0 1\n" for x, y, z in GOOD_PTS)
    cut = sum(len(r) + 1 for r in rows.splitlines()[:keep]) + 5
    return put(tmp / "cut_ascii.ply", head.format(n=len(GOOD_PTS)) + rows[:cut])


POINT_CASES = {
    "missing": (lambda t: t / "nope.ply", FileNotFoundError, "not found"),
    "folder": (lambda t: (t / "d.ply").mkdir() or t / "d.ply", ValueError, "is a folder"),
    "bad extension": (lambda t: put(t / "p.txt", "1 2 3\n"), ValueError, "unsupported extension"),
    "empty ply": (lambda t: put(t / "e.ply", b""), ValueError, "no points \\(truncated or empty file\\)"),
    "header only ply": (lambda t: put(t / "h.ply", PLY_HEAD.format(n=10)), ValueError, "no points \\(truncated or empty file\\)"),
    "zero vertex ply": (lambda t: put(t / "z.ply", PLY_HEAD.format(n=0)), ValueError, "no points"),
    "no end_header": (lambda t: put(t / "n.ply", "ply\nformat ascii 1.0\nelement vertex 3\n"), ValueError, "truncated or empty"),
    "not a ply": (lambda t: put(t / "g.ply", b"\x89PNG garbage"), ValueError, "not a PLY"),
    "binary ply truncated": (lambda t: _binary_ply(t, 100), ValueError, "truncated"),
    "ascii ply truncated": (_ascii_ply_cut, ValueError, "truncated file: the header promises 20 vertices but only 12 complete"),
    "binary ply cut to header": (lambda t: _binary_ply(t, 20 * 24), ValueError, "truncated"),
    "ply huge vertex count": (lambda t: put(t / "b.ply", PLY_HEAD.format(n=10**12) + "1 2 3\n"), ValueError, "corrupt"),
    "ply with nan": (lambda t: put(t / "nan.ply", ply_text([[0, 0, 0], [float("nan"), 1, 2], [1, 1, 1]])), ValueError, "NaN"),
    "xyz mixed columns": (lambda t: put(t / "m.xyz", "0 0 0\n1 1 1\n2 2\n3 3 3\n"), ValueError, "line 3.*mixed column"),
    "xyz not a number": (lambda t: put(t / "w.xyz", "0 0 0\n1 x 1\n"), ValueError, "line 2.*not a number"),
    "xyz only comments": (lambda t: put(t / "c.xyz", "# nothing\n\n"), ValueError, "no points"),
    "xyz empty": (lambda t: put(t / "e.xyz", ""), ValueError, "no points"),
    "xyzn three columns": (lambda t: put(t / "n.xyzn", "0 0 0\n1 1 1\n"), ValueError, "line 1: 3 columns"),
    "xyz infinite": (lambda t: put(t / "i.xyz", "0 0 0\ninf 1 1\n"), ValueError, "infinite"),
}


@pytest.mark.parametrize("case", sorted(POINT_CASES))
def test_bad_point_file_is_refused_and_untouched(tmp_path, case):
    make, exc, pattern = POINT_CASES[case]
    path = make(tmp_path)
    before = snapshot(tmp_path)
    with pytest.raises(exc, match=pattern) as info:
        read_points(path)
    assert "\n" not in str(info.value)
    assert str(Path(path).name) in str(info.value)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


# -- 1b. lidar files (LAS, LAZ, E57) -------------------------------------------------------


def _las(t, name="s.las", cut=0):
    from o3drbf.synthetic.lidar import write_las

    p = write_las(t / name, GOOD_PTS)
    if cut:
        data = p.read_bytes()
        p.write_bytes(data[: len(data) - cut] if cut > 0 else data[:-cut])
    return p


def _e57(t, rotation=(1.0, 0.0, 0.0, 0.0), translation=(0.0, 0.0, 5.0), cut=0, poses=True):
    """Two scans, 'north' and 'south'; the second gets ``rotation`` and ``translation``."""
    from o3drbf.synthetic.lidar import write_e57

    scans = [{"name": "north", "points": GOOD_PTS[:10], "rotation": (1.0, 0.0, 0.0, 0.0), "translation": (0.0, 0.0, -5.0)},
             {"name": "south", "points": GOOD_PTS[10:], "rotation": rotation, "translation": translation}]
    if not poses:
        for scan in scans:
            scan["rotation"] = scan["translation"] = None
    p = write_e57(t / "scans.e57", scans)
    if cut:
        data = p.read_bytes()
        p.write_bytes(data[: len(data) - cut])
    return p


NAN = float("nan")
LIDAR_CASES = {
    "las truncated": (lambda t: _las(t, cut=100), "truncated file"),
    "las cut inside the header": (lambda t: _las(t, cut=-150), "not a readable LAS file.*truncated or corrupt"),
    "las empty": (lambda t: put(t / "e.las", b""), "no points"),
    "las not a las": (lambda t: put(t / "g.las", b"\x89PNG garbage" * 30), "not a readable LAS file"),
    "laz truncated": (lambda t: _las(t, "s.laz", cut=120), "truncated or corrupt point data"),
    "e57 truncated": (lambda t: _e57(t, cut=600), "not a readable E57 file.*truncated or corrupt"),
    "e57 not an e57": (lambda t: put(t / "g.e57", b"garbage" * 200), "not a readable E57 file"),
    "e57 zero quaternion": (lambda t: _e57(t, rotation=(0.0, 0.0, 0.0, 0.0)), "scan 1 'south': quaternion .* unit quaternion"),
    "e57 long quaternion": (lambda t: _e57(t, rotation=(1.0, 1.0, 0.0, 0.0)), "scan 1 'south': quaternion .* unit quaternion"),
}
#: Poses libe57 cannot store (it writes no NaN and reads an overflowing number as +-DBL_MAX): the
#: second scan's pose as the header reader returns it.
BAD_POSES = {
    "nan rotation": {"rotation": np.array([NAN, 0.0, 0.0, 1.0])},
    "nan translation": {"translation": np.array([0.0, NAN, 5.0])},
    "infinite translation": {"translation": np.array([np.inf, 0.0, 5.0])},
    "overflowed translation": {"translation": np.array([np.finfo(float).max, 0.0, 5.0])},
}


def _poison_second_pose(monkeypatch, change):
    import dataclasses

    import o3drbf.cameras.lidar as lidar

    real = lidar.e57_scans
    monkeypatch.setattr(lidar, "e57_scans", lambda path: [s if s.index != 1 else dataclasses.replace(s, **change) for s in real(path)])


@pytest.mark.parametrize("case", sorted(LIDAR_CASES))
def test_bad_lidar_file_is_one_line_and_untouched(tmp_path, case):
    pytest.importorskip("laspy")
    pytest.importorskip("pye57")
    from o3drbf.pointset import read_input

    make, pattern = LIDAR_CASES[case]
    path = make(tmp_path)
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=pattern) as info:
        read_input(path)
    assert "\n" not in str(info.value) and Path(path).name in str(info.value)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


@pytest.mark.parametrize("case", sorted(BAD_POSES))
def test_e57_scan_with_a_non_finite_pose_is_refused_naming_the_scan(tmp_path, monkeypatch, capsys, case):
    pytest.importorskip("pye57")
    from o3drbf.pointset import read_input

    path = _e57(tmp_path)
    before = snapshot(tmp_path)
    _poison_second_pose(monkeypatch, BAD_POSES[case])
    pattern = "scans.e57, scan 1 'south': the pose has NaN or infinite values"
    with pytest.raises(ValueError, match=pattern) as info:
        read_input(path)
    assert "\n" not in str(info.value)
    for extra in ([], TILED):
        assert main(["reconstruct", str(path), "-o", str(tmp_path / "out.ply"), *SMALL, *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and pattern in err and "Traceback" not in err
        assert snapshot(tmp_path) == before and not temporaries(tmp_path)


TILED = ["--tiles", "2", "--scheduler", "synchronous"]  # the file read chunk by chunk (cameras.lidar.LidarPoints)


@pytest.mark.parametrize("tiled", [False, True], ids=["untiled", "tiles"])
@pytest.mark.parametrize("case", ["las truncated", "laz truncated", "e57 truncated", "e57 zero quaternion"])
def test_cli_bad_lidar_file_exits_2_and_writes_nothing(tmp_path, capsys, case, tiled):
    pytest.importorskip("laspy")
    pytest.importorskip("pye57")
    make, pattern = LIDAR_CASES[case]
    path = make(tmp_path)
    before = snapshot(tmp_path)
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "out.ply"), *SMALL, *(TILED if tiled else [])]) == 2
    err = capsys.readouterr().err.strip()
    import re

    assert len(err.splitlines()) == 1 and re.search(pattern, err) and "Traceback" not in err
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


def test_e57_without_poses_is_read_as_points_and_says_so_in_one_line(tmp_path, capsys):
    pytest.importorskip("pye57")
    from o3drbf.pointset import read_input

    path = _e57(tmp_path, poses=False)
    data = read_input(path)
    assert data.cameras is None and data.point_camera is None
    np.testing.assert_allclose(data.points, GOOD_PTS, atol=1e-12)  # the file's frame
    # the command line goes on without free space, says so once, and writes the mesh
    points, normals = Sphere(1.0).sample(400, seed=4)
    from o3drbf.synthetic.lidar import write_e57

    write_e57(path, [{"name": "merged", "points": points, "rotation": None, "translation": None}])
    out = tmp_path / "out.ply"
    assert main(["reconstruct", str(path), "-o", str(out), *SMALL]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "no pose" in line]
    assert len(said) == 1 and "'merged'" in said[0] and "no free-space constraints" in said[0]
    assert o3d.io.read_triangle_mesh(str(out)).is_watertight()


@pytest.mark.parametrize("suffix,package", [(".las", "laspy"), (".laz", "lazrs"), (".e57", "pye57")])
def test_missing_lidar_library_names_the_install(tmp_path, capsys, monkeypatch, suffix, package):
    path = put(tmp_path / f"scan{suffix}", b"not read")
    before = snapshot(tmp_path)
    monkeypatch.setitem(sys.modules, package, None)  # import fails as if not installed
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "out.ply"), *SMALL]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"needs the {package} package" in err and "pip install 'o3drbf[lidar]'" in err
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


# -- 2. camera files ----------------------------------------------------------------------

CAM = {"K": [[100, 0, 50], [0, 100, 50], [0, 0, 1]], "R": np.eye(3).tolist(), "t": [0, 0, 3], "width": 100, "height": 100}


def _json(t, data, name="c.json"):
    p = t / name
    p.write_text(json.dumps(data))
    return p


def _bundler(t, text):
    p = t / "bundle.out"
    p.write_text(text)
    return p


def _conf(t, scan_text=None, line="bmesh a.ply 0 0 0 0 0 0 1"):
    if scan_text is not None:
        (t / "a.ply").write_text(scan_text)
    p = t / "s.conf"
    p.write_text(line + "\n")
    return p


CAMERA_CASES = {
    "binary json": (lambda t: put(t / "c.json", b"\xff\xfe\x00\x81binary"), "not a text JSON file"),
    "invalid json": (lambda t: put(t / "c.json", '{"cameras": ['), "invalid JSON"),
    "json list": (lambda t: _json(t, [1, 2]), "expected a JSON object"),
    "json no camera": (lambda t: _json(t, {"cameras": []}), "no camera"),
    "json ragged colours": (lambda t: _json(t, {"cameras": [CAM], "points": [[0, 0, 0], [1, 1, 1]], "colors": [[1, 0, 0], [1, 0]]}), "ragged"),
    "json colour out of range": (lambda t: _json(t, {"cameras": [CAM], "points": [[0, 0, 0]], "colors": [[255, 0, 0]]}), "in \\[0, 1\\]"),
    "json point_camera out of range": (lambda t: _json(t, {"cameras": [CAM], "points": [[0, 0, 0]], "point_camera": [5]}), "out of range"),
    "json bad K": (lambda t: _json(t, {"cameras": [{**CAM, "K": [[1, 2], [3, 4]]}]}), "cameras\\[0\\]"),
    "bundler 1e12 points": (lambda t: _bundler(t, "# Bundle file v0.3\n1 1000000000000\n100 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n"), "truncated file or corrupt header"),
    "bundler 1e12 cameras": (lambda t: _bundler(t, "# Bundle file v0.3\n1000000000000 0\n"), "truncated file or corrupt header"),
    "bundler bad header": (lambda t: _bundler(t, "# Bundle file v0.3\nx y\n"), "expected numbers"),
    "bundler truncated": (lambda t: _bundler(t, "# Bundle file v0.3\n1 0\n100 0 0\n1 0 0\n"), "truncated|ends early"),
    "middlebury count": (lambda t: put(t / "x_par.txt", "2\nim.png " + " ".join(["1"] * 21) + "\n"), "count mismatch|rotation|R"),
    "conf missing scan": (lambda t: _conf(t), "not found"),
    "conf bad keyword": (lambda t: _conf(t, "", line="foo a.ply 0 0 0 0 0 0 1"), "unknown keyword"),
    "conf truncated scan": (lambda t: _conf(t, PLY_HEAD.format(n=50)), "truncated or empty"),
    "colmap missing images": (lambda t: put(t / "cameras.txt", "1 PINHOLE 10 10 5 5 5 5\n"), "images.txt is missing"),
}


@pytest.mark.parametrize("case", sorted(CAMERA_CASES))
def test_bad_camera_file_is_one_line(tmp_path, case):
    make, pattern = CAMERA_CASES[case]
    path = make(tmp_path)
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=pattern) as info:
        load_range_scans(path) if str(path).endswith(".conf") else load_cameras(path)
    msg = str(info.value)
    assert "\n" not in msg and (Path(path).name in msg or str(path) in msg or str(Path(path).parent) in msg)
    assert snapshot(tmp_path) == before


# -- 3. model files -------------------------------------------------------------------------


def _model(t, **change):
    """A saved model with some fields replaced (None: removed)."""
    good = t / "good.npz"
    tiny_surface().save(good)
    with np.load(good, allow_pickle=False) as d:
        fields = {k: d[k] for k in d.files}
    for k, v in change.items():
        if v is None:
            fields.pop(k)
        else:
            fields[k] = v
    good.unlink()
    p = t / "m.npz"
    with open(p, "wb") as fh:
        np.savez(fh, **fields)
    return p


def _header(**change):
    h = {"format": "o3drbf-implicit-surface", "version": 1, "kernel": MultiOrder().to_dict(),
         "normalization": {"center": [0, 0, 0], "scale": 1.0}, "metadata": {}}
    h.update(change)
    return np.array(json.dumps(h))


def _truncated(t):
    p = t / "m.npz"
    tiny_surface().save(p)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    return p


def _pickled(t):
    p = t / "m.npz"
    tiny_surface().save(p)
    with np.load(p, allow_pickle=False) as d:
        fields = {k: d[k] for k in d.files}
    fields["weights"] = np.array([{"evil": 1}] * 12, dtype=object)
    with open(p, "wb") as fh:
        np.savez(fh, **fields)
    return p


MODEL_CASES = {
    "not a zip": (lambda t: put(t / "m.npz", b"hello"), "not an o3drbf model file"),
    "truncated": (_truncated, "not an o3drbf model file"),
    "empty file": (lambda t: put(t / "m.npz", b""), "not an o3drbf model file"),
    "zip without fields": (lambda t: zipfile.ZipFile(t / "m.npz", "w").close() or t / "m.npz", "'header' is missing"),
    "missing weights": (lambda t: _model(t, weights=None), "'weights' is missing"),
    "header not json": (lambda t: _model(t, header=np.array("{not json")), "'header' is not valid JSON"),
    "header json list": (lambda t: _model(t, header=np.array("[1, 2]")), "'header' must be a JSON object"),
    "header not a string": (lambda t: _model(t, header=np.arange(3)), "'header' must be one JSON string"),
    "wrong format": (lambda t: _model(t, header=_header(format="other")), "header.format"),
    "newer version": (lambda t: _model(t, header=_header(version=99)), "newer o3drbf"),
    "bad version": (lambda t: _model(t, header=_header(version="1")), "header.version"),
    "unknown kernel": (lambda t: _model(t, header=_header(kernel={"name": "spline"})), "header.kernel.*unknown kernel"),
    "negative delta": (lambda t: _model(t, header=_header(kernel={"name": "multiorder", "delta": -1.0, "tau": 0.01})), "header.kernel"),
    "kernel param string": (lambda t: _model(t, header=_header(kernel={"name": "gaussian", "sigma": "big"})), "header.kernel.sigma"),
    "metadata not object": (lambda t: _model(t, header=_header(metadata=[1])), "header.metadata"),
    "weights count": (lambda t: _model(t, weights=np.ones(11)), "'weights'.*count mismatch"),
    "centres nan": (lambda t: _model(t, centres=np.full((12, 3), np.nan)), "'centres' has NaN"),
    "centres 2 columns": (lambda t: _model(t, centres=np.ones((12, 2))), "'centres' has shape"),
    "centres empty": (lambda t: _model(t, centres=np.ones((0, 3)), weights=np.ones(0)), "'centres' is empty"),
    "centres strings": (lambda t: _model(t, centres=np.full((12, 3), "a")), "'centres' must hold numbers"),
    "poly length": (lambda t: _model(t, poly=np.ones(4)), "'poly' has shape"),
    "scale zero": (lambda t: _model(t, scale=np.array(0.0)), "'scale' must be > 0"),
    "center shape": (lambda t: _model(t, center=np.ones(2)), "'center' has shape"),
    "pickled weights": (_pickled, "without pickle"),
    "folder": (lambda t: (t / "m.npz").mkdir() or t / "m.npz", "is a folder"),
}


@pytest.mark.parametrize("case", sorted(MODEL_CASES))
def test_bad_model_file_names_file_and_field(tmp_path, case):
    make, pattern = MODEL_CASES[case]
    path = make(tmp_path)
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=pattern) as info:
        ImplicitSurface.load(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert snapshot(tmp_path) == before


def test_model_round_trip_is_exact(tmp_path):
    s = tiny_surface()
    s.save(tmp_path / "m.npz")
    t = ImplicitSurface.load(tmp_path / "m.npz")
    x = np.random.default_rng(1).normal(size=(50, 3))
    assert np.array_equal(s(x), t(x)) and t.kernel == s.kernel


# -- 4. outputs refused before any costly step --------------------------------------------


def _scan_dir(t):
    (t / "a.ply").write_text(ply_text(GOOD_PTS))
    (t / "s.conf").write_text("camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 0 0 0 0 1\n")
    return t / "s.conf"


def _middlebury(t):
    (t / "im0.png").write_bytes(b"\x89PNG fake image")
    row = "im0.png 100 0 50 0 100 50 0 0 1 1 0 0 0 1 0 0 0 1 0 0 3"
    (t / "x_par.txt").write_text(f"1\n{row}\n")
    return t / "x_par.txt"


def _readonly_dir(t):
    d = t / "ro"
    d.mkdir()
    d.chmod(0o555)
    return d / "out.ply"


def _readonly_file(t):
    p = t / "out.ply"
    p.write_text("old")
    p.chmod(0o444)
    return p


def _symlink(t):
    (t / "in.ply").write_text(ply_text(GOOD_PTS))
    (t / "link.ply").symlink_to(t / "in.ply")
    return t / "link.ply"


OUTPUT_CASES = {
    "output is input": (lambda t: t / "in.ply", lambda t: [t / "in.ply"], ValueError, "is the input file"),
    "output via symlink": (_symlink, lambda t: [t / "in.ply"], ValueError, "is the input file"),
    "output is a conf scan": (lambda t: _scan_dir(t).parent / "a.ply", lambda t: [t / "s.conf"], ValueError, "a file an input refers to"),
    "output is a calibration image": (lambda t: _middlebury(t).parent / "im0.png", lambda t: [t / "x_par.txt"], ValueError, "a file an input refers to"),
    "output is a folder": (lambda t: (t / "dir.ply").mkdir() or t / "dir.ply", lambda t: [], ValueError, "is a folder"),
    "missing parent": (lambda t: t / "no" / "out.ply", lambda t: [], FileNotFoundError, "folder does not exist"),
    "read-only parent": (_readonly_dir, lambda t: [], PermissionError, "not writable"),
    "read-only output": (_readonly_file, lambda t: [], PermissionError, "read-only"),
}


@pytest.mark.parametrize("case", sorted(OUTPUT_CASES))
def test_unsafe_output_refused(tmp_path, case):
    (tmp_path / "in.ply").write_text(ply_text(GOOD_PTS))
    out_fn, inputs_fn, exc, pattern = OUTPUT_CASES[case]
    out = out_fn(tmp_path)
    inputs = inputs_fn(tmp_path)
    before = snapshot(tmp_path)
    try:
        with pytest.raises(exc, match=pattern):
            check_outputs([out], inputs)
        if out.suffix in MESH_FORMATS:
            with pytest.raises(exc, match=pattern):  # the writer refuses it too
                write_mesh(out, sphere_mesh(), inputs=inputs)
    finally:
        for p in tmp_path.rglob("*"):
            if not p.is_symlink():
                p.chmod(0o755 if p.is_dir() else 0o644)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


def test_output_given_twice_and_bad_extensions(tmp_path):
    with pytest.raises(ValueError, match="given twice"):
        check_outputs([tmp_path / "a.ply", tmp_path / "." / "a.ply"])
    with pytest.raises(ValueError, match="cannot read back the .glb"):
        check_output(tmp_path / "a.glb")
    with pytest.raises(ValueError, match="unsupported extension"):
        check_output(tmp_path / "a.xyz")
    assert ".glb" not in MESH_FORMATS
    assert not list(tmp_path.iterdir())


def test_referenced_files_lists_scans_and_images(tmp_path):
    conf = _scan_dir(tmp_path)
    assert referenced_files(conf) == [tmp_path / "a.ply"]
    par = _middlebury(tmp_path)
    assert referenced_files(par) == [tmp_path / "im0.png"]
    assert referenced_files(tmp_path / "missing.conf") == []


# -- 5. precision and round trips --------------------------------------------------------------


@pytest.mark.parametrize("fmt", MESH_FORMATS)
def test_every_listed_format_round_trips(tmp_path, fmt):
    m = sphere_mesh(resolution=10)
    m.compute_vertex_normals()
    out = write_mesh(tmp_path / f"m{fmt}", m)
    back = o3d.io.read_triangle_mesh(str(out))
    assert len(back.triangles) == len(m.triangles)
    v, b = np.asarray(m.vertices), np.asarray(back.vertices)
    from scipy.spatial import cKDTree

    assert cKDTree(v).query(b)[0].max() < 1e-5 and cKDTree(b).query(v)[0].max() < 1e-5


def test_glb_really_does_not_round_trip_in_open3d(tmp_path):
    """Why .glb is not listed: if Open3D ever reads it back, list it again."""
    m = sphere_mesh()
    o3d.io.write_triangle_mesh(str(tmp_path / "m.glb"), m)
    assert len(o3d.io.read_triangle_mesh(str(tmp_path / "m.glb")).triangles) != len(m.triangles)


def test_ply_keeps_coordinates_offset_by_1e9(tmp_path):
    m = sphere_mesh(offset=1e9)
    write_mesh(tmp_path / "far.ply", m)
    back = np.asarray(o3d.io.read_triangle_mesh(str(tmp_path / "far.ply")).vertices)
    assert np.array_equal(back, np.asarray(m.vertices))  # bit exact
    assert check_mesh_precision(tmp_path / "far.ply", np.asarray(m.vertices)) == 0.0


@pytest.mark.parametrize("fmt,offset", [(".stl", 1e9), (".obj", 1e9), (".off", 1e6), (".gltf", 1e9), (".stl", 1e5)])
def test_lossy_format_far_from_origin_is_refused(tmp_path, fmt, offset):
    m = sphere_mesh(offset=offset)
    old = tmp_path / f"far{fmt}"
    old.write_text("previous output")
    before = snapshot(tmp_path)
    with pytest.raises(ValueError, match=f"the \\{fmt} format .*use .ply"):
        check_mesh_precision(old, np.asarray(m.vertices))
    with pytest.raises(ValueError, match=f"the \\{fmt} format moved vertices"):
        write_mesh(old, m)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)
    with pytest.warns(UserWarning, match="use .ply"):
        check_mesh_precision(old, np.asarray(m.vertices), action="warn")


def test_lossy_format_near_origin_is_accepted(tmp_path):
    pts = np.asarray(sphere_mesh().vertices)
    for fmt in (".stl", ".obj", ".off", ".gltf"):
        assert check_mesh_precision(tmp_path / f"a{fmt}", pts) < 1e-5
    assert not temporaries(tmp_path)


# -- 6. compiled code boundaries ---------------------------------------------------------------


@pytest.mark.parametrize(
    "centres,weights,targets,pattern",
    [
        (np.zeros((5, 3)), np.ones(4), np.zeros((2, 3)), "weights must have shape \\(5,\\)"),
        (np.zeros((5, 2)), np.ones(5), np.zeros((2, 3)), "centres must have shape"),
        (np.zeros((5, 3)), np.ones(5), np.zeros((2, 4)), "targets must have shape"),
        (np.zeros((5, 3)), np.ones(5), np.full((2, 3), np.nan), "targets have NaN"),
        (np.zeros((5, 3)), np.array([1, 1, np.inf, 1, 1.0]), np.zeros((2, 3)), "weights have NaN"),
    ],
)
def test_compiled_sums_check_their_arrays(centres, weights, targets, pattern):
    k = MultiOrder()
    for fn in (lambda: compiled.direct_sum(k, centres, weights, targets), lambda: compiled.table_sum(compiled.KernelTable(k), centres, weights, targets)):
        with pytest.raises(ValueError, match=pattern):
            fn()


def test_compiled_matrix_checks_shapes():
    with pytest.raises(ValueError, match="y must have shape"):
        compiled.direct_matrix(MultiOrder(), np.zeros((3, 3)), np.zeros((3, 2)))


# -- 7. writer faults: nothing lost ------------------------------------------------------------


def _fail(kind):
    def body(tmp):
        Path(tmp).write_text("half")
        if kind == "exception":
            raise RuntimeError("writer crashed")
        if kind == "interrupt":
            raise KeyboardInterrupt
        if kind == "disk full":
            raise OSError(28, "No space left on device")
        if kind == "empty":
            Path(tmp).write_text("")

    return body


@pytest.mark.parametrize(
    "kind,exc,pattern",
    [
        ("exception", RuntimeError, "writer crashed"),
        ("interrupt", KeyboardInterrupt, None),
        ("disk full", OSError, "disk is full"),
        ("empty", OSError, "empty file"),
        ("verify", OSError, "read back"),
    ],
)
def test_failed_write_keeps_previous_output(tmp_path, kind, exc, pattern):
    out = tmp_path / "out.ply"
    out.write_text("the previous, complete output")
    before = snapshot(tmp_path)

    def verify(tmp):
        raise OSError("read back 0 of 10 triangles")

    with pytest.raises(exc, match=pattern):
        with atomic_path(out, verify=verify if kind == "verify" else None) as tmp:
            assert tmp in live_temporary_files()
            if kind == "verify":
                Path(tmp).write_text("x")
            else:
                _fail(kind)(tmp)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path) and not live_temporary_files()


def test_open3d_writer_returning_false_is_an_error(tmp_path, monkeypatch):
    out = tmp_path / "out.obj"  # (o3drbf writes .ply itself: tests/mesh/test_arrays.py checks it)
    out.write_text("previous")
    before = snapshot(tmp_path)
    monkeypatch.setattr(o3d.io, "write_triangle_mesh", lambda *a, **k: False)
    with pytest.raises(OSError, match="Open3D could not write"):
        write_mesh(out, sphere_mesh())
    monkeypatch.setattr(o3d.io, "write_point_cloud", lambda *a, **k: False)
    with pytest.raises(OSError, match="Open3D could not write"):
        write_points(tmp_path / "p.ply", GOOD_PTS)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


def test_writer_that_silently_truncates_is_caught(tmp_path, monkeypatch):
    """Open3D returns True but the file lost triangles (e.g. a short write): caught by re-reading."""
    real = o3d.io.write_triangle_mesh

    def short_write(path, mesh, *a, **k):
        ok = real(path, mesh, *a, **k)
        data = Path(path).read_bytes()
        Path(path).write_bytes(data[: len(data) * 2 // 3])
        return ok

    out = tmp_path / "out.obj"  # (o3drbf writes .ply itself: tests/mesh/test_arrays.py checks it)
    out.write_text("previous")
    before = snapshot(tmp_path)
    monkeypatch.setattr(o3d.io, "write_triangle_mesh", short_write)
    with pytest.raises(OSError, match="read back"):
        write_mesh(out, sphere_mesh())
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


_SUB = textwrap.dedent(
    """
    import os, resource, signal, sys
    from pathlib import Path
    import numpy as np, open3d as o3d
    from o3drbf.io.files import atomic_path, signal_cleanup, write_mesh
    out = Path(sys.argv[2])
    mode = sys.argv[1]
    if mode == "fsize":
        m = o3d.geometry.TriangleMesh.create_sphere(1.0, 60)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
        try:
            write_mesh(out, m)
        except OSError as exc:
            print(exc)
            sys.exit(2)
    elif mode == "sigterm":
        with signal_cleanup():
            with atomic_path(out) as tmp:
                Path(tmp).write_text("half written")
                os.kill(os.getpid(), signal.SIGTERM)
                import time; time.sleep(5)
    else:  # installed for good (twice: idempotent); the earlier handler os._exit()s: no unwinding,
        # so only the clean-up in the handler can remove the temporary
        from o3drbf.io.files import install_signal_cleanup
        signal.signal(signal.SIGTERM, lambda *a: os._exit(99))
        install_signal_cleanup()
        install_signal_cleanup()
        import contextlib
        cm = atomic_path(out)
        tmp = cm.__enter__()
        Path(tmp).write_text("half written")
        os.kill(os.getpid(), signal.SIGTERM)
        import time; time.sleep(5)
    """
)


@pytest.mark.parametrize("mode,code,pattern", [("fsize", 2, "file size limit"), ("sigterm", 143, ""), ("sigterm-installed", 99, "")])
def test_disk_limit_and_sigterm_leave_no_partial_file(tmp_path, mode, code, pattern):
    out = tmp_path / "out.ply"
    out.write_text("previous output")
    before = snapshot(tmp_path)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    r = subprocess.run([PY, "-c", _SUB, mode, str(out)], capture_output=True, text=True, env=env, timeout=60)
    assert r.returncode == code, r.stderr
    import re

    assert re.search(pattern, r.stdout + r.stderr)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


# -- 8. duplicates -------------------------------------------------------------------------------


def test_merge_duplicates_averages_and_keeps_order():
    p = np.array([[0, 0, 0], [1, 0, 0], [0, 0, 0], [2, 0, 0], [1, 0, 0], [-0.0, 0, 0]], dtype=float)
    n = np.array([[1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0]], dtype=float)
    cam = np.array([3, 1, 4, 1, 5, 9])
    q, nn, cc, none, merged = merge_duplicates(p, n, cam, None)
    assert merged == 3 and none is None
    assert np.array_equal(q, [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    assert np.allclose(nn[0], np.array([2, 1, 0]) / np.sqrt(5)) and np.allclose(nn[1:], [[0, 1, 0], [0, 0, 1]])
    assert np.array_equal(cc, [3, 1, 1])
    q2, m2 = merge_duplicates(q)
    assert m2 == 0 and np.array_equal(q2, q)
    with pytest.raises(ValueError, match="one row per point"):
        merge_duplicates(p, np.ones((5, 3)))


# -- 9. command line -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    d = tmp_path_factory.mktemp("faults_cli")
    p, n = Sphere(1.0).sample(400, seed=4)
    write_points(d / "in.ply", p, n)
    return d


SMALL = ["--surface-count", "100", "--resolution", "12", "-q"]


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--seed", "-1"], "--seed"),
        (["--seed", "x"], "--seed"),
        (["--delta", "nan"], "--delta"),
        (["--tau", "inf"], "--tau"),
        (["--resolution", "0"], "--resolution"),
        (["--surface-count", "abc"], "--surface-count"),
        (["--sphere-count", "-5"], "--sphere-count"),
        (["--basis", "spline"], "--basis"),
    ],
)
def test_cli_bad_option_names_it(cloud, capsys, args, pattern):
    before = snapshot(cloud)
    with pytest.raises(SystemExit) as info:
        main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), *args])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert pattern in err and "Traceback" not in err
    assert snapshot(cloud) == before


@pytest.mark.parametrize(
    "fault,code,pattern",
    [
        (KeyboardInterrupt(), 130, "^o3drbf: interrupted$"),
        (MemoryError("Unable to allocate 7.45 GiB for an array with shape (31623, 31623) and data type float64"), 2, "7.45 GiB.*--surface-count"),
        (MemoryError(), 2, "out of memory.*--resolution"),
        (ZeroDivisionError("division by zero"), 1, "internal error: ZeroDivisionError"),
        (RuntimeError("solver diverged"), 2, "error: solver diverged"),
    ],
)
def test_cli_faults_during_reconstruction(cloud, capsys, monkeypatch, fault, code, pattern):
    import o3drbf.pipeline

    out = cloud / "out.ply"
    out.write_text("previous output")
    before = snapshot(cloud)

    def boom(*a, **k):
        raise fault

    monkeypatch.setattr(o3drbf.pipeline, "reconstruct", boom)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(out), *SMALL]) == code
    err = capsys.readouterr().err.strip()
    import re

    assert re.search(pattern, err, re.M) and len(err.splitlines()) == 1 and "Traceback" not in err
    assert snapshot(cloud) == before and not temporaries(cloud)
    out.unlink()


def test_cli_interrupt_while_writing_leaves_previous_output(cloud, capsys, monkeypatch):
    out = cloud / "out.ply"
    out.write_text("previous output")
    before = snapshot(cloud)
    import o3drbf.io.files as files

    real = files._write_ply  # (the command writes its .ply itself)

    def interrupted(path, mesh, fields):
        real(path, mesh, fields)
        raise KeyboardInterrupt

    monkeypatch.setattr(files, "_write_ply", interrupted)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(out), *SMALL]) == 130
    assert capsys.readouterr().err.strip() == "o3drbf: interrupted"
    assert snapshot(cloud) == before and not temporaries(cloud)
    out.unlink()


@pytest.mark.parametrize(
    "output,extra,pattern",
    [
        ("in.ply", [], "is the input file"),
        ("out.glb", [], "cannot read back the .glb"),
        ("none/out.ply", [], "folder does not exist"),
        ("out.ply", ["--save-model", "model.bin"], "--save-model must end in .npz"),
        ("out.ply", ["--cameras", "missing.json"], "not found"),
    ],
)
def test_cli_bad_files_exit_2_inputs_untouched(cloud, capsys, output, extra, pattern):
    before = snapshot(cloud)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / output), *SMALL, *[str(cloud / e) if e.endswith((".ply", ".json")) else e for e in extra]]) == 2
    err = capsys.readouterr().err
    assert pattern in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert snapshot(cloud) == before and not temporaries(cloud)


def test_cli_is_deterministic_by_seed(cloud):
    outs = []
    for name in ("a.ply", "b.ply"):
        assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / name), *SMALL, "--seed", "7"]) == 0
        outs.append((cloud / name).read_bytes())
    assert outs[0] == outs[1]
    (cloud / "a.ply").unlink()
    (cloud / "b.ply").unlink()


def test_cli_file_size_limit_in_subprocess(cloud):
    """Disk full simulated by RLIMIT_FSIZE: exit 2, one line, previous output intact, no temporary."""
    out = cloud / "limited.ply"
    out.write_text("previous output")
    before = snapshot(cloud)
    code = (
        "import resource, sys; from o3drbf.cli.commands import main;"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (4000, resource.RLIM_INFINITY));"
        "sys.exit(main(sys.argv[1:]))"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO), "O3DRBF_NO_PROGRESS": "1"}
    r = subprocess.run([PY, "-c", code, "reconstruct", str(cloud / "in.ply"), "-o", str(out), *SMALL],
                       capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 2, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("o3drbf: error: cannot write") and "file size limit (ulimit -f) is 4,000 bytes" in last
    assert "Traceback" not in r.stderr
    assert snapshot(cloud) == before and not temporaries(cloud)
    out.unlink()


# -- 10. soak -------------------------------------------------------------------------------------


def test_soak_repeated_reconstructions_bounded_memory():
    """30 tiny reconstructions (200 take ~60 s on the shared machine): same mesh each time, RSS bounded."""
    import psutil

    from o3drbf.pipeline import reconstruct

    p, n = Sphere(1.0).sample(300, seed=4)
    proc = psutil.Process()
    first = reconstruct(p, n, surface_count=100, resolution=12, seed=0, progress=False)
    ref = np.asarray(first.mesh.vertices).copy()
    gc.collect()
    rss0 = proc.memory_info().rss
    for i in range(30):
        r = reconstruct(p, n, surface_count=100, resolution=12, seed=0, progress=False)
        assert np.array_equal(np.asarray(r.mesh.vertices), ref)
    gc.collect()
    growth = proc.memory_info().rss - rss0
    assert growth < 50 * 2**20, f"RSS grew by {growth / 2**20:.1f} MiB over 30 runs"


# -- 11. every output kind goes through the one checked, atomic helper -------------------------


def _write_kind(kind: str, path: Path) -> None:
    if kind == "mesh":
        write_mesh(path, sphere_mesh())
    elif kind == "points":
        write_points(path, GOOD_PTS)
    elif kind == "model":
        tiny_surface().save(path)
    elif kind == "cameras":
        from o3drbf.cameras.model import Camera, save_cameras_json

        save_cameras_json(path, [Camera.from_dict(CAM)], points=GOOD_PTS[:3])
    elif kind == "tables":
        from o3drbf.evaluation.compare import write_tables

        write_tables([{"method": "x"}], path.parent, stem=path.stem)
    elif kind == "picture":
        from o3drbf.photo.pipeline import picture
        from o3drbf.cameras.model import Camera

        picture(sphere_mesh(offset=0.0), Camera.from_dict({**CAM, "t": [0, 0, 4], "width": 16, "height": 16}), np.zeros((16, 16, 3)), path)


OUTPUT_KINDS = {"mesh": "o.ply", "points": "o.xyz", "model": "o.npz", "cameras": "o.json", "tables": "o.csv", "picture": "o.png"}


@pytest.mark.parametrize("kind", sorted(OUTPUT_KINDS))
@pytest.mark.parametrize("fault", ["disk full at flush", "short write"])
def test_every_output_kind_is_atomic_and_checked(tmp_path, monkeypatch, kind, fault):
    import o3drbf.io.files as files

    out = tmp_path / OUTPUT_KINDS[kind]
    out.write_text("the previous output")
    before = snapshot(tmp_path)
    if fault == "disk full at flush":
        def fsync(fd):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(files.os, "fsync", fsync)
        pattern = "disk is full"
    else:  # the writer's file comes out empty, or cut short for the verified kinds
        real_verify_entry = files.atomic_path

        @files.contextlib.contextmanager
        def cutting(path, verify=None):
            with real_verify_entry(path, verify=verify) as tmp:
                yield tmp
                data = Path(tmp).read_bytes()
                Path(tmp).write_bytes(data[: len(data) // 3] if verify is not None else b"")

        monkeypatch.setattr(files, "atomic_path", cutting)
        import o3drbf.surface

        monkeypatch.setattr(o3drbf.surface, "atomic_path", cutting)
        pattern = "cannot write"
    with pytest.raises(OSError, match=pattern):
        _write_kind(kind, out)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


@pytest.mark.parametrize(
    "output,model,cameras,exc,pattern",
    [
        ("in.ply", None, None, ValueError, "is the input file"),
        ("o.ply", "o.ply", None, ValueError, "must end in .npz"),
        ("o.ply", "in.npz", "in.npz", ValueError, "is the input file"),
        ("a.ply", None, "s.conf", ValueError, "a file an input refers to"),
        ("o.stl", None, None, ValueError, "the .stl format would move vertices"),
    ],
)
def test_reconstruct_file_checks(tmp_path, output, model, cameras, exc, pattern):
    import argparse

    from o3drbf.cli.commands import check_reconstruct_files

    _scan_dir(tmp_path)
    (tmp_path / "in.ply").write_text(ply_text(GOOD_PTS))
    (tmp_path / "in.npz").write_bytes(b"model")
    before = snapshot(tmp_path)
    j = lambda name: None if name is None else str(tmp_path / name)  # noqa: E731
    args = argparse.Namespace(input=j("in.ply"), output=j(output), save_model=j(model), cameras=j(cameras))
    with pytest.raises(exc, match=pattern):
        check_reconstruct_files(args, GOOD_PTS + 1e6)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)
    ok = argparse.Namespace(input=j("in.ply"), output=j("fine.ply"), save_model=j("m.npz"), cameras=None)
    assert check_reconstruct_files(ok, GOOD_PTS + 1e6) == tmp_path / "fine.ply"


# -- 12. bad input gets one line naming the problem and the fix (issue 26) ----------------------


def _one_error_line(capsys) -> str:
    """The command's stderr, which must be one ``o3drbf: error:`` line."""
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("o3drbf: error: ") and "Traceback" not in err, err
    return err


def test_cli_points_all_copies_of_one_are_named(tmp_path, capsys):
    write_points(tmp_path / "same.ply", np.tile([[0.1, 0.2, 0.3]], (2000, 1)), np.tile([[0.0, 0.0, 1.0]], (2000, 1)))
    before = snapshot(tmp_path)
    assert main(["reconstruct", str(tmp_path / "same.ply"), "-o", str(tmp_path / "o.ply"), *SMALL]) == 2
    err = _one_error_line(capsys)
    assert "all 2,000 points are copies of one point: 1,999 repeats removed, 1 distinct left; at least 10 distinct points" in err
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


@pytest.mark.parametrize(
    "args,pattern",
    [
        (["--tau", "1e-300"], r"--tau 1e-300 is outside the sensible range \[1e-06, 10\] \(box units; the paper uses 0.005 to 0.025\); give --tau"),
        (["--delta", "1e-300"], r"--delta 1e-300 is outside the sensible range \[0.1, 200\]"),
        (["--basis", "gaussian", "--sigma", "1e-6"], r"--sigma 1e-06 is outside the sensible range \[0.001, 10\]"),
        (["--kernel", "gaussian", "--sigma", "0.01"], r"--sigma 0.01 is narrower than the surface constraints' spacing .* give --sigma of at least"),
    ],
)
def test_cli_kernel_parameter_out_of_range_is_one_line(cloud, capsys, args, pattern):
    import re

    before = snapshot(cloud)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), *SMALL, *args]) == 2
    assert re.search(pattern, _one_error_line(capsys))
    assert snapshot(cloud) == before and not temporaries(cloud)


def test_kernel_parameter_range_in_python_and_photos(tmp_path, capsys):
    from o3drbf.pipeline import reconstruct

    p, n = Sphere(1.0).sample(200, seed=1)
    with pytest.raises(ValueError, match="--tau 1e-300 is outside the sensible range"):
        reconstruct(p, n, tau=1e-300)
    with pytest.raises(ValueError, match="--delta 1e-300 is outside"):
        reconstruct(p, n, delta=1e-300)
    # photos checks it before reading a single photograph
    assert main(["photos", str(tmp_path), "-o", str(tmp_path / "m.ply"), "--tau", "1e-300", "-q"]) == 2
    assert "--tau 1e-300 is outside the sensible range" in _one_error_line(capsys)


def test_cli_voxel_size_beyond_the_data_is_refused(cloud, capsys):
    before = snapshot(cloud)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), *SMALL, "--voxel-size", "1e6"]) == 2
    err = _one_error_line(capsys)
    assert "--voxel-size 1e+06 leaves 2.2e-06 cells along the longest side" in err and "give --voxel-size of at most 0.274 (8 cells)" in err
    assert snapshot(cloud) == before and not temporaries(cloud)
    assert main(["reconstruct", str(cloud / "in.ply"), "-o", str(cloud / "o.ply"), *SMALL, "--voxel-size", "0.25"]) == 0
    (cloud / "o.ply").unlink()


# -- 13. the closing summary says the truth (issue 26) ------------------------------------------


def test_cli_summary_counts_and_fitness_over_kept_points(tmp_path, capsys):
    import re

    rng = np.random.default_rng(0)
    p, n = Sphere(1.0).sample(600, noise=0.002, seed=1)
    far = rng.uniform(-2.0, 2.0, size=(30, 3))
    far = far[np.abs(np.linalg.norm(far, axis=1) - 1.0) > 0.5]  # well off the surface
    m = rng.normal(size=far.shape)
    write_points(tmp_path / "noisy.ply", np.vstack([p, far]), np.vstack([n, m / np.linalg.norm(m, axis=1)[:, None]]))
    assert main(["reconstruct", str(tmp_path / "noisy.ply"), "-o", str(tmp_path / "o.ply"), "--surface-count", "200",
                 "--resolution", "24"]) == 0
    out = capsys.readouterr().out
    read, kept, removed = map(int, re.search(r"points +(\d+) read, (\d+) kept \((\d+) removed as outliers\)", out).groups())
    assert read == 600 + len(far) and kept + removed == read and removed >= len(far) // 2
    fit = re.search(rf"fitness error +over the {kept} kept points: mean (\S+), RMS (\S+), max (\S+) \(data units", out)
    assert fit is not None, out
    assert float(fit.group(3)) < 0.5  # the far points (0.5 to 2.5 off the sphere) are not measured


# -- 14. nothing is lost: no command writes over what it reads (issue 26) -------------------------


@pytest.mark.parametrize("where", ["beside the calibration", "in images/"])
def test_cli_photos_never_writes_over_a_photograph(tmp_path, capsys, where):
    par = _middlebury(tmp_path)  # names im0.png
    photo = tmp_path / "im0.png"
    if where == "in images/":
        (tmp_path / "images").mkdir()
        photo = photo.rename(tmp_path / "images" / "im0.png")
    before = snapshot(tmp_path)
    assert main(["photos", str(tmp_path), "--calibration", str(par), "-o", str(tmp_path / "m.ply"), "--picture", str(photo), "-q"]) == 2
    assert f"output {str(photo)!r} is the input file; choose another name" in _one_error_line(capsys)
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


def test_picture_is_checked_against_inputs_and_read_back(tmp_path, monkeypatch):
    from o3drbf.cameras.model import Camera
    from o3drbf.photo.pipeline import picture

    cam = Camera.from_dict({**CAM, "t": [0, 0, 4], "width": 16, "height": 16})
    photo = tmp_path / "photo.png"
    photo.write_bytes(b"the photograph")
    with pytest.raises(ValueError, match="is the input file"):
        picture(sphere_mesh(), cam, np.zeros((16, 16, 3)), photo, inputs=[photo])
    import skimage.io

    monkeypatch.setattr(skimage.io, "imread", lambda path: np.zeros((3, 3, 3), dtype=np.uint8))  # a write that came out wrong
    with pytest.raises(OSError, match="cannot write .*reads back as 3x3"):
        picture(sphere_mesh(), cam, np.zeros((16, 16, 3)), tmp_path / "new.png")
    assert photo.read_bytes() == b"the photograph" and not (tmp_path / "new.png").exists() and not temporaries(tmp_path)


def test_cli_photos_refuses_a_photograph_of_another_size(tmp_path, capsys):
    """A Middlebury calibration names no image size: each photograph's own is used, so check it against the principal point."""
    import skimage.io

    rows = []
    for i, (w, h) in enumerate([(16, 12), (16, 12), (8, 6)]):  # the third was resized to half
        skimage.io.imsave(tmp_path / f"im{i}.png", np.full((h, w, 3), 200, dtype=np.uint8), check_contrast=False)
        rows.append(f"im{i}.png 20 0 8 0 20 6 0 0 1 1 0 0 0 1 0 0 0 1 0 0 3")
    par = tmp_path / "x_par.txt"
    par.write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")
    before = snapshot(tmp_path)
    assert main(["photos", str(tmp_path), "--calibration", str(par), "-o", str(tmp_path / "m.ply"), "-q"]) == 2
    err = _one_error_line(capsys)
    assert "image im2.png is 8x6, but its calibration is for about 16x12 images (principal point (8, 6)" in err
    assert "give the photograph at the size it was calibrated for" in err
    assert snapshot(tmp_path) == before and not temporaries(tmp_path)


# -- 15. a camera inside the data is dropped, so the mesh stays right (issue 26) -----------------


def _ring_cameras():
    from o3drbf.synthetic.scans import camera_ring

    return camera_ring((0, 0, 0), 1.0, n_views=6, elevation=35, width=80, height=60, fov=50) + camera_ring(
        (0, 0, 0), 1.0, n_views=6, elevation=-35, width=80, height=60, fov=50, azimuth=30)


@pytest.mark.parametrize("scans", [False, True], ids=["cameras only", "with point_camera"])
def test_camera_at_a_surface_point_is_dropped(caplog, scans):
    from o3drbf.cameras.model import Camera
    from o3drbf.mesh.metrics import mesh_report
    from o3drbf.pipeline import reconstruct

    points, _ = Sphere(1.0).sample(2000, seed=2)
    cams = _ring_cameras()
    kw = {}
    if scans:  # each point seen by its nearest ring camera; those near the bad camera's centre by it
        centres = np.array([c.center for c in cams])
        pc = np.argmin(((points[:, None] - centres[None]) ** 2).sum(-1), axis=1)
        pc[np.linalg.norm(points - points[0], axis=1) < 0.5] = len(cams)
        kw["point_camera"] = pc
    with caplog.at_level("WARNING", logger="o3drbf"):
        r = reconstruct(points, cameras=cams + [Camera.from_center(points[0], name="bad")], surface_count=500, resolution=32, **kw)
    assert r.report.cameras == 12 and r.report.cameras_dropped == ["camera 12 (bad)"]
    assert "camera 12 (bad) lies 0 point spacings from a data point" in caplog.text
    radial = np.abs(np.linalg.norm(np.asarray(r.mesh.vertices), axis=1) - 1.0)
    assert mesh_report(r.mesh)["components"] == 1 and radial.max() < 0.035, radial.max()


def test_every_camera_inside_the_data_is_refused():
    from o3drbf.cameras.model import Camera
    from o3drbf.pipeline import reconstruct

    points, _ = Sphere(1.0).sample(500, seed=2)
    with pytest.raises(ValueError, match="every camera lies within the data .*check the camera poses"):
        reconstruct(points, cameras=[Camera.from_center(points[0]), Camera.from_center([0.0, 0.0, 1.0])], surface_count=100, resolution=16)
