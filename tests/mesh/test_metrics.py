"""Tests for o3drbf.mesh.metrics: every number against an analytic truth."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest

from o3drbf.mesh import metrics
from o3drbf.mesh.metrics import (
    average_curvature,
    chamfer,
    f_score,
    fitness_error,
    mean_curvature,
    mesh_report,
    normal_consistency,
)

N_SAMPLES = 5_000  # enough for exact-truth checks, keeps the file fast


# --------------------------------------------------------------------------
# helpers


def sphere(radius: float = 1.0, resolution: int = 60) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)


def mesh_from(verts, tris) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(verts, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(tris, dtype=np.int32)),
    )


def grid(n: int = 11, size: float = 2.0, z: float = 0.0) -> o3d.geometry.TriangleMesh:
    """A flat ``size x size`` square at height ``z``, ``n x n`` vertices."""
    x = np.linspace(0.0, size, n)
    xx, yy = np.meshgrid(x, x, indexing="ij")
    verts = np.stack([xx.ravel(), yy.ravel(), np.full(n * n, z)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return mesh_from(verts, tris)


def flipped(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    return mesh_from(np.asarray(mesh.vertices), np.asarray(mesh.triangles)[:, ::-1])


def face_plane_distances(mesh) -> np.ndarray:
    """Distance from the origin to the plane of each (non-degenerate) face."""
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    return np.abs(np.einsum("fd,fd->f", n[ok] / norm[ok, None], v[f[ok, 0]]))


# --------------------------------------------------------------------------
# curvature


@pytest.mark.parametrize("radius", [0.5, 3.0])
def test_sphere_average_curvature_is_inverse_radius(radius):
    # Measured: relative error 7.6e-5 at resolution 60, for every radius.
    assert average_curvature(sphere(radius)) == pytest.approx(1.0 / radius, rel=5e-3)


def test_sphere_curvature_is_uniform_per_vertex():
    # Measured: every vertex within 3.1e-4 of 1/R (poles included).
    h = mean_curvature(sphere(2.0))
    assert h.shape == (len(sphere(2.0).vertices),)
    assert np.all(np.isfinite(h))
    np.testing.assert_allclose(h, 0.5, rtol=2e-3)


def test_torus_curvature_matches_analytic_mean_curvature():
    # H = (R + 2 r cos v) / (2 r (R + r cos v)); cos v from each vertex position.
    R, r = 1.0, 0.3
    tor = o3d.geometry.TriangleMesh.create_torus(R, r, 60, 40)
    v = np.asarray(tor.vertices)
    cos_v = (np.hypot(v[:, 0], v[:, 1]) - R) / r
    truth = (R + 2 * r * cos_v) / (2 * r * (R + r * cos_v))
    # Measured: worst vertex 0.31 % off, average 0.03 %.
    np.testing.assert_allclose(mean_curvature(tor), truth, rtol=1e-2)
    assert average_curvature(tor) == pytest.approx(truth.mean(), rel=2e-3)


def test_flat_grid_has_zero_curvature_inside_and_nan_on_boundary():
    n = 11
    h = mean_curvature(grid(n))
    boundary = np.zeros((n, n), dtype=bool)
    boundary[[0, -1], :] = boundary[:, [0, -1]] = True
    assert np.all(np.isnan(h[boundary.ravel()]))
    np.testing.assert_allclose(h[~boundary.ravel()], 0.0, atol=1e-12)
    assert average_curvature(grid(n)) == pytest.approx(0.0, abs=1e-12)


def marching_cubes_sphere(n: int = 64) -> o3d.geometry.TriangleMesh:
    """Unit sphere from marching cubes on its distance field (slivers, obtuse triangles)."""
    from skimage.measure import marching_cubes

    x = np.linspace(-1.5, 1.5, n)
    xx, yy, zz = np.meshgrid(x, x, x, indexing="ij")
    verts, faces, _, _ = marching_cubes(np.sqrt(xx**2 + yy**2 + zz**2) - 1.0, 0.0, spacing=(x[1] - x[0],) * 3)
    return mesh_from(verts - 1.5, faces)


def test_marching_cubes_sphere_average_curvature():
    # The realistic input: cotangent curvature is noisy per vertex on
    # marching-cubes meshes (median 7 % off) and, being a magnitude, its
    # average is biased up.  Measured 1.031 with the mixed area; a pure
    # Voronoi area gives 1.31, a barycentric area 1.054.
    mesh = marching_cubes_sphere()
    h = mean_curvature(mesh)
    assert np.all(np.isfinite(h))
    assert average_curvature(mesh) == pytest.approx(1.0, rel=0.045)


@pytest.mark.parametrize("make", [sphere, marching_cubes_sphere], ids=["uv-sphere", "marching-cubes"])
def test_laplacian_and_mixed_area_invariants(make):
    mesh = make()
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    lap, area = metrics._cotangent_laplacian(v, f)
    assert abs(lap - lap.T).max() < 1e-12  # symmetric
    np.testing.assert_allclose(lap @ np.ones(len(v)), 0.0, atol=1e-9)  # constants in the kernel
    # Mixed areas are positive and partition the surface area.
    assert np.all(area > 0)
    assert area.sum() == pytest.approx(mesh_report(mesh)["area"], rel=1e-12)


def test_open_sphere_drops_only_the_hole_vertices():
    mesh = sphere(1.0)
    hole = np.asarray(mesh.triangles)[0].copy()  # a view would change below
    mesh.remove_triangles_by_index([0])
    h = mean_curvature(mesh)
    assert set(np.flatnonzero(np.isnan(h))) == set(hole.tolist())
    assert average_curvature(mesh) == pytest.approx(1.0, rel=5e-3)


# --------------------------------------------------------------------------
# fitness error


def test_fitness_of_mesh_vertices_is_zero():
    mesh = sphere(1.0)
    err = fitness_error(np.asarray(mesh.vertices), mesh)
    assert set(err) == {"mean", "rms", "max"}
    assert err["max"] < 1e-6


@pytest.mark.parametrize("offset", [0.01, 0.5])
def test_fitness_of_radially_offset_vertices_is_the_offset(offset):
    # Along the radius through a vertex of an inscribed convex polyhedron the
    # closest surface point is that vertex, so the distance is exactly |offset|.
    R = 1.5
    mesh = sphere(R)
    pts = np.asarray(mesh.vertices) * (R + offset) / R
    err = fitness_error(pts, mesh)
    for key in ("mean", "rms", "max"):
        assert err[key] == pytest.approx(abs(offset), abs=1e-6)


def test_fitness_mixed_distances():
    # Points 0, 1 and 3 above the plane z = 0: mean 4/3, rms sqrt(10/3), max 3.
    pts = np.array([[0.5, 0.5, 0.0], [1.0, 1.0, 1.0], [1.5, 0.5, 3.0]])
    err = fitness_error(pts, grid())
    assert err["mean"] == pytest.approx(4 / 3, rel=1e-6)
    assert err["rms"] == pytest.approx(math.sqrt(10 / 3), rel=1e-6)
    assert err["max"] == pytest.approx(3.0, rel=1e-6)


def test_fitness_keeps_precision_far_from_the_origin():
    # float32 spacing at 3e5 is ~3e-2; centring on the mesh keeps ~1e-7.
    centre = np.array([1e5, -2e5, 3e5])
    mesh = sphere(1.0).translate(centre)
    pts = centre + (np.asarray(mesh.vertices) - centre) * 1.01
    err = fitness_error(pts, mesh)
    assert err["mean"] == pytest.approx(0.01, abs=1e-6)
    assert err["max"] == pytest.approx(0.01, abs=1e-6)


def test_fitness_accepts_a_point_cloud():
    mesh = sphere(1.0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * 1.1))
    assert fitness_error(pcd, mesh)["mean"] == pytest.approx(0.1, abs=1e-6)


# --------------------------------------------------------------------------
# chamfer / f-score


def test_chamfer_of_a_mesh_with_itself_is_zero():
    mesh = sphere(1.0)
    c = chamfer(mesh, mesh, n_samples=N_SAMPLES)
    assert set(c) == {"l1", "l2", "a_to_b_mean", "b_to_a_mean", "hausdorff"}
    assert c["hausdorff"] < 1e-6


def test_chamfer_of_parallel_planes_is_their_gap():
    d = 0.07
    c = chamfer(grid(z=0.0), grid(z=d), n_samples=N_SAMPLES)
    for key in c:
        assert c[key] == pytest.approx(d, rel=1e-5), key


def test_chamfer_of_point_grids_uses_nearest_points():
    d = 0.03
    g = np.asarray(grid(z=0.0).vertices)
    c = chamfer(g, g + [0.0, 0.0, d])
    for key in c:
        assert c[key] == pytest.approx(d, rel=1e-12), key


def test_chamfer_mixes_points_and_meshes():
    d = 0.2
    pts = np.asarray(grid(n=5, z=d).vertices)
    c = chamfer(pts, grid(z=0.0), n_samples=N_SAMPLES)
    assert c["a_to_b_mean"] == pytest.approx(d, rel=1e-5)  # points to mesh: exact
    # Mesh samples to a 5x5 point grid: at least d, at most the distance
    # to the farthest point of a grid cell (half-diagonal 0.5 / sqrt(2)).
    assert d < c["b_to_a_mean"] < math.hypot(d, 0.5 / math.sqrt(2))


def test_chamfer_definitions_of_l1_l2_and_hausdorff():
    # a -> b distances [1]; b -> a distances [1, 3].
    a = [[0.0, 0.0, 0.0]]
    b = [[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]
    c = chamfer(a, b)
    assert c["a_to_b_mean"] == 1.0
    assert c["b_to_a_mean"] == 2.0
    assert c["l1"] == 1.5
    assert c["l2"] == pytest.approx((1.0 + math.sqrt(5.0)) / 2.0)
    assert c["hausdorff"] == 3.0


def test_chamfer_of_concentric_spheres_is_the_radius_gap():
    # Homothetic inscribed polyhedra: every directed distance lies in
    # [d * h_min / R, d] with h_min the smallest face-plane distance.
    R, d = 1.0, 0.05
    a, b = sphere(R), sphere(R + d)
    low = d * face_plane_distances(a).min() / R
    c = chamfer(a, b, n_samples=N_SAMPLES)
    for key in c:
        assert low - 1e-6 <= c[key] <= d + 1e-6, key


def test_chamfer_sampling_is_seeded():
    a, b = sphere(1.0, 20), sphere(1.2, 7)
    first = chamfer(a, b, n_samples=2000, seed=3)
    assert chamfer(a, b, n_samples=2000, seed=3) == first
    assert chamfer(a, b, n_samples=2000, seed=4) != first


@pytest.mark.parametrize("threshold, expected", [(0.15, 1.0), (0.05, 0.0)])
def test_f_score_of_parallel_planes(threshold, expected):
    s = f_score(grid(z=0.0), grid(z=0.1), threshold, n_samples=N_SAMPLES)
    assert s == {"precision": expected, "recall": expected, "f": expected}


def test_f_score_precision_and_recall_are_directed():
    a = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]  # one of two points is far from b
    b = [[0.0, 0.0, 0.0]]
    s = f_score(a, b, threshold=1.0)
    assert s["precision"] == 0.5
    assert s["recall"] == 1.0
    assert s["f"] == pytest.approx(2 / 3)


# --------------------------------------------------------------------------
# normal consistency


def test_normal_consistency_of_a_mesh_with_itself_is_one():
    mesh = sphere(1.0)
    assert normal_consistency(mesh, mesh, n_samples=N_SAMPLES) == pytest.approx(1.0, abs=1e-6)


def test_normal_consistency_is_unsigned():
    # Flipping every normal (reversed winding) does not change it.
    mesh = sphere(1.0)
    assert normal_consistency(mesh, flipped(mesh), n_samples=N_SAMPLES) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("angle_deg", [30.0, 75.0])
def test_normal_consistency_of_tilted_planes_is_cosine(angle_deg):
    tilted = grid(z=0.0)
    rot = tilted.get_rotation_matrix_from_xyz((math.radians(angle_deg), 0.0, 0.0))
    tilted.rotate(rot, center=(1.0, 1.0, 0.0))
    nc = normal_consistency(grid(z=0.0), tilted, n_samples=N_SAMPLES)
    assert nc == pytest.approx(math.cos(math.radians(angle_deg)), abs=1e-9)


# --------------------------------------------------------------------------
# mesh report


def test_report_of_a_sphere():
    R = 2.0
    rep = mesh_report(sphere(R))
    assert rep["watertight"] and rep["closed"] and rep["edge_manifold"] and rep["vertex_manifold"]
    assert (rep["euler_characteristic"], rep["genus"], rep["components"]) == (2, 0, 1)
    assert rep["vertices"] == len(sphere(R).vertices) and rep["triangles"] == len(sphere(R).triangles)
    assert rep["self_intersections"] == 0
    # Inscribed polyhedron: a little under the sphere.  Measured -0.07 % / -0.14 %.
    assert rep["area"] == pytest.approx(4 * math.pi * R**2, rel=3e-3)
    assert rep["volume"] == pytest.approx(4 / 3 * math.pi * R**3, rel=3e-3)


def test_report_of_a_box_is_exact():
    rep = mesh_report(o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0))
    assert rep["area"] == pytest.approx(22.0, rel=1e-12)
    assert rep["volume"] == pytest.approx(6.0, rel=1e-12)
    assert (rep["euler_characteristic"], rep["genus"]) == (2, 0)


def test_volume_does_not_depend_on_orientation():
    box = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    assert mesh_report(flipped(box))["volume"] == pytest.approx(6.0, rel=1e-12)


def test_report_of_a_torus():
    rep = mesh_report(o3d.geometry.TriangleMesh.create_torus(1.0, 0.4, 40, 24))
    assert rep["watertight"]
    assert (rep["euler_characteristic"], rep["genus"], rep["components"]) == (0, 1, 1)
    # Solid torus volume 2 pi^2 R r^2 (inscribed tessellation a little under).
    assert rep["volume"] == pytest.approx(2 * math.pi**2 * 1.0 * 0.4**2, rel=2e-2)


def test_report_of_a_mesh_with_one_triangle_turned():
    """A closed mesh whose triangles are not all turned alike has no volume (it is not consistently
    oriented) but still a genus (Open3D finds it orientable); every triangle turned, it has both."""
    mesh = sphere(1.0)
    tris = np.asarray(mesh.triangles).copy()
    tris[5] = tris[5][::-1]
    turned = o3d.geometry.TriangleMesh(mesh.vertices, o3d.utility.Vector3iVector(tris))
    rep = mesh_report(turned)
    assert rep["watertight"] and rep["volume"] is None and rep["genus"] == 0 and turned.is_orientable()
    rep = mesh_report(flipped(mesh))
    assert rep["volume"] == pytest.approx(mesh_report(mesh)["volume"], rel=1e-12) and rep["genus"] == 0


def test_report_sums_genus_over_components():
    torus = o3d.geometry.TriangleMesh.create_torus(1.0, 0.3, 30, 20)
    two_tori_and_a_sphere = torus + sphere(0.3, 10).translate((4, 0, 0)) + torus.translate((0, 4, 0))
    rep = mesh_report(two_tori_and_a_sphere)
    assert (rep["components"], rep["euler_characteristic"], rep["genus"]) == (3, 2, 2)


def test_report_flags_a_missing_triangle():
    mesh = sphere(1.0)
    mesh.remove_triangles_by_index([0])
    rep = mesh_report(mesh)
    assert not rep["watertight"] and not rep["closed"]
    assert rep["edge_manifold"]
    assert rep["euler_characteristic"] == 1  # one face fewer
    assert rep["genus"] is None and rep["volume"] is None


def test_report_counts_self_intersections_by_default():
    box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    overlapping = box + o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate((0.5, 0.5, 0.5))
    disjoint = box + o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0).translate((3.0, 0.0, 0.0))
    rep = mesh_report(overlapping, self_intersections=False)
    assert rep["watertight"] and rep["self_intersections"] is None  # topologically closed ...
    rep = mesh_report(overlapping)
    assert rep["self_intersections"] == len(overlapping.get_self_intersecting_triangles()) > 0
    assert not rep["watertight"] and not overlapping.is_watertight()  # ... but not watertight
    rep = mesh_report(disjoint)
    assert rep["self_intersections"] == 0 and rep["watertight"] and disjoint.is_watertight()
    assert rep["components"] == 2 and rep["volume"] == pytest.approx(2.0)


# --------------------------------------------------------------------------
# error paths


def empty_mesh():
    return o3d.geometry.TriangleMesh()


def vertices_only():
    return mesh_from(np.eye(3), np.zeros((0, 3)))


def nan_mesh():
    mesh = sphere(1.0, 10)
    v = np.asarray(mesh.vertices)
    v[5] = np.nan
    mesh.vertices = o3d.utility.Vector3dVector(v)
    return mesh


def bad_index_mesh():
    return mesh_from(np.eye(3), [[0, 1, 3]])


MESH_FUNCTIONS = {
    "mean_curvature": mean_curvature,
    "average_curvature": average_curvature,
    "mesh_report": mesh_report,
    "fitness_error": lambda m: fitness_error(np.zeros((1, 3)), m),
    "chamfer": lambda m: chamfer(m, sphere(1.0, 5), n_samples=10),
    "f_score": lambda m: f_score(sphere(1.0, 5), m, 0.1, n_samples=10),
    "normal_consistency": lambda m: normal_consistency(m, sphere(1.0, 5), n_samples=10),
}

BAD_MESHES = {
    "empty": (empty_mesh, r"empty \(no vertices\)"),
    "no triangles": (vertices_only, "3 vertices but no triangles"),
    "nan": (nan_mesh, "NaN or infinite coordinates"),
    "bad index": (bad_index_mesh, r"triangle indices outside \[0, 3\)"),
}


@pytest.mark.parametrize("bad", list(BAD_MESHES))
@pytest.mark.parametrize("func", list(MESH_FUNCTIONS))
def test_bad_meshes_raise(func, bad):
    make, message = BAD_MESHES[bad]
    with pytest.raises(ValueError, match=message):
        MESH_FUNCTIONS[func](make())


@pytest.mark.parametrize("func", [mean_curvature, mesh_report, average_curvature])
def test_non_mesh_raises(func):
    with pytest.raises(ValueError, match="mesh must be an open3d.geometry.TriangleMesh"):
        func(np.zeros((4, 3)))


BAD_POINTS = {
    "wrong shape": (np.zeros((5, 2)), r"must have shape \(N, 3\), got \(5, 2\)"),
    "empty": (np.zeros((0, 3)), "is empty"),
    "nan": (np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 0.0]]), "has 1 row.* with NaN or infinite coordinates"),
    "not numbers": ([["a", "b", "c"]], r"must be an \(N, 3\) array of numbers"),
}


@pytest.mark.parametrize("bad", list(BAD_POINTS))
def test_bad_points_raise(bad):
    pts, message = BAD_POINTS[bad]
    with pytest.raises(ValueError, match="^points " + message):
        fitness_error(pts, sphere(1.0, 5))
    with pytest.raises(ValueError, match="^a " + message):
        chamfer(pts, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="^b " + message):
        f_score(np.zeros((2, 3)), pts, 0.1)


@pytest.mark.parametrize("threshold", [0.0, -1.0, float("nan"), "x"])
def test_bad_threshold_raises(threshold):
    with pytest.raises(ValueError, match="threshold"):
        f_score(np.zeros((2, 3)), np.zeros((2, 3)), threshold)


@pytest.mark.parametrize("n_samples", [0, -5, 2.5])
def test_bad_n_samples_raises(n_samples):
    mesh = sphere(1.0, 5)
    for call in (chamfer, normal_consistency, lambda a, b, n_samples: f_score(a, b, 0.1, n_samples=n_samples)):
        with pytest.raises(ValueError, match="n_samples"):
            call(mesh, mesh, n_samples=n_samples)


def test_bad_seed_raises():
    with pytest.raises(ValueError, match="seed"):
        chamfer(sphere(1.0, 5), sphere(1.0, 5), seed=-1)


def test_zero_area_mesh_cannot_be_sampled():
    flat = mesh_from([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="a has zero surface area"):
        chamfer(flat, np.zeros((1, 3)))


def test_curvature_undefined_everywhere_raises():
    triangle = mesh_from(np.eye(3), [[0, 1, 2]])
    assert np.all(np.isnan(mean_curvature(triangle)))
    with pytest.raises(ValueError, match="no interior vertex"):
        average_curvature(triangle)


def test_public_names():
    assert set(metrics.__all__) == {
        "fitness_error",
        "point_distances",
        "mean_curvature",
        "average_curvature",
        "chamfer",
        "f_score",
        "normal_consistency",
        "mesh_report",
        "drop_specks",
    }


def test_point_distances_to_a_unit_square():
    # Two triangles spanning the unit square at z = 0: a point above it is |z| away, one beside it
    # is the distance to the nearest edge.
    square = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]),
                                       o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]]))
    pts = np.array([[0.5, 0.5, 0.3], [0.2, 0.7, -0.05], [2.0, 0.5, 0.0], [-3.0, -4.0, 0.0]])
    assert metrics.point_distances(pts, square) == pytest.approx([0.3, 0.05, 1.0, 5.0], abs=1e-6)
    with pytest.raises(ValueError):
        metrics.point_distances(np.zeros((2, 2)), square)


def test_drop_specks_removes_only_pieces_smaller_than_the_size():
    from o3drbf.mesh.metrics import drop_specks

    big = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=20)
    speck = o3d.geometry.TriangleMesh.create_sphere(0.02, resolution=4).translate((3.0, 0.0, 0.0))  # 0.069 across
    small_object = o3d.geometry.TriangleMesh.create_sphere(0.1, resolution=6).translate((-3.0, 0.0, 0.0))  # 0.35 across
    mesh = big + speck + small_object
    n_big, n_small = len(big.triangles), len(small_object.triangles)
    out, removed = drop_specks(o3d.geometry.TriangleMesh(mesh), 0.1)
    assert removed == 1 and len(out.triangles) == n_big + n_small
    assert np.asarray(out.vertices)[:, 0].max() < 1.01  # the speck at x = 3 is gone, the rest untouched
    assert mesh_report(out)["components"] == 2 and mesh_report(out)["watertight"]
    # Never all of it: a mesh made only of specks stays as it is.
    only, removed = drop_specks(o3d.geometry.TriangleMesh(speck), 1.0)
    assert removed == 0 and len(only.triangles) == len(speck.triangles)
    # size 0 removes nothing
    assert drop_specks(o3d.geometry.TriangleMesh(mesh), 0.0)[1] == 0
