"""o3drbf.evaluation.compare: several methods on one sampled torus, tables, picture, CLI entry."""

from __future__ import annotations

import argparse
import csv
import json

import numpy as np
import pytest

o3d = pytest.importorskip("open3d")

from o3drbf.evaluation import compare as C  # noqa: E402
from o3drbf.cameras.model import Camera  # noqa: E402
from o3drbf.synthetic.shapes import Sphere, Torus  # noqa: E402

R_MAJOR, R_TUBE = 0.6, 0.25
METHODS = ("multiorder", "poisson", "bpa")
RES = 32
N_SAMPLES = 20_000
# Measured (1500 points, noise 0.002, seed 1, resolution 32): Chamfer L1
# multiorder 0.0058, poisson 0.0011; a 0.05 shift of the truth gives 0.0207 / 0.0201.
CHAMFER_BOUND = {"multiorder": 0.010, "poisson": 0.004}


def _truth():
    return o3d.geometry.TriangleMesh.create_torus(R_MAJOR, R_TUBE, radial_resolution=90, tubular_resolution=45)


@pytest.fixture(scope="module")
def torus_data():
    return Torus(R_MAJOR, R_TUBE).sample(1500, noise=0.002, seed=1)


@pytest.fixture(scope="module")
def run(torus_data):
    points, normals = torus_data
    rows, meshes = C.compare_with_meshes(points, normals, truth=_truth(), methods=METHODS, resolution=RES, n_samples=N_SAMPLES)
    return rows, meshes


def test_open3d_torus_matches_shapes_torus():
    # Same axis (z) and radii: every vertex of Open3D's torus is on shapes.Torus.
    v = np.asarray(_truth().vertices)
    assert np.abs(Torus(R_MAJOR, R_TUBE).signed_distance(v)).max() < 1e-9
    assert np.ptp(v[:, 2]) < 2 * R_TUBE + 1e-9 < np.ptp(v[:, 0])


def test_rows_and_measures(run):
    rows, meshes = run
    assert [r["method"] for r in rows] == list(METHODS)
    assert set(meshes) == set(METHODS)
    by = {r["method"]: r for r in rows}
    for r in rows:
        assert r["error"] is None, r
        assert set(r) == set(C.COLUMNS)
        assert r["triangles"] > 100 and r["seconds"] > 0 and r["peak_mb"] >= 0 and r["rss_peak_mb"] >= 0
        assert r["f_threshold"] == pytest.approx(0.01 * np.linalg.norm([1.7, 1.7, 0.5]), rel=0.01)
    for name, bound in CHAMFER_BOUND.items():
        assert by[name]["chamfer_l1"] < bound, by[name]
        assert by[name]["f_score"] > 0.95 and by[name]["normal_consistency"] > 0.95
    mo = by["multiorder"]
    assert mo["watertight"] is True and mo["components"] == 1 and mo["euler_characteristic"] == 0 and mo["genus"] == 1
    assert mo["fitness_mean"] < 0.01 and mo["average_curvature"] > 0


def test_shifted_truth_fails_the_bound(torus_data):
    points, normals = torus_data
    shifted = _truth().translate((0.05, 0.0, 0.0))
    rows = C.compare(points, normals, truth=shifted, methods="multiorder,poisson", resolution=RES, n_samples=N_SAMPLES)
    for r in rows:
        assert r["chamfer_l1"] > CHAMFER_BOUND[r["method"]], r


def test_no_truth_leaves_truth_columns_empty_and_failures_are_rows(torus_data):
    points, normals = torus_data
    rows = C.compare(points, normals, methods=["bpa"])
    assert rows[0]["chamfer_l1"] is None and rows[0]["triangles"] > 0
    # A method that produces nothing is reported, not raised.
    rows = C.compare(points[:50] * 1e-3 + np.arange(50)[:, None], None, methods="alpha,bpa")
    assert [r["method"] for r in rows] == ["alpha", "bpa"]
    for r in rows:
        assert r["method"] in r["error"] and r["triangles"] is None and r["chamfer_l1"] is None


def test_open3d_normals_face_the_cameras():
    points, normals = Sphere(1.0).sample(800, seed=3)
    cams = [Camera.from_center(c) for c in ([3, 0, 0], [-3, 0, 0], [0, 3, 0], [0, -3, 0], [0, 0, 3], [0, 0, -3])]
    n = C.open3d_normals(points, cams)
    assert np.einsum("ij,ij->i", n, normals).min() > 0.9
    inward = C.open3d_normals(points, [Camera.from_center([0, 0, 0])])  # a camera inside flips every normal
    assert np.einsum("ij,ij->i", inward, normals).max() < -0.9


def test_tables(run, tmp_path):
    rows, _ = run
    paths = C.write_tables(rows, tmp_path)
    md = paths["markdown"].read_text().splitlines()
    table = [line for line in md if line.startswith("|")]
    assert table[0].startswith("| method |") and "chamfer_l1" in table[0] and set(table[1]) <= set("|-")
    assert len(table) == 2 + len(METHODS)
    assert [line.split("|")[1].strip() for line in table[2:]] == list(METHODS)
    with open(paths["csv"], newline="") as fh:
        parsed = list(csv.DictReader(fh))
    assert [r["method"] for r in parsed] == list(METHODS)
    assert float(parsed[0]["chamfer_l1"]) == pytest.approx(rows[0]["chamfer_l1"])
    assert json.loads(paths["json"].read_text()) == rows
    assert not list(tmp_path.glob(".*"))  # no temporaries left behind


def test_picture_is_png(run, torus_data, tmp_path):
    _, meshes = run
    path = C.picture({**meshes, "alpha": None}, tmp_path / "all.png", points=torus_data[0])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(path.read_bytes()[16:20], "big"), int.from_bytes(path.read_bytes()[20:24], "big")
    assert width == 4 * 420 and height == 420  # one panel per mesh, the failed one included
    with pytest.raises(ValueError, match="png"):
        C.picture(meshes, tmp_path / "all.jpg")


def test_unknown_method_lists_valid_ones(torus_data):
    with pytest.raises(ValueError, match="nope") as info:
        C.compare(torus_data[0], methods="multiorder,nope")
    for name in C.METHODS:
        assert name in str(info.value)
    with pytest.raises(ValueError, match="valid methods"):
        C.run_method("marching", torus_data[0])


def _cli(argv):
    parser = argparse.ArgumentParser(prog="o3drbf")
    sub = parser.add_subparsers(dest="command")
    C.add_compare_arguments(sub.add_parser("compare"))
    return parser.parse_args(argv)


def test_main_compare_end_to_end(torus_data, tmp_path, capsys):
    points, normals = torus_data
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    o3d.io.write_point_cloud(str(tmp_path / "torus.ply"), cloud)
    o3d.io.write_triangle_mesh(str(tmp_path / "truth.ply"), _truth())
    out = tmp_path / "out"
    args = _cli(["compare", str(tmp_path / "torus.ply"), "--truth", str(tmp_path / "truth.ply"),
                 "--methods", "multiorder,poisson", "-o", str(out), "--resolution", str(RES)])
    assert args.poisson_depth == 8 and args.density_quantile == 0.0 and args.seed == 0 and args.cameras is None
    assert C.main_compare(args) == 0
    for name in ("comparison.md", "comparison.csv", "comparison.json", "comparison.png"):
        assert (out / name).stat().st_size > 0, name
    rows = json.loads((out / "comparison.json").read_text())
    assert [r["method"] for r in rows] == ["multiorder", "poisson"]
    assert all(r["chamfer_l1"] < CHAMFER_BOUND[r["method"]] for r in rows)
    assert "| multiorder |" in capsys.readouterr().out

    bad = tmp_path / "broken.ply"
    bad.write_text("not a mesh\n")
    args.truth = str(bad)
    with pytest.raises(ValueError, match="broken.ply"):
        C.main_compare(args)
    args.truth, args.methods = None, "poisson,bogus"
    with pytest.raises(ValueError, match="valid methods: multiorder, thinplate"):
        C.main_compare(args)
