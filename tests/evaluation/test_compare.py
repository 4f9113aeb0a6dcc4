"""o3drbf.evaluation.compare: several methods on one sampled torus, tables, picture, CLI entry."""

from __future__ import annotations

import argparse
import csv
import json
import re

import numpy as np
import pytest

o3d = pytest.importorskip("open3d")

from o3drbf.cli.compare import add_compare_arguments, main_compare  # noqa: E402
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


# The markdown's headers, written out here (not read from compare.HUMAN_COLUMNS).
HUMAN = {
    "Method": "method", "Time (s)": "seconds", "Peak memory (MB)": "rss_peak_mb", "Triangles": "triangles",
    "Watertight": "watertight", "Pieces": "components", "Euler characteristic": "euler_characteristic",
    "Genus": "genus", "Fitness mean (data units)": "fitness_mean", "Mean curvature (1/data units)": "average_curvature",
    "Chamfer L1 (data units)": "chamfer_l1", "Hausdorff (data units)": "hausdorff", "F-score @ τ": "f_score",
    "Precision @ τ": "precision", "Recall @ τ": "recall", "Normal consistency": "normal_consistency",
}
NAMES = {"multiorder": "o3drbf multi-order (default)", "poisson": "Open3D Poisson (raw points)", "bpa": "Open3D ball pivoting"}


def _cell_matches(cell, value):
    if isinstance(value, bool):
        return cell == ("yes" if value else "no")
    if isinstance(value, int):
        return int(cell) == value
    return float(cell) == pytest.approx(value, rel=5e-4, abs=1e-12)


def test_tables(run, tmp_path):
    rows, _ = run
    paths = C.write_tables(rows, tmp_path, points=1500, reference="torus.ply")
    md = paths["markdown"].read_text().splitlines()
    # One line of shared settings above the table: points, reference, tau.
    tau = rows[0]["f_threshold"]
    assert md[0].startswith("1,500 input points · reference: torus.ply · τ = ") and md[1] == ""
    assert float(md[0].split("τ = ")[1].split()[0]) == pytest.approx(tau, rel=5e-4)
    table = [line for line in md if line.startswith("|")]
    header = [h.strip() for h in table[0].strip("|").split("|")]
    assert header == list(HUMAN)  # human names, one memory column, no constant f_threshold column
    assert set(table[1]) <= set("|-") and len(table) == 2 + len(METHODS)
    assert not any("_" in h for h in header)
    for line, row in zip(table[2:], rows):
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[0] == NAMES[row["method"]]
        for head, cell in zip(header[1:], cells[1:]):
            value = row[HUMAN[head]]
            assert (cell == "") if value is None else _cell_matches(cell, value), (head, cell, value)
    assert any(line.startswith("Peak memory: growth of the process's resident memory") for line in md)
    # The machine-readable files keep the raw names, f_threshold and the tracemalloc peak included.
    with open(paths["csv"], newline="") as fh:
        parsed = list(csv.DictReader(fh))
    assert [r["method"] for r in parsed] == list(METHODS)
    assert float(parsed[0]["chamfer_l1"]) == pytest.approx(rows[0]["chamfer_l1"])
    assert float(parsed[0]["f_threshold"]) == tau and float(parsed[0]["peak_mb"]) == rows[0]["peak_mb"]
    assert json.loads(paths["json"].read_text()) == rows
    assert not list(tmp_path.glob(".*"))  # no temporaries left behind


def test_failed_rows_get_an_error_column(tmp_path):
    rows = [{"method": "bpa", "error": "RuntimeError: bpa produced no triangles"}, {"method": "poisson", "seconds": 0.5, "triangles": 10}]
    md = C.markdown_table(rows, points=50)
    table = [line for line in md.splitlines() if line.startswith("|")]
    assert table[0] == "| Method | Time (s) | Triangles | Error |"
    assert table[2] == "| Open3D ball pivoting |  |  | RuntimeError: bpa produced no triangles |"
    assert md.startswith("50 input points · no reference mesh")


SIZE = 160  # pixels per panel in the picture tests


def _png_size(path):
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _panel(image, row, col):
    from o3drbf.pictures import HEADER_HEIGHT

    y = HEADER_HEIGHT + row * SIZE
    return image[y + 70 : y + 140, col * SIZE + 5 : (col + 1) * SIZE - 5]  # below the titles, above the view names


def test_picture_grid(run, torus_data, tmp_path):
    from PIL import Image

    from o3drbf.pictures import HEADER_HEIGHT

    rows, meshes = run
    rows = [*rows, {**dict.fromkeys(C.COLUMNS), "method": "alpha", "error": "RuntimeError: alpha produced no triangles"}]
    meshes = {**meshes, "alpha": None}
    panels, header, clim, bounds = C.picture_panels(rows, meshes, torus_data[0], _truth(), "torus.ply")
    assert bounds == pytest.approx([-0.935, 0.935, -0.935, 0.935, -0.335, 0.335], abs=1e-3)  # the torus' box + 5% of 1.7
    # Rows: points, truth, one per method (the failed one included); columns: four views, one from below.
    assert len(panels) == 2 + len(rows) and all(len(r) == 4 for r in panels)
    assert [p.view for p in panels[0]] == ["front", "side", "top", "below"]
    assert panels[0][0].points is not None and all(p.mesh is None for p in panels[0])  # points on their own
    assert panels[1][0].mesh is not None and panels[1][0].scalars is None and panels[1][0].title.startswith("reference: torus.ply")
    tau = rows[0]["f_threshold"]
    assert clim == (0.0, pytest.approx(2 * tau)) and f"{tau:.4g}" in header
    for row, line in zip(rows, panels[2:]):
        title = line[0].title
        assert title.splitlines()[0] == NAMES.get(row["method"], "Open3D alpha shape")
        if row["error"]:
            assert "FAILED" in title and all(p.mesh is None for p in line)
            continue
        numbers = dict(re.findall(r"(Chamfer L1|F-score) ([0-9.e-]+)", title))
        assert float(numbers["Chamfer L1"]) == pytest.approx(row["chamfer_l1"], rel=5e-4)
        assert float(numbers["F-score"]) == pytest.approx(row["f_score"], rel=5e-4)
        pieces = row["components"]
        assert f"watertight {'yes' if row['watertight'] else 'no'}, {pieces} piece{'' if pieces == 1 else 's'}" in title
        assert len(line[0].scalars) == len(meshes[row["method"]].vertices)
    path = C.picture(meshes, tmp_path / "all.png", points=torus_data[0], rows=rows, truth=_truth(), panel_size=SIZE)
    assert _png_size(path) == (4 * SIZE, HEADER_HEIGHT + len(panels) * SIZE)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    drawn = [[(_panel(image, i, j) < 230).any(axis=2).mean() for j in range(4)] for i in range(len(panels))]
    assert min(min(r) for r in drawn[:-1]) > 0.05  # every view of points, truth and meshes holds something
    assert max(drawn[-1]) == 0.0  # the failed method's row is empty below its title
    for i in range(len(panels)):  # titles drawn at the top left of each row's first panel only
        y = HEADER_HEIGHT + i * SIZE
        assert (image[y + 2 : y + 14, 2:60] < 100).any() and not (image[y + 2 : y + 14, SIZE + 2 : SIZE + 60] < 100).any()
    with pytest.raises(ValueError, match="png"):
        C.picture(meshes, tmp_path / "all.jpg")


def _colour_fraction(panel, rgb, tol=60):
    return (np.abs(panel - np.array(rgb)).sum(axis=2) < tol).mean()


def _reddish(panel):
    r, g, b = panel[..., 0], panel[..., 1], panel[..., 2]
    return ((r - g > 50) & (r - b > 30)).mean()


def test_picture_distance_colours_and_hidden_pieces(tmp_path):
    from PIL import Image

    from o3drbf.pictures import PIECE_COLOR

    truth = o3d.geometry.TriangleMesh.create_sphere(1.0, 40)
    tau = 0.01 * np.linalg.norm(np.ptp(np.asarray(truth.vertices), axis=0))
    bigger = o3d.geometry.TriangleMesh.create_sphere(1.0 + tau, 40)  # every vertex tau from the truth
    inner = o3d.geometry.TriangleMesh.create_sphere(0.4, 20)
    two = bigger + inner
    rows = [{"method": "poisson", "f_threshold": tau, "components": 1, "watertight": True}, {"method": "thinplate", "f_threshold": tau, "components": 2, "watertight": True}]
    panels, _, clim, _ = C.picture_panels(rows, {"poisson": bigger, "thinplate": two}, truth=truth)
    assert clim == (0.0, pytest.approx(2 * tau))
    assert np.asarray(panels[1][0].scalars) == pytest.approx(tau, rel=0.02)  # distance to the truth, per vertex
    assert "2 pieces" in panels[2][0].title
    path = C.picture({"poisson": bigger, "thinplate": two}, tmp_path / "p.png", rows=rows, truth=truth, panel_size=SIZE)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert PIECE_COLOR == "#e8112d"  # red: not in viridis, not the orange of back faces
    for view in range(4):
        assert _reddish(_panel(image, 1, view)) == 0.0  # one piece: no red
        assert _reddish(_panel(image, 2, view)) > 0.03  # the inner piece, seen through the outer one


def test_views_follow_the_up_axis():
    from o3drbf.pictures import views_around

    for up in ([0, 0, 1], [0, 1, 0], [-1, 0, 0]):
        views = views_around(up)
        assert np.asarray(views["top"][0]) == pytest.approx(up) and np.asarray(views["below"][0]) == pytest.approx(-np.asarray(up, float))
        assert np.dot(views["top"][1], up) == pytest.approx(0.0)  # screen-up of the top view lies in the ground plane
        assert np.dot(views["front"][0], up) > 0 and np.dot(views["side"][0], up) > 0  # seen slightly from above
    assert _cli(["compare", "in.ply", "--up", "y"]).up == "y"


def test_picture_below_view_sees_the_underside(tmp_path):
    from PIL import Image

    # The upper half of a torus: from below, its inside (back faces, orange) shows; from above, none.
    mesh = _truth()
    tris = np.asarray(mesh.triangles)
    upper = np.asarray(mesh.vertices)[tris].mean(axis=1)[:, 2] > 0.0
    mesh.triangles = o3d.utility.Vector3iVector(tris[upper])
    path = C.picture({"bpa": mesh}, tmp_path / "half.png", rows=[{"method": "bpa", "components": 1, "watertight": False}], panel_size=SIZE)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    orange = (0xE8, 0xA3, 0x3C)
    top, below = _colour_fraction(_panel(image, 0, 2), orange, 90), _colour_fraction(_panel(image, 0, 3), orange, 90)
    assert top < 0.01 and below > 0.1, (top, below)


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
    add_compare_arguments(sub.add_parser("compare"))
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
    assert args.poisson_depth == 8 and args.density_quantile == 0.0 and args.seed == 0 and args.cameras is None and args.up == "z"
    assert main_compare(args) == 0
    for name in ("comparison.md", "comparison.csv", "comparison.json", "comparison.png"):
        assert (out / name).stat().st_size > 0, name
    rows = json.loads((out / "comparison.json").read_text())
    assert [r["method"] for r in rows] == ["multiorder", "poisson"]
    assert all(r["chamfer_l1"] < CHAMFER_BOUND[r["method"]] for r in rows)
    assert "| o3drbf multi-order (default) |" in capsys.readouterr().out
    md = (out / "comparison.md").read_text().splitlines()
    assert md[0].startswith("1,500 input points · reference: truth.ply · τ = ")
    assert [line for line in md if line.startswith("|")][0].startswith("| Method | Time (s) | Peak memory (MB) |")

    bad = tmp_path / "broken.ply"
    bad.write_text("not a mesh\n")
    args.truth = str(bad)
    with pytest.raises(ValueError, match="broken.ply"):
        main_compare(args)
    args.truth, args.methods = None, "poisson,bogus"
    with pytest.raises(ValueError, match="valid methods: multiorder, thinplate"):
        main_compare(args)


def test_poisson_both_ways_on_scans_with_outliers():
    # Poisson on the raw points and as Open3D's tutorial runs it (statistical outliers removed, 5 % density trim),
    # both labelled in the table and the picture's titles.
    from o3drbf.synthetic.scans import range_scans

    points, owner, cams = range_scans(_truth(), n_views=3, width=80, height=60, noise=0.002, outliers=0.02, seed=0)
    rows, meshes = C.compare_with_meshes(points, None, cams, _truth(), methods="poisson,poisson-tutorial", point_camera=owner, n_samples=N_SAMPLES)
    by = {r["method"]: r for r in rows}
    assert all(r["error"] is None for r in rows), rows
    raw, tutorial = by["poisson"], by["poisson-tutorial"]
    assert tutorial["chamfer_l1"] < 0.2 * raw["chamfer_l1"] and tutorial["f_score"] > raw["f_score"], (raw, tutorial)
    assert not tutorial["watertight"]  # trimmed: never closed
    table = C.markdown_table(rows, len(points), "torus.ply")
    assert "| Open3D Poisson (raw points) |" in table
    assert "| Open3D Poisson (tutorial: outlier removal + density trim) |" in table
    titles = [C.row_title(r) for r in rows]
    assert titles[0].startswith("Open3D Poisson (raw points)\nChamfer")
    assert titles[1].replace("\n", " ").startswith("Open3D Poisson (tutorial: outlier removal + density trim) Chamfer")
    assert "poisson-tutorial" in C.available_methods()


def test_both_poissons_get_the_clouds_normals(torus_data, monkeypatch):
    points, normals = torus_data

    def no_estimate(*args, **kwargs):
        raise AssertionError("the cloud has normals: none should be estimated")

    monkeypatch.setattr(C, "open3d_normals", no_estimate)
    rows = C.compare(points, normals, methods="poisson,poisson-tutorial")
    assert [r["error"] for r in rows] == [None, None]


def test_poisson_takes_one_thread_on_a_busy_machine_and_all_otherwise(torus_data, monkeypatch):
    """Open3D's threaded Poisson crashes at random with the cores oversubscribed (isl-org/Open3D#6828).

    The threads asked for are recorded, and Poisson then runs on one thread: this test runs beside
    others (pytest-xdist), where the threaded Poisson it checks for would be the random crash."""
    import open3d as o3d

    from o3drbf.evaluation import peers
    from o3drbf.solvers import base

    points, normals = torus_data
    asked = []
    original = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson

    def recording(pcd, depth=8, **kwargs):
        asked.append(kwargs.get("n_threads", -1))
        return original(pcd, depth=depth, **dict(kwargs, n_threads=1))

    monkeypatch.setattr(o3d.geometry.TriangleMesh, "create_from_point_cloud_poisson", recording)
    for busy in (True, False):
        monkeypatch.setattr(base, "busy_machine", lambda busy=busy: busy)
        mesh = peers.poisson(points, normals, depth=5)
        assert len(mesh.triangles) > 0
    peers.poisson(points, normals, depth=5, threads=2)
    assert asked == [1, -1, 2]
