"""Lidar inputs (issue 28): LAS/LAZ and E57 with scanner poses, against synthetic scans of known shapes.

The scans are ray-cast from terrestrial scanners around an Open3D torus or
sphere (:mod:`o3drbf.synthetic.lidar`) and written by the repository's own
writers; the truth is the analytic shape (:mod:`o3drbf.synthetic.shapes`)
and the poses written.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

pytest.importorskip("laspy")
pytest.importorskip("lazrs")
pytest.importorskip("pye57")

import o3drbf  # noqa: E402
from o3drbf.cameras.lidar import load_e57  # noqa: E402
from o3drbf.cameras.model import Camera, load_cameras  # noqa: E402
from o3drbf.cli import main  # noqa: E402
from o3drbf.constraints.freespace import free_space_check  # noqa: E402
from o3drbf.io.files import point_count  # noqa: E402
from o3drbf.io.lidar import e57_scans, read_las  # noqa: E402
from o3drbf.mesh.metrics import point_distances  # noqa: E402
from o3drbf.synthetic.lidar import e57_scans_from, terrestrial_scans, write_e57, write_las  # noqa: E402
from o3drbf.synthetic.shapes import Sphere, Torus  # noqa: E402

TORUS = Torus(0.6, 0.25)
SCANNERS = [[2.5, 0.0, 1.2], [-1.25, 2.2, 1.0], [-1.25, -2.2, -1.0]]


def torus_mesh():
    return o3d.geometry.TriangleMesh.create_torus(TORUS.R, TORUS.r, 90, 45)


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Three terrestrial scans of the torus (world points, scanner of each point, scanners) and their E57 file."""
    folder = tmp_path_factory.mktemp("lidar")
    points, point_camera, cameras = terrestrial_scans(torus_mesh(), SCANNERS, step=0.8, noise=0.002, seed=0)
    path = write_e57(folder / "torus.e57", e57_scans_from(points, point_camera, cameras))
    return points, point_camera, cameras, path


def truth_errors(mesh, shape, seed=1):
    """Chamfer-like distances to the analytic shape: truth samples to the mesh, and |signed distance| of the vertices."""
    samples, _ = shape.sample(20_000, seed=seed)
    to_mesh = point_distances(samples, mesh)
    sd = np.abs(shape.signed_distance(np.asarray(mesh.vertices)))
    return float(to_mesh.mean()), float(sd.mean()), float(max(to_mesh.max(), sd.max()))


def test_e57_pose_round_trips(scans):
    points, point_camera, cameras, path = scans
    read = load_e57(path)
    assert read.format == "e57" and len(read) == 3 and read.names == [c.name for c in cameras]
    for got, want, position in zip(read, cameras, SCANNERS):
        assert got.kind == "center"
        np.testing.assert_allclose(got.center, position, atol=1e-12)  # the scanner stands at the pose's translation
        np.testing.assert_allclose(got.R, want.R, atol=1e-12)  # and keeps the scan's frame
    np.testing.assert_allclose(read.points, points, atol=1e-12)  # world coordinates as written
    assert np.array_equal(read.point_camera, point_camera)  # each point's scan index
    # the headers: one pose per scan, the counts without reading a point
    listed = e57_scans(path)
    assert [s.count for s in listed] == np.bincount(point_camera).tolist() and point_count(path) == len(points)
    # a scanner's orientation survives the JSON camera format
    back = Camera.from_dict(read[1].to_dict())
    np.testing.assert_allclose(back.R, read[1].R, atol=1e-15)
    np.testing.assert_allclose(back.center, read[1].center, atol=1e-15)
    assert len(load_cameras(path)) == 3  # an E57 file is a camera file too (--cameras scans.e57)


def test_e57_points_are_read_in_chunks(scans):
    points, point_camera, _, path = scans
    small = load_e57(path, chunk_size=97)  # many chunks per scan, a partial last one
    np.testing.assert_array_equal(small.points, load_e57(path).points)
    assert np.array_equal(small.point_camera, point_camera)


def test_e57_reconstructs_the_torus_with_its_scanners(scans):
    data = o3drbf.read_input(scans[3])
    assert len(data.cameras) == 3 and data.normals is None
    result = o3drbf.reconstruct(data, surface_count=1200, resolution=48)
    mesh, report = result.mesh, result.report
    assert report.cameras == 3 and min(report.points_seen_per_camera) > 0
    assert not report.normals_estimated  # the scanners orient the surface, no normals needed
    assert mesh.is_watertight() and mesh.euler_poincare_characteristic() == 0
    to_mesh, vertex_sd, worst = truth_errors(mesh, TORUS)
    print(f"E57 torus: truth -> mesh mean {to_mesh:.4f}, |sd| of vertices mean {vertex_sd:.4f}, max {worst:.4f}")
    assert to_mesh < 0.01 and vertex_sd < 0.005 and worst < 0.08


def test_free_space_check_rejects_spurious_returns_from_scanner_poses(tmp_path):
    points, point_camera, cameras = terrestrial_scans(torus_mesh(), SCANNERS, step=0.8, noise=0.002, outliers=0.02, seed=3)
    clean = len(terrestrial_scans(torus_mesh(), SCANNERS, step=0.8, noise=0.002, seed=3)[0])
    path = write_e57(tmp_path / "outliers.e57", e57_scans_from(points, point_camera, cameras))
    read = load_e57(path)
    order = np.concatenate([np.flatnonzero(point_camera == j) for j in range(len(cameras))])  # the file groups points by scan
    np.testing.assert_allclose(read.points, points[order], atol=1e-12)
    spurious = order >= clean  # the generator's last rows
    check = free_space_check(read.points, read.cameras, read.point_camera)
    caught, wrong = int(check.outlier[spurious].sum()), int(check.outlier[~spurious].sum())
    print(f"free space from E57 scanners: {caught} of {len(points) - clean} spurious returns caught, {wrong} of {clean} genuine points removed")
    assert check.cameras_used == 3
    assert caught >= 0.85 * (len(points) - clean) and wrong <= 0.005 * clean


def test_las_and_laz_read_back_and_reconstruct_a_sphere(tmp_path):
    points, _ = Sphere(1.0).sample(3000, noise=0.002, seed=1)  # all around: LAS has no scanner to tell the unseen
    colors = np.random.default_rng(0).uniform(size=points.shape)
    write_las(tmp_path / "s.las", points, colors)
    write_las(tmp_path / "s.laz", points)
    las, las_colors = read_las(tmp_path / "s.las", chunk_size=500)  # several chunks
    laz, laz_colors = read_las(tmp_path / "s.laz", chunk_size=500)
    np.testing.assert_allclose(las, points, atol=1e-5)  # the LAS scale
    np.testing.assert_array_equal(laz, las)
    np.testing.assert_allclose(las_colors, colors, atol=1e-4)
    assert laz_colors is None
    assert point_count(tmp_path / "s.laz") == len(points)
    data = o3drbf.read_input(tmp_path / "s.laz")
    assert data.cameras is None and data.normals is None  # points only: no pose in LAS
    result = o3drbf.reconstruct(data, surface_count=1000, resolution=40)
    assert result.report.normals_estimated
    assert result.mesh.is_watertight() and result.mesh.euler_poincare_characteristic() == 2
    to_mesh, vertex_sd, worst = truth_errors(result.mesh, Sphere(1.0))
    print(f"LAZ sphere: truth -> mesh mean {to_mesh:.4f}, |sd| of vertices mean {vertex_sd:.4f}, max {worst:.4f}")
    assert to_mesh < 0.01 and vertex_sd < 0.005 and worst < 0.08


def test_cli_reads_e57_and_tiles_auto_runs_untiled_when_it_fits(scans, tmp_path, capsys):
    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(scans[3]), "-o", str(out), "--tiles", "auto", "--surface-count", "600", "--resolution", "32"]) == 0
    captured = capsys.readouterr()
    said = [line for line in captured.err.splitlines() if "--tiles auto" in line]
    assert len(said) == 1 and "fit in memory without tiles" in said[0] and "running untiled" in said[0]
    assert "o3drbf reconstruct: " in captured.out and "cameras          3" in captured.out  # the untiled summary, with scanners
    assert o3d.io.read_triangle_mesh(str(out)).is_watertight()


def test_cli_tiles_auto_decides_once_read_when_the_header_has_no_count(tmp_path, capsys):
    points, normals = Sphere(1.0).sample(400, seed=2)
    np.savetxt(tmp_path / "s.xyzn", np.hstack([points, normals]))
    assert point_count(tmp_path / "s.xyzn") is None
    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(tmp_path / "s.xyzn"), "-o", str(out), "--tiles", "auto", "--surface-count", "200",
                 "--resolution", "24", "-q"]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "--tiles auto" in line]
    assert len(said) == 1 and "400 points fit in memory" in said[0] and out.exists()


def test_cli_tiles_auto_stays_tiled_when_the_input_does_not_fit(scans, tmp_path, capsys, monkeypatch):
    import o3drbf.cli.commands as commands

    monkeypatch.setattr("o3drbf.solvers.base.available_memory", lambda: 100 * 2**20)
    ran = {}
    monkeypatch.setattr(commands, "_reconstruct_tiled", lambda args, data, *a: ran.setdefault("tiles", args.tiles) and 0)
    assert main(["reconstruct", str(scans[3]), "-o", str(tmp_path / "m.ply"), "--tiles", "auto", "-q"]) == 0
    assert ran["tiles"] == "auto" and "running untiled" not in capsys.readouterr().err


def test_cli_tiles_on_e57_uses_the_scanners(scans, tmp_path, capsys):
    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(scans[3]), "-o", str(out), "--tiles", "2", "--scheduler", "synchronous",
                 "--resolution", "32"]) == 0
    captured = capsys.readouterr()
    assert "does not use cameras" not in captured.err
    summary = captured.out[captured.out.index("o3drbf reconstruct --tiles:"):]
    assert "tiles            2;" in summary and "watertight       yes" in summary and "1 component(s)" in summary
    assert "cameras          3: exterior constraints toward them and the free-space outlier test in every tile" in summary
    assert o3d.io.read_triangle_mesh(str(out)).is_watertight()
