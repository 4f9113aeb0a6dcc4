"""Synthetic range scans and voxel shells (o3drbf.synthetic.scans)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3drbf.cameras.model import load_cameras
from o3drbf.prep.outliers import voxel_components
from o3drbf.synthetic.scans import range_scans, voxel_shell, write_scan_json
from o3drbf.synthetic.shapes import Torus


def sphere_mesh():
    return o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=40)


def distance_to(mesh, points):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def test_points_lie_on_the_mesh():
    mesh = sphere_mesh()
    points, owner, cams = range_scans(mesh, seed=1)
    assert len(points) > 5000 and np.bincount(owner).min() > 1000
    assert distance_to(mesh, points).max() < 1e-5  # float32 ray casting
    noisy, _, _ = range_scans(mesh, noise=0.01, seed=1)
    d = distance_to(mesh, noisy)
    # Noise is along the ray, so the distance to the surface is at most |noise|:
    # RMS between 0.5 and 1 sigma (measured 0.0085).
    assert 0.005 < np.sqrt((d**2).mean()) < 0.0105
    assert d.max() < 0.06


def test_three_views_120_degrees_apart():
    points, owner, cams = range_scans(sphere_mesh(), n_views=3, elevation=20.0)
    assert len(cams) == 3
    centers = np.array([c.center for c in cams])
    az = np.degrees(np.arctan2(centers[:, 1], centers[:, 0]))
    np.testing.assert_allclose(np.sort((az - az[0]) % 360), [0, 120, 240], atol=1e-9)
    dist = np.linalg.norm(centers, axis=1)
    np.testing.assert_allclose(dist, dist[0])
    np.testing.assert_allclose(np.degrees(np.arcsin(centers[:, 2] / dist)), 20.0)
    for cam, c in zip(cams, centers):
        np.testing.assert_allclose(cam.direction, -c / np.linalg.norm(c), atol=1e-12)  # looks at the centre
        # each view only sees its own side of the sphere
        mine = points[owner == cams.index(cam)]
        assert ((mine @ c) > 0).all()


def test_outlier_fraction_is_honoured():
    mesh = sphere_mesh()
    clean, _, _ = range_scans(mesh, seed=2)
    points, owner, cams = range_scans(mesh, outliers=0.1, seed=2)
    n_out = len(points) - len(clean)
    assert abs(n_out / len(points) - 0.1) < 1 / len(points)
    np.testing.assert_array_equal(points[: len(clean)], clean)  # outliers are the last rows
    out = points[len(clean) :]
    own = owner[len(clean) :]
    assert (distance_to(mesh, out) > 0.01).mean() > 0.9
    assert set(np.unique(own)) <= {0, 1, 2}
    # each outlier is a spurious return in its camera's free space: the ray
    # from that camera through it meets the mesh only beyond it
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    centres = np.array([cams[k].center for k in own])
    d = out - centres
    dist = np.linalg.norm(d, axis=1)
    rays = np.hstack([centres, d / dist[:, None]]).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    assert (t_hit > dist + 1e-4).all()
    with pytest.raises(ValueError, match="below 1"):
        range_scans(mesh, outliers=1.0)


def test_scan_json_round_trip(tmp_path):
    points, owner, cams = range_scans(sphere_mesh(), width=40, height=30, seed=3)
    path = write_scan_json(tmp_path / "scan.json", points, cams, owner)
    back = load_cameras(path)
    np.testing.assert_array_equal(back.points, points)
    np.testing.assert_array_equal(back.point_camera, owner)
    for a, b in zip(cams, back):
        np.testing.assert_allclose(a.project(points)[0], b.project(points)[0], atol=1e-9, equal_nan=True)


def test_voxel_shell_imitates_carving():
    torus = Torus(0.7, 0.25)
    shell = voxel_shell(torus, resolution=64, thickness=1.5, jitter=1.5, stray_fraction=0.02, seed=4)
    h = shell.voxel_size
    centers = shell.centers()
    sd = torus.signed_distance(centers)
    is_stray = shell.stray[tuple(shell.indices().T)]
    body = sd[~is_stray]
    assert body.min() >= -2.0 * h - 1e-9  # thickness inward, plus half a voxel
    assert np.percentile(body, 99) > 1.5 * h  # jagged outward
    n_shell = (~is_stray).sum()
    assert abs(is_stray.sum() - 0.02 * n_shell) <= 1
    assert (sd[is_stray] > 2 * h).all()
    # The shell is one 26-connected piece: keeping the largest component drops exactly the strays.
    kept, report = voxel_components(shell.indices())
    np.testing.assert_array_equal(kept, np.flatnonzero(~is_stray))
    assert len(shell.cameras) == 16
    assert all(c.in_image(centers).all() for c in shell.cameras)
