"""Camera model and camera file formats (o3drbf.cameras.model)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from o3drbf.cameras.model import Camera, load_cameras, load_range_scans, quaternion_to_matrix, save_cameras_json

# K, R (90 degrees about z), t chosen so projection is easy by hand.
K = np.array([[100.0, 0.0, 50.0], [0.0, 200.0, 40.0], [0.0, 0.0, 1.0]])
R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
T = np.array([1.0, 2.0, 3.0])


def _cam():
    return Camera(K=K, R=R, t=T, width=100, height=200, name="hand")


def test_project_known_point():
    cam = _cam()
    # R X = (0, 1, 2); + t = (1, 3, 5); u = 100 * 1/5 + 50, v = 200 * 3/5 + 40.
    pixels, depth = cam.project([[1.0, 0.0, 2.0]])
    np.testing.assert_allclose(pixels, [[70.0, 160.0]])
    np.testing.assert_allclose(depth, [5.0])
    np.testing.assert_allclose(cam.center, [-2.0, 1.0, -3.0])  # -R^T t
    np.testing.assert_allclose(cam.direction, [0.0, 0.0, 1.0])
    front, inside = cam.in_view([[1.0, 0.0, 2.0], [0.0, 0.0, -10.0], [1.0, 10.0, 2.0]])
    assert front.tolist() == [True, False, True]
    # Third point: x_cam = (-9, 3, 5) -> u = -130, outside the 100-pixel-wide image.
    assert inside.tolist() == [True, False, False]


def test_toward_points_at_center_and_against_direction():
    cam = _cam()
    d, dist = cam.toward([[1.0, 0.0, 2.0]])
    np.testing.assert_allclose(dist, [np.linalg.norm([1 + 2, -1, 2 + 3])])
    np.testing.assert_allclose([1.0, 0.0, 2.0] + d[0] * dist[0], cam.center)
    scanner = Camera.from_direction([0.0, 0.0, -1.0])
    d, dist = scanner.toward(np.zeros((2, 3)))
    np.testing.assert_allclose(d, [[0, 0, 1], [0, 0, 1]], atol=1e-12)
    assert np.isinf(dist).all()


def test_look_at_projects_target_to_image_centre():
    cam = Camera.look_at([3.0, 1.0, 2.0], [0.0, 0.5, 0.0], up=(0, 0, 1), fov=60, width=64, height=48)
    pixels, depth = cam.project([[0.0, 0.5, 0.0]])
    np.testing.assert_allclose(pixels, [[32.0, 24.0]], atol=1e-9)
    # World up projects upward in the image (smaller v).
    above, _ = cam.project([[0.0, 0.5, 0.1]])
    assert above[0, 1] < 24.0


def test_json_round_trip(tmp_path):
    cams = [
        _cam(),
        Camera.from_center([1.0, 2.0, 3.0], name="c"),
        Camera.from_direction([0.0, 1.0, 0.0], name="d"),
    ]
    pts = np.random.default_rng(0).normal(size=(20, 3))
    pc = np.arange(20) % 3 - 1
    path = save_cameras_json(tmp_path / "cams.json", cams, points=pts, point_camera=pc)
    back = load_cameras(path)
    assert back.format == "json" and len(back) == 3
    assert [c.kind for c in back] == ["pinhole", "center", "direction"]
    assert back.names == ["hand", "c", "d"]
    for a, b in zip(cams, back):
        np.testing.assert_allclose(a.project(pts)[1], b.project(pts)[1])
        np.testing.assert_allclose(a.toward(pts)[0], b.toward(pts)[0])
    np.testing.assert_allclose(back[0].project(pts)[0], cams[0].project(pts)[0])
    np.testing.assert_array_equal(back.points, pts)
    np.testing.assert_array_equal(back.point_camera, pc)
    known = back.known_visible()
    assert known.shape == (20, 3) and known.sum() == (pc >= 0).sum()


def test_json_centers(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps({"centers": [[0, 0, 5], [5, 0, 0]]}))
    cams = load_cameras(path)
    assert [c.kind for c in cams] == ["center", "center"]
    np.testing.assert_allclose(cams[1].center, [5, 0, 0])


def _colmap_model(folder, cam, points, seen_by):
    folder.mkdir()
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    (folder / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        f"1 PINHOLE {cam.width} {cam.height} {fx:.17g} {fy:.17g} {cx:.17g} {cy:.17g}\n"
        f"2 SIMPLE_RADIAL {cam.width} {cam.height} {fx:.17g} {cx:.17g} {cy:.17g} 0.01\n"
    )
    qx, qy, qz, qw = Rotation.from_matrix(cam.R).as_quat()
    tx, ty, tz = cam.t
    (folder / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        f"7 {qw:.17g} {qx:.17g} {qy:.17g} {qz:.17g} {tx:.17g} {ty:.17g} {tz:.17g} 1 first.png\n"
        "10.5 20.5 0 30.5 40.5 -1\n"
        f"9 1 0 0 0 0 0 5 2 second.png\n"
        "\n"
    )
    lines = []
    for i, (p, images) in enumerate(zip(points, seen_by)):
        track = " ".join(f"{im} 0" for im in images)
        lines.append(f"{i + 1} {p[0]:.17g} {p[1]:.17g} {p[2]:.17g} 255 128 0 0.5 {track}")
    (folder / "points3D.txt").write_text("# 3D point list\n" + "\n".join(lines) + "\n")


def test_colmap_round_trip(tmp_path):
    cam = Camera(K=[[500.0, 0, 310.0], [0, 505.0, 245.0], [0, 0, 1]], R=Rotation.from_euler("xyz", [0.3, -0.5, 1.1]).as_matrix(), t=[0.1, -0.2, 4.0], width=640, height=480)
    pts = np.random.default_rng(1).normal(scale=0.5, size=(6, 3))
    _colmap_model(tmp_path / "sparse", cam, pts, [[7], [7, 9], [9], [7], [9, 7], [7]])
    for path in (tmp_path / "sparse", tmp_path / "sparse" / "images.txt", tmp_path):
        cams = load_cameras(path)
        assert cams.format == "colmap" and cams.names == ["first.png", "second.png"]
    np.testing.assert_allclose(cams[0].project(pts)[0], cam.project(pts)[0], atol=1e-9)
    assert (cams[0].width, cams[0].height) == (640, 480)
    np.testing.assert_allclose(cams[1].center, [0, 0, -5])
    np.testing.assert_allclose(cams.points, pts)
    np.testing.assert_allclose(cams.colors[0], [1.0, 128 / 255, 0.0])
    known = cams.known_visible()
    assert known.tolist() == [[True, False], [True, True], [False, True], [True, False], [True, True], [True, False]]


def test_bundler_round_trip(tmp_path):
    w, h, f = 640, 480, 700.0
    cam = Camera(K=[[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], R=Rotation.from_euler("zyx", [0.2, 0.4, -0.3]).as_matrix(), t=[0.3, 0.1, 3.0], width=w, height=h)
    flip = np.diag([1.0, -1.0, -1.0])
    Rb, tb = flip @ cam.R, flip @ cam.t  # Bundler looks along -z with y up
    pts = np.random.default_rng(2).normal(scale=0.3, size=(4, 3))
    lines = ["# Bundle file v0.3", "3 4", f"{f:.17g} 0 0"]
    lines += [" ".join(f"{x:.17g}" for x in row) for row in Rb] + [" ".join(f"{x:.17g}" for x in tb)]
    lines += ["0 0 0"] + ["0 0 0"] * 4  # camera 1 not registered
    lines += ["650 0 0", "1 0 0", "0 1 0", "0 0 1", "0 0 -4"]
    for i, p in enumerate(pts):
        views = "2 0 5 1.5 -2.5 2 6 3.0 1.0" if i % 2 else "1 0 5 1.5 -2.5"
        lines += [" ".join(f"{x:.17g}" for x in p), "10 20 30", views]
    (tmp_path / "bundle.out").write_text("\n".join(lines) + "\n")
    cams = load_cameras(tmp_path / "bundle.out", image_size=(w, h))
    assert cams.format == "bundler" and len(cams) == 2  # the zero camera is skipped
    np.testing.assert_allclose(cams[0].project(pts)[0], cam.project(pts)[0], atol=1e-9)
    np.testing.assert_allclose(cams[0].project(pts)[1], cam.project(pts)[1], atol=1e-12)
    np.testing.assert_allclose(cams[1].center, [0, 0, 4])
    np.testing.assert_allclose(cams[1].direction, [0, 0, -1])  # Bundler camera looking along its -z
    assert cams.known_visible().tolist() == [[True, False], [True, True], [True, False], [True, True]]
    assert load_cameras(tmp_path).format == "bundler"


def test_stanford_conf_convention(tmp_path):
    """p_world = R(q)^T p_scan + t with q in (x, y, z, w) order; the scanner looks along local -z."""
    q = Rotation.from_euler("xyz", [0.4, -0.7, 0.2]).as_quat()  # x, y, z, w
    t = np.array([0.01, -0.02, 0.03])
    scan = np.random.default_rng(3).normal(scale=0.05, size=(5, 3))
    header = f"ply\nformat ascii 1.0\nelement vertex {len(scan)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "a.ply").write_text(header + "\n".join(" ".join(f"{v:.9f}" for v in p) for p in scan) + "\n")
    (tmp_path / "b.ply").write_text(header + "\n".join(" ".join(f"{v:.9f}" for v in p) for p in scan) + "\n")
    (tmp_path / "s.conf").write_text(
        "camera 0 0 0 0 0 0 1\n" f"bmesh a.ply {t[0]} {t[1]} {t[2]} {q[0]:.17g} {q[1]:.17g} {q[2]:.17g} {q[3]:.17g}\n" "bmesh b.ply 0 0 0 0 0 0 1\n"
    )
    Rq = quaternion_to_matrix(*q)
    np.testing.assert_allclose(Rq, Rotation.from_quat(q).as_matrix(), atol=1e-12)
    cams = load_cameras(tmp_path / "s.conf")
    assert cams.points is None and [c.kind for c in cams] == ["direction", "direction"]
    data = load_range_scans(tmp_path / "s.conf")
    np.testing.assert_allclose(data.points[:5], scan @ Rq + t, atol=1e-6)  # rows: R^T p + t
    np.testing.assert_allclose(data.points[5:], scan, atol=1e-6)
    np.testing.assert_array_equal(data.point_camera, [0] * 5 + [1] * 5)
    np.testing.assert_allclose(cams[0].direction, -Rq.T[:, 2], atol=1e-12)
    np.testing.assert_allclose(cams[1].direction, [0, 0, -1], atol=1e-12)


PAR_LINE = "img{0}.png 1520.4 0 302.32 0 1525.9 246.87 0 0 1 1 0 0 0 1 0 0 0 1 0.1 0.2 0.6"


@pytest.mark.parametrize(
    "text, where, what",
    [
        ("2\n" + PAR_LINE.format(1) + "\n" + PAR_LINE.format(2).replace("1525.9", "x1525.9") + "\n", "line 3", "expected numbers"),
        ("2\n" + PAR_LINE.format(1) + "\n" + PAR_LINE.format(2).replace("0.6", "nan") + "\n", "line 3", "NaN"),
        ("2\n" + PAR_LINE.format(1) + "\n" + PAR_LINE.format(2).replace(" 1 0 0 0 1 0 0 0 1 ", " 1 0 0 0 1 0.3 0 0 1 ") + "\n", "line 3", "not orthonormal"),
        ("3\n" + PAR_LINE.format(1) + "\n" + PAR_LINE.format(2) + "\n", "", "count mismatch"),
        ("2\n" + PAR_LINE.format(1) + "\n" + PAR_LINE.format(2)[:-4] + "\n", "line 3", "22 fields"),
        ("two\n" + PAR_LINE.format(1) + "\n", "line 1", "image count"),
    ],
)
def test_malformed_middlebury_names_file_and_line(tmp_path, text, where, what):
    path = tmp_path / "bad_par.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=re.escape(str(path)) + ".*" + re.escape(where) + ".*" + what):
        load_cameras(path)


def test_malformed_files_name_file_and_entry(tmp_path):
    conf = tmp_path / "scan.conf"
    conf.write_text("bmesh missing.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"scan\.conf, line 1: scan file missing\.ply not found.*count mismatch"):
        load_cameras(conf)
    conf.write_text("camera 0 0 0 0 0 0 1\nbmesh a.ply 0 0 nan 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"scan\.conf, line 2: .*NaN"):
        load_cameras(conf)
    conf.write_text("bmesh a.ply 0 0 0 0 0 0 2\n")
    with pytest.raises(ValueError, match=r"scan\.conf, line 1: .*unit quaternion"):
        load_cameras(conf)
    js = tmp_path / "c.json"
    js.write_text(json.dumps({"cameras": [_cam().to_dict(), {**_cam().to_dict(), "R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}]}))
    with pytest.raises(ValueError, match=r"c\.json, cameras\[1\]: R is not orthonormal"):
        load_cameras(js)
    js.write_text(json.dumps({"cameras": [_cam().to_dict()], "points": [[0, 0, 0], [1, 1, 1]], "point_camera": [0, 3]}))
    with pytest.raises(ValueError, match=r"c\.json, point_camera\[1\]: .*1 camera.*count mismatch"):
        load_cameras(js)
    js.write_text('{"cameras": [\n  {"K": 1,}\n]}')
    with pytest.raises(ValueError, match=r"c\.json, line 2: invalid JSON"):
        load_cameras(js)
    out = tmp_path / "bundle.out"
    out.write_text("# Bundle file v0.3\n1 0\n500 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(ValueError, match=r"bundle\.out: file ends early"):
        load_cameras(out)
    with pytest.raises(ValueError, match="cannot tell the camera format"):
        (tmp_path / "x.txt").write_text("hello\n")
        load_cameras(tmp_path / "x.txt")
    with pytest.raises(FileNotFoundError):
        load_cameras(tmp_path / "nothing.json")


def test_camera_rejects_bad_parameters():
    with pytest.raises(ValueError, match="not orthonormal"):
        Camera(K=K, R=np.eye(3) * 1.1, t=T)
    with pytest.raises(ValueError, match="reflection"):
        Camera(K=K, R=np.diag([1.0, 1.0, -1.0]), t=T)
    with pytest.raises(ValueError, match="positive focal"):
        Camera(K=np.diag([-1.0, 1.0, 1.0]), R=R, t=T)
    with pytest.raises(ValueError, match="t must be a finite"):
        Camera(K=K, R=R, t=[0, np.nan, 0])
    with pytest.raises(ValueError, match="kind"):
        Camera(K=K, kind="fisheye")
