"""Scans registered to each other (o3drbf.prep.registration and the register stage of reconstruct).

The truth is the misregistration itself: :func:`o3drbf.synthetic.scans.misregister`
moves each scan by a rigid motion that the test recovers exactly (Kabsch on
the same points before and after), so the best any registration can do,
the true motions undone up to their mean, is known; and the analytic
torus's signed distance measures the points.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import o3drbf
from o3drbf.cameras.model import Camera
from o3drbf.prep.registration import apply_transforms, refine_registration
from o3drbf.synthetic.scans import misregister, range_scans

R_TORUS, r_TORUS = 0.6, 0.25


def torus_sdf(p):
    return np.hypot(np.hypot(p[:, 0], p[:, 1]) - R_TORUS, p[:, 2]) - r_TORUS


@pytest.fixture(scope="module")
def torus():
    import open3d as o3d

    return o3d.geometry.TriangleMesh.create_torus(R_TORUS, r_TORUS, 60, 30)


def six_views(mesh, width=200, height=150, noise=0.0, seed=0):
    """Three scans from 20 degrees above and three from 20 below, interleaved (the study's 6 views)."""
    pa, oa, ca = range_scans(mesh, n_views=3, elevation=20, width=width, height=height, noise=noise, seed=seed)
    pb, ob, cb = range_scans(mesh, n_views=3, elevation=-20, azimuth=60, width=width, height=height, noise=noise, seed=seed + 1)
    return np.vstack([pa, pb]), np.concatenate([oa, ob + 3]), ca + cb


def toward(points, owner, cameras):
    out = np.zeros_like(points)
    for k, cam in enumerate(cameras):
        sel = owner == k
        out[sel] = cam.toward(points[sel])[0]
    return out


def kabsch(a, b):
    """The rigid motion (R, t) taking points a onto b exactly (b = a R^T + t)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def best_possible(true_points, moved_points, owner):
    """The true scans moved by the mean of the true misregistrations: what a perfect registration gives."""
    motions = [kabsch(true_points[owner == k], moved_points[owner == k]) for k in range(owner.max() + 1)]
    c = moved_points.mean(axis=0)
    mean_rot = Rotation.from_matrix(np.stack([R for R, _ in motions])).mean().as_matrix()
    mean_shift = np.mean([R @ c + t - c for R, t in motions], axis=0)
    return (true_points - c) @ mean_rot.T + c + mean_shift


@pytest.mark.parametrize("seed", [0, 1])
def test_recovers_a_known_misregistration(torus, seed):
    pts, owner, cams = six_views(torus, seed=seed)
    moved, moved_cams = misregister(pts, owner, cams, 0.01, seed=seed + 5)
    reg = refine_registration(moved, owner, len(cams), toward=toward(moved, owner, moved_cams), seed=seed)
    assert reg.applied and reg.scans == 6, reg.reason
    assert reg.after < 0.5 * reg.before
    registered = apply_transforms(moved, owner, reg.transforms)
    err = {name: float(np.abs(torus_sdf(p)).mean()) for name, p in
           (("registered", registered), ("misregistered", moved), ("best", best_possible(pts, moved, owner)))}
    # the best a registration can do (the pose errors' mean stays: nothing says where the object is)
    assert err["misregistered"] > 1.4 * err["best"], err
    assert err["registered"] < 1.1 * err["best"], err
    # every motion is a rigid one of the size of the error (0.01 translation plus a rotation of 0.01 at the rim)
    for T in reg.transforms:
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert 0.003 < reg.motion.max() < 0.05


def test_registered_scans_are_left_exactly_as_they_were(torus):
    pts, owner, cams = six_views(torus, noise=0.004, seed=3)
    reg = refine_registration(pts, owner, len(cams), toward=toward(pts, owner, cams))
    assert not reg.applied, reg.reason
    assert "left as they were" in reg.reason
    assert reg.after > 0.95 * reg.before  # noise, not a pose error: nothing to gain
    np.testing.assert_array_equal(reg.transforms, np.tile(np.eye(4), (6, 1, 1)))


def test_thin_walls_are_not_pulled_together():
    """A pipe's wall is 5 % of its diameter: its inner and outer sides face away from each other and must not be matched."""
    from o3drbf.synthetic.solids import solid_mesh

    pipe = solid_mesh("pipe", cells=96)
    pts, owner, cams = range_scans(pipe, n_views=3, elevation=20, width=160, height=120, seed=0)
    reg = refine_registration(pts, owner, len(cams), toward=toward(pts, owner, cams))
    assert not reg.applied, reg.reason
    assert reg.motion.max() < 0.005  # the wall is 0.05 thick


def test_cameras_move_with_their_scans():
    """A camera moved with its scan sees each moved point at the same pixel and depth."""
    rng = np.random.default_rng(0)
    cam = Camera.look_at((2.0, 0.5, 1.0), (0.0, 0.0, 0.0), width=320, height=240)
    pts = rng.uniform(-0.5, 0.5, size=(50, 3))
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.02, -0.05, 0.03]).as_matrix()
    T[:3, 3] = [0.01, -0.02, 0.015]
    moved_pts = pts @ T[:3, :3].T + T[:3, 3]
    moved_cam = cam.moved(T)
    uv, depth = cam.project(pts)[:2]
    uv2, depth2 = moved_cam.project(moved_pts)[:2]
    np.testing.assert_allclose(uv2, uv, atol=1e-9)
    np.testing.assert_allclose(depth2, depth, atol=1e-12)
    np.testing.assert_allclose(moved_cam.center, T[:3, :3] @ cam.center + T[:3, 3], atol=1e-12)
    with pytest.raises(ValueError, match="transform"):
        cam.moved(np.eye(3))


def test_bad_arguments_are_refused():
    pts = np.random.default_rng(1).normal(size=(500, 3))
    with pytest.raises(ValueError, match="point_camera"):
        refine_registration(pts, np.zeros(10, int))
    with pytest.raises(ValueError, match="toward"):
        refine_registration(pts, np.zeros(500, int), toward=np.ones((3, 3)))
    with pytest.raises(ValueError, match="min_gain"):
        refine_registration(pts, np.zeros(500, int), min_gain=2.0)
    one = refine_registration(pts, np.zeros(500, int))
    assert not one.applied and "fewer than two scans" in one.reason
    with pytest.raises(ValueError, match="register"):
        o3drbf.Options.create(register="icp").validate()


@pytest.fixture(scope="module")
def misregistered_torus_scan(torus):
    pts, owner, cams = six_views(torus, width=160, height=120, noise=0.003, seed=0)
    moved, moved_cams = misregister(pts, owner, cams, 0.01, seed=5)
    return moved, owner, moved_cams


def test_reconstruct_registers_misregistered_scans_by_default(torus, misregistered_torus_scan):
    from o3drbf.mesh.metrics import chamfer

    pts, owner, cams = misregistered_torus_scan
    default = o3drbf.reconstruct(pts, cameras=cams, point_camera=owner, resolution=96)
    off = o3drbf.reconstruct(pts, cameras=cams, point_camera=owner, resolution=96, register="none")
    reg = default.report.registration
    assert reg["applied"] and reg["scans"] == 6 and reg["after"] < reg["before"]
    assert off.report.registration is None
    assert [s.name for s in default.report.stages][:3] == ["read", "register", "outliers"]
    ch = {name: chamfer(r.mesh, torus, n_samples=20_000, seed=0)["l1"] for name, r in (("default", default), ("off", off))}
    assert ch["default"] < 0.85 * ch["off"], ch  # measured: 0.0036 against 0.0046
    assert default.mesh.is_watertight()


def test_reconstruct_leaves_registered_scans_alone(torus):
    pts, owner, cams = six_views(torus, width=120, height=90, noise=0.003, seed=2)
    default = o3drbf.reconstruct(pts, cameras=cams, point_camera=owner, resolution=64, surface_count=1500)
    off = o3drbf.reconstruct(pts, cameras=cams, point_camera=owner, resolution=64, surface_count=1500, register="none")
    assert not default.report.registration["applied"]
    np.testing.assert_array_equal(np.asarray(default.mesh.vertices), np.asarray(off.mesh.vertices))


def test_too_many_scans_are_left_to_a_registration_tool():
    from o3drbf.prep.registration import MAX_SCANS

    pts = np.random.default_rng(2).normal(size=(250 * (MAX_SCANS + 1), 3))
    owner = np.repeat(np.arange(MAX_SCANS + 1), 250)
    reg = refine_registration(pts, owner)
    assert not reg.applied and reg.rounds == 0 and f"more than {MAX_SCANS}" in reg.reason


def test_register_scans_turns_normals_with_their_scan(torus):
    pts, owner, cams = six_views(torus, width=120, height=90, seed=4)
    r = np.hypot(pts[:, 0], pts[:, 1])
    ring = np.stack([pts[:, 0] * R_TORUS / r, pts[:, 1] * R_TORUS / r, np.zeros(len(pts))], axis=1)
    normals = (pts - ring) / np.linalg.norm(pts - ring, axis=1, keepdims=True)  # the torus's true normals
    moved, moved_cams = misregister(pts, owner, cams, 0.01, seed=7)
    data = o3drbf.PointSet.create(moved, normals, cameras=moved_cams, point_camera=owner)
    out, reg = o3drbf.register_scans(data, o3drbf.Options().registration)
    assert reg.applied
    for k, T in enumerate(reg.transforms):
        sel = owner == k
        np.testing.assert_allclose(out.normals[sel], normals[sel] @ T[:3, :3].T, atol=1e-12)
        np.testing.assert_allclose(out.points[sel], moved[sel] @ T[:3, :3].T + T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(out.normals, axis=1), 1.0, atol=1e-9)
    assert out.cameras[0] is not moved_cams[0] and data.points is moved  # a new PointSet; the input untouched


def test_scan_normals_are_open3ds_knn_normals_turned_toward_the_sensor():
    """The scans' own normals (the least-squares plane of each point's nearest neighbours, computed without
    Open3D) are Open3D's ``estimate_normals`` with the same neighbours, each turned toward its sensor."""
    import open3d as o3d

    from o3drbf.prep.registration import NORMAL_NEIGHBOURS, _scan_normals

    rng = np.random.default_rng(3)
    from o3drbf.synthetic.shapes import Torus

    points, _ = Torus(0.7, 0.25).sample(3000, noise=0.002, seed=4)
    toward = rng.normal(size=points.shape)
    toward /= np.linalg.norm(toward, axis=1)[:, None]
    ours = _scan_normals(points, toward)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
    theirs = np.asarray(pcd.normals)
    theirs = theirs * np.where(np.einsum("ij,ij->i", theirs, toward) < 0, -1.0, 1.0)[:, None]
    assert (np.einsum("ij,ij->i", ours, toward) >= 0).all()
    np.testing.assert_allclose(np.einsum("ij,ij->i", ours, theirs), 1.0, atol=1e-9)
