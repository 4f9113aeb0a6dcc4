"""Cameras end to end: synthetic range scans of a torus -> scan JSON / PLY + camera file -> closed mesh.

Three pinhole range scans 120 degrees apart (elevation 20 degrees, so the
underside of the torus is never seen), Gaussian noise along the rays and 2 %
uniform outliers, reconstructed through the command line and the API with
the cameras placing the exterior constraints.  Then the bad-input cases of
issue 3 that reach ``reconstruct``: each must exit 2 with one line naming
the file and the entry.  No shared data needed.
"""

from __future__ import annotations

import re

import json

import numpy as np
import open3d as o3d
import pytest

from o3drbf import reconstruct
from o3drbf.cameras.model import Camera, save_cameras_json
from o3drbf.cli.commands import main
from o3drbf.io.files import write_points
from o3drbf.mesh.metrics import mesh_report
from o3drbf.synthetic.scans import range_scans, write_scan_json
from o3drbf.synthetic.shapes import Torus

TORUS = Torus(0.7, 0.25)
NOISE = 0.003  # standard deviation along the rays (tube radius 0.25)
OUTLIERS = 0.02
SCAN = dict(n_views=3, elevation=20.0, width=120, height=90, noise=NOISE, outliers=OUTLIERS, seed=1)
FIT = ["--outliers", "largest", "--surface-count", "1500", "--resolution", "64"]

# Area-weighted mean |signed distance| of the reconstruction to the analytic torus.
# Measured with the default (automatic) parameters: 0.0086 over the whole mesh
# and 0.0017 over the upper half (z > 0) for this scan (the paper's fixed
# parameters: 0.0144 and 0.0039).  The upper half is seen by all three
# scanners, so its error is below the ray noise (sigma 0.003): bound 0.003.
# The underside is seen by no scanner and is filled in by the regularization
# alone: the delta floor of 8 (o3drbf.constraints.parameters) closes unseen
# regions flatter, right for the flat undersides of parts, a little flat for
# a torus's round one (0.0044 at delta 4, 0.0065 at 6), hence the
# whole-surface bound 0.011 (1.3x the measurement).  Both can fail: moving
# the mesh down by 0.01 gives 0.0081 on the upper half, moving it sideways by
# 0.02 gives 0.0142 overall, scaling it by 1.02 gives 0.0148 / 0.0098
# (checked in the test).
MEAN_BOUND = 0.011
UPPER_MEAN_BOUND = 0.003


def torus_mesh():
    return o3d.geometry.TriangleMesh.create_torus(torus_radius=TORUS.R, tube_radius=TORUS.r, radial_resolution=120, tubular_resolution=60)


def distance_to_torus(mesh, shift=(0.0, 0.0, 0.0), scale=1.0):
    """Area-weighted mean |SDF| of the true torus over the mesh: (all, upper half z > 0)."""
    v = scale * np.asarray(mesh.vertices) + np.asarray(shift)
    t = np.asarray(mesh.triangles)
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    centroid = (a + b + c) / 3
    d = np.abs(TORUS.signed_distance(centroid))
    up = centroid[:, 2] > 0
    return float((area * d).sum() / area.sum()), float((area[up] * d[up]).sum() / area[up].sum())


def check_torus(mesh):
    rep = mesh_report(mesh)
    assert rep["closed"] and rep["watertight"], rep
    assert rep["components"] == 1 and rep["genus"] == 1 and rep["euler_characteristic"] == 0, rep
    mean, upper = distance_to_torus(mesh)
    assert mean < MEAN_BOUND, f"mean distance to the torus {mean:.4f}"
    assert upper < UPPER_MEAN_BOUND, f"mean distance over the seen upper half {upper:.4f}"
    return mean, upper


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("camera_pipeline")
    points, owner, cams = range_scans(torus_mesh(), **SCAN)
    write_scan_json(d / "scan.json", points, cams, owner)
    write_points(d / "points.ply", points)  # a plain point cloud: no normals, no cameras
    save_cameras_json(d / "cameras.json", cams)
    return d, points, owner, cams


def test_scans_hold_noise_and_outliers(scans):
    _, points, owner, cams = scans
    assert len(cams) == 3 and np.bincount(owner).min() > 1000
    d = np.abs(TORUS.signed_distance(points))
    n_out = OUTLIERS * len(points)  # the last rows, uniform in the bounding box
    assert (d > 10 * NOISE).sum() >= 0.5 * n_out  # the outliers are there, far from the surface
    assert np.median(d) < 2 * NOISE


def test_cli_scan_json_and_api_with_cameras(scans, capsys):
    d, points, owner, cams = scans
    out = d / "cli.ply"
    # The command line and the API share one table of defaults, so both build the same mesh.
    assert main(["reconstruct", str(d / "scan.json"), "-o", str(out), *FIT]) == 0
    text = capsys.readouterr().out
    assert "cameras          3; surface constraints seen per camera" in text
    assert re.search(r"outliers         [1-9][\d,]* removed \(largest", text) and "watertight       yes" in text
    cli_mesh = o3d.io.read_triangle_mesh(str(out))
    check_torus(cli_mesh)

    rec = reconstruct(points, cameras=cams, point_camera=owner, outliers="largest", surface_count=1500, resolution=64)
    check_torus(rec.mesh)
    s = rec.stats
    assert s["cameras"] == 3 and min(s["points_seen_per_camera"]) > 300
    assert s["outliers_removed"] > 0.5 * OUTLIERS * len(points)
    assert 120 <= s["exterior_constraints"] <= 180  # ~ one per ten surface constraints
    ext = rec.constraints.select(1)  # EXTERIOR
    # Exterior constraints toward the cameras: on the seen side and outside the torus
    # (a few may follow the outliers that survive next to the surface).
    assert (TORUS.signed_distance(ext) > 0).mean() > 0.99
    # The JSON round trip is exact: the command line and the API build the same mesh.
    assert len(cli_mesh.vertices) == len(rec.mesh.vertices)
    np.testing.assert_allclose(np.asarray(cli_mesh.vertices), np.asarray(rec.mesh.vertices), atol=1e-6)

    # The bounds can fail: the same mesh moved or scaled slightly does.
    assert distance_to_torus(rec.mesh, shift=(0, 0, -0.01))[1] > UPPER_MEAN_BOUND
    assert distance_to_torus(rec.mesh, shift=(0.02, 0, 0))[0] > MEAN_BOUND
    assert all(m > b for m, b in zip(distance_to_torus(rec.mesh, scale=1.02), (MEAN_BOUND, UPPER_MEAN_BOUND)))


def test_cli_plain_ply_with_camera_file(scans, capsys):
    d, *_ = scans
    out = d / "ply_cameras.ply"
    assert main(["reconstruct", str(d / "points.ply"), "--cameras", str(d / "cameras.json"), "-o", str(out), *FIT]) == 0
    text = capsys.readouterr().out
    assert "normals estimated" not in text  # the cameras, not estimated normals, orient the fit
    assert "cameras          3;" in text
    check_torus(o3d.io.read_triangle_mesh(str(out)))


# -- bad input -----------------------------------------------------------------


def _par_line(cam):
    values = [*cam.K.ravel(), *cam.R.ravel(), *cam.t]
    return f"{cam.name.replace(' ', '_')}.png " + " ".join(f"{x:.12g}" for x in values)


@pytest.fixture(scope="module")
def bad(scans):
    """Broken camera files next to the good scans; values are (INPUT args, text the error must contain)."""
    d, points, owner, cams = scans
    away = Camera.look_at(eye=[0, 0, 5], target=[0, 0, 10], up=(0, 1, 0), name="away")
    away2 = Camera.look_at(eye=[5, 0, 0], target=[10, 0, 0], name="away2")
    write_scan_json(d / "blind.json", points, [*cams, away], owner)
    save_cameras_json(d / "cams_blind.json", [*cams, away])
    save_cameras_json(d / "behind.json", [away, away2])
    scan = json.loads((d / "scan.json").read_text())
    scan["point_camera"][5] = 3
    (d / "index_mismatch.json").write_text(json.dumps(scan))
    scan = json.loads((d / "scan.json").read_text())
    scan["point_camera"] = scan["point_camera"][:-4]
    (d / "length_mismatch.json").write_text(json.dumps(scan))
    cam = json.loads((d / "cameras.json").read_text())
    cam["cameras"][1]["t"][2] = float("nan")  # Python's json writes NaN
    (d / "nan.json").write_text(json.dumps(cam))
    cam = json.loads((d / "cameras.json").read_text())
    cam["cameras"][2]["K"] = [[1, 0], [0, 1]]
    (d / "malformed.json").write_text(json.dumps(cam))
    lines = [_par_line(c) for c in cams]
    (d / "count_par.txt").write_text("4\n" + "\n".join(lines) + "\n")
    (d / "malformed_par.txt").write_text("3\n" + "\n".join([*lines[:2], lines[2].rsplit(" ", 1)[0]]) + "\n")
    (d / "nan_par.txt").write_text("3\n" + "\n".join([lines[0], lines[1].rsplit(" ", 1)[0] + " nan", lines[2]]) + "\n")
    conf = d / "scans.conf"
    write_points(d / "s0.ply", points[owner == 0])
    conf.write_text("bmesh s0.ply 0 0 0 0 0 0 1\nbmesh s1.ply 0 0 0 0 nan 0 1\n")
    (d / "missing.conf").write_text("bmesh s0.ply 0 0 0 0 0 0 1\nbmesh gone.ply 0 0 0 0 0 0 1\n")
    ply = str(d / "points.ply")
    return d, {
        "camera sees no point (scan json)": ([str(d / "blind.json")], ["camera 3 (away)", "see no point"]),
        "camera sees no point (--cameras)": ([ply, "--cameras", str(d / "cams_blind.json")], ["camera 3 (away)", "see no point"]),
        "points behind every camera": ([ply, "--cameras", str(d / "behind.json")], ["behind every camera"]),
        "point_camera index beyond the camera count": ([str(d / "index_mismatch.json")], ["index_mismatch.json", "point_camera[5]", "count mismatch"]),
        "point_camera length differs from the points": ([str(d / "length_mismatch.json")], ["length_mismatch.json", "point_camera", "count mismatch"]),
        "Middlebury count line differs": ([ply, "--cameras", str(d / "count_par.txt")], ["count_par.txt", "line 1", "count mismatch"]),
        ".conf lists a scan that is missing": ([str(d / "missing.conf")], ["missing.conf", "line 2", "gone.ply"]),
        "malformed Middlebury line": ([ply, "--cameras", str(d / "malformed_par.txt")], ["malformed_par.txt", "line 4", "22 fields"]),
        "malformed JSON camera": ([ply, "--cameras", str(d / "malformed.json")], ["malformed.json", "cameras[2]", "K must have shape"]),
        "NaN in a JSON pose": ([ply, "--cameras", str(d / "nan.json")], ["nan.json", "cameras[1]", "NaN"]),
        "NaN in a Middlebury pose": ([ply, "--cameras", str(d / "nan_par.txt")], ["nan_par.txt", "line 3", "NaN"]),
        "NaN in a .conf quaternion": ([str(conf)], ["scans.conf", "line 2", "NaN"]),
    }


CASES = [
    "camera sees no point (scan json)",
    "camera sees no point (--cameras)",
    "points behind every camera",
    "point_camera index beyond the camera count",
    "point_camera length differs from the points",
    "Middlebury count line differs",
    ".conf lists a scan that is missing",
    "malformed Middlebury line",
    "malformed JSON camera",
    "NaN in a JSON pose",
    "NaN in a Middlebury pose",
    "NaN in a .conf quaternion",
]


@pytest.mark.parametrize("case", CASES)
def test_bad_input_exits_2_with_one_line(bad, case, capsys):
    d, cases = bad
    args, needles = cases[case]
    out = d / "never.ply"
    assert main(["reconstruct", *args, "-o", str(out), *FIT, "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("o3drbf: error:") and "\n" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)
    assert not out.exists()


@pytest.mark.parametrize("case", ["camera sees no point (--cameras)", "points behind every camera"])
def test_visibility_errors_name_the_camera_file(bad, case, capsys):
    d, cases = bad
    args, _ = cases[case]
    assert main(["reconstruct", *args, "-o", str(d / "never.ply"), *FIT, "-q"]) == 2
    assert args[-1].rsplit("/", 1)[-1] in capsys.readouterr().err
