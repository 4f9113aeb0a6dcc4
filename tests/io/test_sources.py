"""Depth images and voxel grids as surface data, against analytic truth."""

import numpy as np
import open3d as o3d
import pytest

import o3drbf
from o3drbf.cameras.model import Camera
from o3drbf.synthetic.shapes import Sphere, Torus
from o3drbf.io.sources import points_from_depth, points_from_voxels, read_voxel_grid


def sphere_depth(camera, radius=1.0):
    """Exact depth image of a sphere at the origin by ray casting (Open3D)."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere(radius, 200)))
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    K = camera.K
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1).reshape(-1, 3)
    dirs_world = d @ camera.R  # R^T d
    rays = np.hstack([np.broadcast_to(camera.center, dirs_world.shape), dirs_world]).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.where(np.isfinite(t), t, 0.0).reshape(camera.height, camera.width)  # t along d (z = 1) is the depth


def test_depth_back_projection_lands_on_the_sphere():
    cam = Camera.look_at(eye=(0, -4, 1), target=(0, 0, 0), fov=40, width=120, height=90)
    depth = sphere_depth(cam)
    pts, pc = points_from_depth(depth, cam, camera_index=3)
    assert len(pts) > 1000 and (pc == 3).all()
    assert np.abs(np.linalg.norm(pts, axis=1) - 1.0).max() < 2e-3  # tessellation of the ray-cast sphere
    # depth_scale: millimetres
    pts_mm, _ = points_from_depth(depth * 1000, cam, depth_scale=1000)
    assert np.allclose(pts_mm, pts, atol=1e-6)  # depth is float32 from the ray caster


def test_depth_errors():
    cam = Camera.look_at(eye=(0, -4, 1), target=(0, 0, 0), width=40, height=30)
    with pytest.raises(ValueError, match="2-D image"):
        points_from_depth(np.ones(5), cam)
    with pytest.raises(ValueError, match="30x40|40x30"):
        points_from_depth(np.ones((40, 30)), cam)
    with pytest.raises(ValueError, match="no valid pixel"):
        points_from_depth(np.zeros((30, 40)), cam)
    with pytest.raises(ValueError, match="pinhole"):
        points_from_depth(np.ones((30, 40)), Camera.from_center((0, 0, 5)))


def shell(shape, n=40, half=1.2):
    h = 2 * half / (n - 1)
    g = np.stack(np.meshgrid(*[np.linspace(-half, half, n)] * 3, indexing="ij"), -1)
    occ = np.abs(shape.signed_distance(g)) < 0.75 * h
    return occ, np.full(3, -half), h


def test_voxel_shell_to_points_and_reconstruction():
    torus = Torus(0.6, 0.25)
    occ, origin, h = shell(torus)
    occ[2, 2, 2] = True  # a stray voxel
    pts, cols, report = points_from_voxels(occ, origin, h)
    assert report.removed == 1
    assert np.abs(torus.signed_distance(pts)).max() < 0.75 * h + 1e-12
    r = o3drbf.reconstruct(pts, surface_count=1500, resolution=48, lambda_surface=0.01)
    assert r.mesh.euler_poincare_characteristic() == 0
    assert np.abs(torus.signed_distance(np.asarray(r.mesh.vertices))).mean() < h


def test_voxel_indices_colours_and_open3d_files(tmp_path):
    occ, origin, h = shell(Sphere(1.0), n=24)
    idx = np.argwhere(occ)
    colours = np.tile([0.2, 0.4, 0.6], (len(idx), 1))
    pts, cols, _ = points_from_voxels(idx, origin, h, colors=colours, keep_components=None)
    assert np.allclose(cols, colours) and len(pts) == len(idx)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.colors = o3d.utility.Vector3dVector(cols)
    grid = o3d.geometry.VoxelGrid.create_from_point_cloud_within_bounds(pcd, h, origin - h / 2, origin - h / 2 + h * np.array(occ.shape))
    o3d.io.write_voxel_grid(str(tmp_path / "g.ply"), grid)
    gi, go, gs, gc = read_voxel_grid(tmp_path / "g.ply")
    back, _, _ = points_from_voxels(gi, go, gs, keep_components=None)
    assert gs == pytest.approx(h) and len(back) == len(pts)
    assert np.abs(np.sort(back, axis=0) - np.sort(pts, axis=0)).max() < 1e-6


def test_voxel_errors(tmp_path):
    with pytest.raises(ValueError, match="no occupied voxel"):
        points_from_voxels(np.zeros((4, 4, 4), bool))
    with pytest.raises(ValueError, match="boolean grid or"):
        points_from_voxels(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="voxel_size must be"):
        points_from_voxels(np.ones((2, 2, 2), bool), voxel_size=0)
    with pytest.raises(FileNotFoundError, match="voxel grid file not found"):
        read_voxel_grid(tmp_path / "none.ply")


def _ply(path, records, fmt="binary_little_endian"):
    """A PLY of one vertex element from a structured array (its field names and types as the properties)."""
    kinds = {"f8": "double", "f4": "float", "u1": "uchar", "i4": "int"}
    lines = ["ply", f"format {fmt} 1.0", f"element vertex {len(records)}"]
    lines += [f"property {kinds[records.dtype[k].str[1:]]} {k}" for k in records.dtype.names]
    with open(path, "wb") as fh:
        fh.write(("\n".join([*lines, "end_header"]) + "\n").encode())
        fh.write(records.tobytes())
    return path


@pytest.mark.parametrize("layout", ["xyz double", "xyz normals colours", "float32 big-endian", "extra property", "ascii"])
def test_point_ply_read_without_open3d_as_open3d_reads_it(tmp_path, layout):
    """Plain binary point PLYs are read without Open3D, to the same arrays as Open3D's reader gives; others
    (an unknown property, ASCII) go to Open3D's reader."""
    import open3d as o3d

    from o3drbf.io.files import read_points
    from o3drbf.io.ply import read_plain_ply

    rng = np.random.default_rng(1)
    n = 500
    fields = {"xyz double": [("x", "<f8"), ("y", "<f8"), ("z", "<f8")],
              "xyz normals colours": [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f8"), ("ny", "<f8"), ("nz", "<f8"),
                                      ("red", "u1"), ("green", "u1"), ("blue", "u1")],
              "float32 big-endian": [("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("nx", ">f4"), ("ny", ">f4"), ("nz", ">f4")],
              "extra property": [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<f4")],
              "ascii": [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]}[layout]
    records = np.zeros(n, dtype=fields)
    for name in records.dtype.names:
        records[name] = rng.integers(0, 256, n) if name in ("red", "green", "blue") else rng.normal(size=n)
    if layout == "ascii":
        path = tmp_path / "cloud.ply"
        path.write_text("ply\nformat ascii 1.0\nelement vertex 500\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
                        + "\n".join(" ".join(repr(float(v)) for v in row) for row in records.tolist()) + "\n")
    else:
        path = _ply(tmp_path / "cloud.ply", records, "binary_big_endian" if layout.endswith("big-endian") else "binary_little_endian")
    assert (read_plain_ply(path) is None) == (layout in ("extra property", "ascii"))
    points, normals, colors = read_points(path)
    pcd = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(points, np.asarray(pcd.points))
    assert (normals is None) == (not pcd.has_normals()) and (colors is None) == (not pcd.has_colors())
    if normals is not None:
        np.testing.assert_array_equal(normals, np.asarray(pcd.normals))
    if colors is not None:
        np.testing.assert_array_equal(colors, np.asarray(pcd.colors))
