"""Exact point-to-mesh distances (o3drbf.mesh.nearest) against analytic distances and Open3D's."""

import numpy as np
import open3d as o3d
import pytest

from o3drbf.mesh.nearest import SEARCH_SHELLS, point_mesh_distance


def _cube(subdivisions: int = 0):
    """The surface of [-1, 1]^3 as triangles (each face split into 2 * 4^subdivisions)."""
    mesh = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 2.0).translate((-1.0, -1.0, -1.0))
    if subdivisions:
        mesh = mesh.subdivide_midpoint(subdivisions)
    return np.asarray(mesh.vertices), np.asarray(mesh.triangles)


def _box_distance(p):
    """Distance from points to the surface of [-1, 1]^3, analytically."""
    q = np.abs(p) - 1.0
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = -np.max(q, axis=1)
    return np.where((q > 0).any(axis=1), outside, inside)


def _open3d_distance(points, verts, tris):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(tris.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(float)


@pytest.mark.parametrize("subdivisions", [0, 3])
def test_distances_to_a_cube_are_the_analytic_ones(subdivisions):
    """Inside, outside, near the edges and corners, on the faces: the distance to the cube's surface,
    to rounding (the 12 big triangles of the plain cube go to the every-point list, the subdivided ones to the grid)."""
    verts, tris = _cube(subdivisions)
    rng = np.random.default_rng(0)
    p = np.vstack([rng.uniform(-1.3, 1.3, (3000, 3)), rng.uniform(-0.99, 0.99, (200, 3)) * [1, 1, 0] + [0, 0, 1]])
    assert np.abs(point_mesh_distance(p, verts, tris) - _box_distance(p)).max() < 1e-12


def test_points_far_from_the_mesh_are_answered_too(monkeypatch):
    """Beyond the searched shells: against every triangle (exact), or for many points and triangles by
    Open3D's single-precision query."""
    import o3drbf.mesh.nearest as nearest

    verts, tris = _cube(3)
    p = np.array([[100.0, 0.0, 0.0], [0.0, -7.0, 3.0], [5.0, 5.0, 5.0], [0.5, 0.2, 1.01]])
    assert np.abs(point_mesh_distance(p, verts, tris) - _box_distance(p)).max() < 1e-12
    monkeypatch.setattr(nearest, "_BRUTE_PAIRS", 0)
    assert np.allclose(point_mesh_distance(p, verts, tris), _box_distance(p), rtol=1e-6)


def test_distances_to_a_fine_sphere_match_open3d():
    """Thousands of small triangles, points near the surface and some cells away: Open3D's distances
    (float32) to its precision; the exact search stops early only where nothing nearer can exist."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=80)
    verts, tris = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = np.r_[1 + rng.normal(0, 0.01, 15000), rng.uniform(0.7, 1.3, 5000)]
    p = d * r[:, None]
    got = point_mesh_distance(p, verts, tris)
    assert np.abs(got - _open3d_distance(p, verts, tris)).max() < 1e-6
    assert np.abs(got - np.abs(r - 1)).max() < 2e-3  # and the sphere's, to its tessellation


def test_a_large_triangle_among_small_ones_and_a_degenerate_one():
    """A triangle covering many cells is tested against every point; a zero-area (collinear) triangle
    is as near as its longest side."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(0.2, resolution=40)
    verts, tris = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    n = len(verts)
    verts = np.vstack([verts, [[-5, -5, -1.0], [5, -5, -1.0], [0, 5, -1.0], [2, 2, 2.0], [3, 3, 3.0], [4, 4, 4.0]]])
    tris = np.vstack([tris, [[n, n + 1, n + 2], [n + 3, n + 4, n + 5]]])
    rng = np.random.default_rng(2)
    p = rng.uniform(-1.5, 1.5, (3000, 3))
    got = point_mesh_distance(p, verts, tris)
    assert np.abs(got - _open3d_distance(p, verts, tris)).max() < 1e-6
    seg = np.array([[2.0, 2.0, 2.1]])  # beside the segment from (2, 2, 2) to (4, 4, 4), a few cells away
    along = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0)
    perp = seg[0] - [2, 2, 2] - along * (along @ (seg[0] - [2, 2, 2]))
    assert point_mesh_distance(seg, verts, tris)[0] == pytest.approx(np.linalg.norm(perp), rel=1e-12)


@pytest.mark.parametrize("corners", [[[0, 0, 0], [0, 0, 0], [1, 0, 0]], [[0, 0, 0], [1, 0, 0], [1, 0, 0]],
                                     [[1, 0, 0], [0, 0, 0], [0.5, 0, 0]], [[0.5, 0, 0], [0.5, 0, 0], [0.5, 0, 0]]])
def test_a_triangle_of_no_area_is_as_near_as_its_sides(corners):
    """Collinear or coincident corners: the distance to the segment they span (or the point)."""
    c = np.asarray(corners, dtype=float)
    lo, hi = c[:, 0].min(), c[:, 0].max()
    rng = np.random.default_rng(3)
    p = rng.uniform(-1, 2, (500, 3))
    along = np.clip(p[:, 0], lo, hi)
    want = np.linalg.norm(p - np.column_stack([along, np.zeros(500), np.zeros(500)]), axis=1)
    assert np.abs(point_mesh_distance(p, c, [[0, 1, 2]]) - want).max() < 1e-12


def test_bad_meshes_are_refused_with_the_fix():
    with pytest.raises(ValueError, match="no triangles"):
        point_mesh_distance(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match=r"indices must lie in \[0, 3\)"):
        point_mesh_distance(np.zeros((2, 3)), np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError, match="NaN or infinite vertex"):
        point_mesh_distance(np.zeros((2, 3)), [[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]])
    assert point_mesh_distance(np.zeros((0, 3)), *_cube()).shape == (0,)
    assert SEARCH_SHELLS >= 1
