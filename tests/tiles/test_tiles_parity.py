"""The tiled path keeps the default path's behaviour (issue 28): scanners' free space, outliers, denoising, summary.

A 3-view range scan of a torus (noise and 3 % spurious returns in the
cameras' free space): the untiled ``reconstruct`` and ``reconstruct_tiled``
on the same points and cameras are compared by Chamfer distance to the
analytic torus.  The tiled fit must be about as good, catch about as many
outliers, and be clearly better than the same tiles with outliers kept.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3drbf.mesh.metrics import chamfer
from o3drbf.synthetic.scans import range_scans
from o3drbf.synthetic.shapes import Torus

TORUS = Torus(0.7, 0.25)
SCAN = dict(n_views=3, elevation=25.0, width=110, height=85, noise=0.002, outliers=0.03, seed=4)
RESOLUTION = 64


@pytest.fixture(scope="module")
def scan():
    mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=TORUS.R, tube_radius=TORUS.r, radial_resolution=120,
                                                  tubular_resolution=60)
    points, owner, cameras = range_scans(mesh, **SCAN)
    return points, owner, cameras


@pytest.fixture(scope="module")
def truth():
    return TORUS.sample(40000, seed=11)[0]


@pytest.fixture(scope="module")
def untiled(scan):
    from o3drbf import reconstruct

    points, owner, cameras = scan
    return reconstruct(points, cameras=cameras, point_camera=owner, resolution=RESOLUTION)


def tiled(scan, **options):
    from o3drbf.tiles.run import reconstruct_tiled

    points, owner, cameras = scan
    return reconstruct_tiled(points, cameras=cameras, point_camera=owner, tiles=3, scheduler="synchronous", resolution=RESOLUTION,
                             **options)


def test_tiled_scan_with_outliers_and_cameras_is_as_good_as_untiled(scan, truth, untiled):
    points, owner, cameras = scan
    planted = int(round(SCAN["outliers"] * len(points)))
    surface, mesh, stats = tiled(scan)
    d_tiled = chamfer(mesh, truth, n_samples=40000)["l1"]
    d_untiled = chamfer(untiled.mesh, truth, n_samples=40000)["l1"]
    _, kept_mesh, kept_stats = tiled(scan, outliers="none")
    d_kept = chamfer(kept_mesh, truth, n_samples=40000)["l1"]
    print(f"Chamfer L1 to the torus: untiled {d_untiled:.5f} ({untiled.report.outliers_removed} outliers removed), "
          f"tiled {d_tiled:.5f} ({stats['outliers']} removed; {planted} planted), tiled with outliers kept {d_kept:.5f}")
    assert mesh.is_watertight() and mesh.euler_poincare_characteristic() == 0
    assert len(mesh.cluster_connected_triangles()[1]) == 1
    assert d_tiled < 1.25 * d_untiled
    assert d_kept > 1.5 * d_tiled  # the test has teeth: outliers left in the tiles spoil the surface
    # The outliers caught, each point counted once (in the tile whose cell holds it), about as many as untiled.
    assert stats["points"] == len(points) and stats["kept"] + stats["outliers"] == len(points)
    assert 0.8 * untiled.report.outliers_removed <= stats["outliers"] <= 1.2 * untiled.report.outliers_removed
    assert stats["outliers"] >= 0.8 * planted
    assert kept_stats["outliers"] == 0
    # Free space: every tile builds exterior constraints toward the scanners (no normals were given).
    assert stats["cameras"] == 3 and all(t["exterior"] > 0 for t in surface.metadata["tiles"])


def test_tiled_noisy_points_are_denoised_like_untiled(truth):
    """Noisy points with normals (no cameras): tiles move their constraints onto local fits when the untiled path would."""
    from o3drbf import reconstruct
    from o3drbf.tiles.run import reconstruct_tiled

    pts, nrm = TORUS.sample(9000, noise=0.01, seed=3)
    ref = reconstruct(pts, nrm, resolution=RESOLUTION)
    assert ref.report.denoised  # the untiled path denoises these
    surface, mesh, stats = reconstruct_tiled(pts, nrm, tiles=3, scheduler="synchronous", resolution=RESOLUTION)
    _, raw, _ = reconstruct_tiled(pts, nrm, tiles=3, scheduler="synchronous", resolution=RESOLUTION, denoise=False)
    d = {name: chamfer(m, truth, n_samples=40000)["l1"] for name, m in (("untiled", ref.mesh), ("tiled", mesh), ("raw", raw))}
    print("Chamfer L1 to the torus:", {k: round(v, 5) for k, v in d.items()})
    assert stats["denoised_tiles"] == 3 and all(t["denoised"] > 0 for t in surface.metadata["tiles"])
    assert d["tiled"] < 1.25 * d["untiled"] and d["tiled"] < d["raw"]


def test_cli_tiled_summary_has_the_untiled_lines(scan, tmp_path, capsys):
    from o3drbf.cli import main
    from o3drbf.synthetic.scans import write_scan_json

    points, owner, cameras = scan
    write_scan_json(tmp_path / "scan.json", points, cameras, owner)
    out = tmp_path / "m.ply"
    assert main(["reconstruct", str(tmp_path / "scan.json"), "-o", str(out), "--tiles", "3", "--scheduler", "synchronous",
                 "--resolution", str(RESOLUTION)]) == 0
    text = capsys.readouterr().out
    n = len(points)
    assert f"  points           {n:,} read, " in text and "removed as outliers)" in text
    assert "  cameras          3: exterior constraints toward them" in text
    assert "  watertight       yes (Open3D's is_watertight" in text and "1 component(s)" in text
    assert o3d.io.read_triangle_mesh(str(out)).is_watertight()


def test_docstring_examples_of_the_tiled_entry_points_run():
    import doctest

    import o3drbf.tiles.extract
    import o3drbf.tiles.fit
    import o3drbf.tiles.run

    for module in (o3drbf.tiles.fit, o3drbf.tiles.extract, o3drbf.tiles.run):
        result = doctest.testmod(module)
        assert result.attempted > 0 and result.failed == 0, module.__name__


def test_tiled_camera_at_a_surface_point_is_dropped_in_every_tile(caplog):
    """As untiled (tests/test_faults.py): the camera is dropped once, from the sample, and its points' camera index
    is remapped in every tile (the other cameras keep theirs)."""
    from o3drbf.cameras.model import Camera
    from o3drbf.synthetic.scans import camera_ring
    from o3drbf.synthetic.shapes import Sphere
    from o3drbf.tiles.run import reconstruct_tiled

    points, _ = Sphere(1.0).sample(3000, seed=2)
    cams = camera_ring((0, 0, 0), 1.0, n_views=6, elevation=35, width=80, height=60, fov=50) + camera_ring(
        (0, 0, 0), 1.0, n_views=6, elevation=-35, width=80, height=60, fov=50, azimuth=30)
    bad = Camera.from_center(points[0], name="bad")
    centres = np.array([c.center for c in cams])
    pc = np.argmin(((points[:, None] - centres[None]) ** 2).sum(-1), axis=1)
    pc[np.linalg.norm(points - points[0], axis=1) < 0.5] = 0  # seen by the bad camera, listed first
    pc[np.linalg.norm(points - points[0], axis=1) >= 0.5] += 1
    with caplog.at_level("WARNING", logger="o3drbf"):
        surface, mesh, stats = reconstruct_tiled(points, cameras=[bad] + cams, point_camera=pc, tiles=3, scheduler="synchronous",
                                                 resolution=32, surface_count_per_tile=500, global_count=400)
    assert "camera 0 (bad) lies 0 point spacings from a data point" in caplog.text
    assert stats["cameras"] == 12 and stats["outliers"] <= 3
    from o3drbf import reconstruct

    ref = reconstruct(points, cameras=[bad] + cams, point_camera=pc, surface_count=1000, resolution=32)
    radial = {name: np.abs(np.linalg.norm(np.asarray(m.vertices), axis=1) - 1.0).max() for name, m in (("tiled", mesh), ("untiled", ref.mesh))}
    print("largest radial error", radial, "outliers", stats["outliers"], ref.report.outliers_removed)
    assert mesh.is_watertight() and len(mesh.cluster_connected_triangles()[1]) == 1
    assert radial["tiled"] < 1.5 * radial["untiled"]
