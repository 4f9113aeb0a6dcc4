"""Denoised surface constraints (local quadric projection), misregistered scans and the study's solids."""

import numpy as np
import pytest

from o3drbf.prep.smoothing import neighbourhood_size, project_to_local_surface
from o3drbf.synthetic.shapes import Sphere, Torus


def test_projection_removes_most_of_the_noise_on_a_sphere():
    sigma = 0.02
    pts, _ = Sphere(1.0).sample(20000, noise=sigma, seed=1)
    targets = pts[::10]
    moved, offset, gain = project_to_local_surface(pts, targets, k=60)
    before = np.sqrt(np.mean((np.linalg.norm(targets, axis=1) - 1.0) ** 2))
    after = np.sqrt(np.mean((np.linalg.norm(moved, axis=1) - 1.0) ** 2))
    assert before == pytest.approx(sigma, rel=0.1)
    assert after < 0.3 * sigma
    # the predicted remaining noise is the measured one
    assert sigma * np.sqrt(np.mean(gain ** 2)) == pytest.approx(after, rel=0.25)
    # the move is along the normal by the reported offset
    assert np.allclose(np.linalg.norm(moved - targets, axis=1), np.abs(offset))


def test_projection_keeps_exact_samples_of_a_curved_surface():
    pts, _ = Torus(0.7, 0.25).sample(20000, seed=2)
    moved, offset, _ = project_to_local_surface(pts, pts[::7], k=32)
    r = np.hypot(np.hypot(moved[:, 0], moved[:, 1]) - 0.7, moved[:, 2])
    assert np.abs(r - 0.25).max() < 2e-4  # the quadric absorbs the curvature (a plane fit would move them ~1e-3)
    assert np.abs(offset).max() < 2e-4


def test_neighbourhood_size_rule():
    assert neighbourhood_size(33000, 5500) == 24
    assert neighbourhood_size(90000, 3000) == 90
    assert neighbourhood_size(10**6, 3000) == 96


def _scan(noise):
    from o3drbf.synthetic.scans import range_scans
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=0.7, tube_radius=0.3, radial_resolution=80, tubular_resolution=40)
    return mesh, range_scans(mesh, n_views=3, width=120, height=90, noise=noise, seed=0)


def test_reconstruct_denoises_noisy_scans_and_leaves_clean_ones():
    from o3drbf import reconstruct
    from o3drbf.mesh.metrics import chamfer

    mesh, (pts, owner, cams) = _scan(0.02)
    common = dict(cameras=cams, point_camera=owner, surface_count=1500, resolution=64, robust=False)
    off = reconstruct(pts, denoise=False, **common)
    on = reconstruct(pts, **common)
    assert off.report.denoised == 0 and on.report.denoised == on.report.surface_constraints
    assert on.report.constraint_noise < 0.5 * on.report.noise
    # noise along the rays, 0.02, is smaller across the surface where the rays graze it
    assert 0.4 * 0.02 < on.report.noise < 1.1 * 0.02
    assert chamfer(on.mesh, mesh, n_samples=20000)["l1"] < 0.8 * chamfer(off.mesh, mesh, n_samples=20000)["l1"]
    _, (clean, owner, cams) = _scan(0.0)
    rec = reconstruct(clean, cameras=cams, point_camera=owner, surface_count=1500, resolution=48, robust=False)
    assert rec.report.denoised == 0


def test_bad_denoise_value():
    from o3drbf.options import ConstraintOptions

    with pytest.raises(ValueError, match="denoise must be"):
        ConstraintOptions(denoise="sometimes").validate()


def test_misregistered_scans_move_with_their_cameras():
    from o3drbf.synthetic.scans import misregister, range_scans
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=30)
    pts, owner, cams = range_scans(mesh, n_views=3, width=60, height=45, seed=0)
    pts = np.vstack([pts, [[5.0, 5.0, 5.0]]])
    owner = np.append(owner, -1)
    error = 0.01
    moved, moved_cams = misregister(pts, owner, cams, error, seed=3)
    assert np.array_equal(moved[-1], pts[-1])  # no camera: not moved
    for k, (a, b) in enumerate(zip(cams, moved_cams)):
        sel = owner == k
        # what each camera saw is unchanged in its own frame: one rigid motion of scan and camera
        assert np.allclose(a.to_camera(pts[sel]), b.to_camera(moved[sel]), atol=1e-12)
        shift = np.linalg.norm(moved[sel] - pts[sel], axis=1)
        assert shift.max() <= 2 * error + 1e-12 and shift.min() > 0
        assert np.allclose(b.R @ b.R.T, np.eye(3))
    assert not np.allclose(moved[owner == 0].mean(axis=0) - pts[owner == 0].mean(axis=0), 0.0)


@pytest.mark.parametrize("name, genus", [("double-torus", 2), ("thin-plate", 0)])
def test_study_solids_have_their_topology(name, genus):
    from o3drbf.mesh.metrics import mesh_report
    from o3drbf.synthetic.solids import SOLIDS, solid_mesh

    mesh = solid_mesh(name, cells=90)
    rep = mesh_report(mesh, self_intersections=False)
    assert rep["components"] == 1 and rep["genus"] == SOLIDS[name].genus
    v = np.asarray(mesh.vertices)
    assert np.allclose(v.min(axis=0), SOLIDS[name].lo, atol=0.02) and np.allclose(v.max(axis=0), SOLIDS[name].hi, atol=0.02)
    mesh.compute_vertex_normals()
    i = np.argmax(v[:, 0])
    assert np.asarray(mesh.vertex_normals)[i, 0] > 0.5  # outward


def test_bracket_holes_go_through():
    from o3drbf.synthetic.solids import solid

    sdf = solid("bracket").signed_distance
    assert sdf(np.array([0.45, 0.0, -0.4])) < 0  # the base plate
    assert sdf(np.array([0.2, 0.0, -0.4])) > 0  # its hole
    assert sdf(np.array([-0.5, 0.0, 0.2])) > 0  # the upright's hole
    assert sdf(np.array([-0.5, 0.0, 0.5])) < 0
