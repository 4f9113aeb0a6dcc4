"""Tests for o3drbf.mesh.intersections: the truth is Open3D itself
(``get_self_intersecting_triangles`` and ``is_watertight``, quadratic but
exact to its own definition) on meshes small enough for it to be quick."""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
import pytest
from skimage.measure import marching_cubes

from o3drbf.mesh.intersections import is_watertight, nonmanifold_vertices, self_intersecting_pairs
from o3drbf.mesh.metrics import mesh_report

# --------------------------------------------------------------------------
# helpers


def mesh_from(verts, tris) -> o3d.geometry.TriangleMesh:
    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(verts, dtype=float)),
        o3d.utility.Vector3iVector(np.asarray(tris, dtype=np.int32)),
    )


def open3d_pairs(mesh) -> set[tuple[int, int]]:
    got = np.asarray(mesh.get_self_intersecting_triangles()).reshape(-1, 2)
    return set(map(tuple, np.sort(got, axis=1).tolist()))


def check_same(mesh) -> int:
    """Assert our pairs and watertightness equal Open3D's; return the pair count."""
    ours = self_intersecting_pairs(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    assert ours.dtype == np.int64 and ours.shape[1] == 2
    as_set = set(map(tuple, ours.tolist()))
    assert len(as_set) == ours.shape[0], "a pair was reported twice"
    assert (ours[:, 0] < ours[:, 1]).all()
    assert (np.lexsort((ours[:, 1], ours[:, 0])) == np.arange(ours.shape[0])).all(), "pairs not sorted"
    assert as_set == open3d_pairs(mesh)
    assert is_watertight(mesh) == mesh.is_watertight()
    return ours.shape[0]


def noisy_blob(n: int, noise: float, seed: int, degenerate: bool = False) -> o3d.geometry.TriangleMesh:
    """Marching-cubes mesh of a sphere's distance plus grid noise."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-1.2, 1.2, n)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    f = np.sqrt(x * x + y * y + z * z) - 0.8 + noise * rng.standard_normal(x.shape)
    v, t, _, _ = marching_cubes(f, 0.0, allow_degenerate=degenerate)
    return mesh_from(v, t)


def two_triangles(q, shared: bool = False):
    """Triangle (0,0,0),(1,0,0),(0,1,0) and triangle ``q`` (3, 3); with
    ``shared`` q's first corner reuses vertex 0's index."""
    p = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]
    if shared:
        return mesh_from(p + list(q[1:]), [[0, 1, 2], [0, 3, 4]])
    return mesh_from(p + list(q), [[0, 1, 2], [3, 4, 5]])


# --------------------------------------------------------------------------
# the definition, on two triangles


@pytest.mark.parametrize(
    "q, shared, expected",
    [
        ([[0.2, 0.2, -1], [0.2, 0.2, 1], [0.6, 0.1, 0.3]], False, 1),  # crossing
        ([[0, 0, 0], [0.3, 0.3, -1], [0.3, 0.3, 1]], True, 0),  # crossing, but shares a vertex index: skipped
        ([[0, 0, 0], [0.3, 0.3, -1], [0.3, 0.3, 1]], False, 1),  # same, vertex duplicated: counted
        ([[1, 0, 0], [2, 0, 0.5], [2, 0, -0.5]], False, 1),  # touching at one vertex only
        ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], False, 1),  # touching along an edge only
        ([[1, 0, 0], [0, 1, 0], [1, 1, 0]], False, 1),  # coplanar, touching along an edge
        ([[0.2, 0.2, 0], [1.2, 0.2, 0], [0.2, 1.2, 0]], False, 1),  # coplanar overlap
        ([[0.1, 0.1, 0], [0.3, 0.1, 0], [0.1, 0.3, 0]], False, 1),  # coplanar, contained
        ([[0.2, 0.2, 0], [0.2, 0.2, 1], [0.5, 0.5, 1]], False, 1),  # a vertex on the face
        ([[0.2, 0.2, 1e-3], [0.2, 0.2, 1], [0.5, 0.5, 1]], False, 0),  # near miss
        ([[0.1, 0.1, 1e-7], [0.3, 0.1, 1e-7], [0.1, 0.3, 1e-7]], False, 0),  # parallel, 1e-7 apart
        ([[2, 2, 2], [3, 2, 2], [2, 3, 2]], False, 0),  # far apart
    ],
)
def test_two_triangles_as_open3d(q, shared, expected):
    mesh = two_triangles(q, shared)
    assert len(open3d_pairs(mesh)) == expected  # the definition, as Open3D 0.20 has it
    assert check_same(mesh) == expected


def test_near_corner_pair_of_a_real_mesh():
    """Two triangles of o3drbf's bunny (resolution 96) that meet near a grid
    corner: no edge crosses the other triangle in exact arithmetic, yet
    Open3D reports the pair (Moller's EPSILON snaps tiny plane distances to
    zero).  Matching Open3D means reporting it too."""
    p = [[0.011811014881740155, 0.12208731897486658, 0.034041131723073256],
         [0.01360223973548045, 0.12122314267384193, 0.034041131723073256],
         [0.013604263960794536, 0.12122314267384193, 0.034040245541484146]]  # fmt: skip
    q = [[0.013604263960794536, 0.12122208858416225, 0.034041131723073256],
         [0.015397513039848924, 0.120323826940752, 0.034041131723073256],
         [0.015397513039848924, 0.12122314267384193, 0.0332102945062539]]  # fmt: skip
    mesh = mesh_from(p + q, [[0, 1, 2], [3, 4, 5]])
    assert check_same(mesh) == 1




# --------------------------------------------------------------------------
# many meshes against Open3D


@pytest.mark.parametrize(
    "mesh",
    [
        o3d.geometry.TriangleMesh.create_sphere(1.0, 30),
        o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0),
        o3d.geometry.TriangleMesh.create_torus(1.0, 0.4, 40, 20),
        o3d.geometry.TriangleMesh.create_cylinder(0.5, 2.0, 30, 8),
        o3d.geometry.TriangleMesh.create_cone(),
        o3d.geometry.TriangleMesh.create_mobius(),
        o3d.geometry.TriangleMesh.create_arrow(),
        o3d.geometry.TriangleMesh.create_icosahedron(),
        o3d.geometry.TriangleMesh.create_tetrahedron(),
    ],
    ids=["sphere", "box", "torus", "cylinder", "cone", "mobius", "arrow", "icosahedron", "tetrahedron"],
)
def test_primitives_alone_shifted_and_noisy(mesh):
    check_same(mesh)
    shifted = o3d.geometry.TriangleMesh(mesh)
    shifted.translate((0.3, 0.2, 0.1))
    assert check_same(mesh + shifted) > 0  # two overlapping copies merged
    rng = np.random.default_rng(3)
    v = np.asarray(mesh.vertices)
    check_same(mesh_from(v + 0.05 * rng.standard_normal(v.shape), np.asarray(mesh.triangles)))


@pytest.mark.parametrize("seed", range(4))
def test_marching_cubes_of_noisy_functions(seed):
    n, noise = (18, 26), (0.0, 0.08, 0.25)
    for degenerate in (False, True):
        mesh = noisy_blob(n[seed % 2] + seed, noise[seed % 3], seed, degenerate)
        assert len(mesh.triangles) < 10_000
        check_same(mesh)


def test_overlapping_spheres_merged():
    a = o3d.geometry.TriangleMesh.create_sphere(1.0, 25)
    b = o3d.geometry.TriangleMesh.create_sphere(0.7, 25)
    b.translate((1.2, 0.1, 0.05))
    merged = a + b
    assert merged.is_edge_manifold(False) and merged.is_vertex_manifold()  # closed and manifold ...
    assert check_same(merged) > 0  # ... but not watertight
    assert not is_watertight(merged)
    b.translate((1.0, 0.0, 0.0))  # now disjoint
    assert check_same(a + b) == 0 and is_watertight(a + b)


def test_torus_with_a_vertex_pushed_through():
    mesh = o3d.geometry.TriangleMesh.create_torus(1.0, 0.4, 40, 20)
    v = np.asarray(mesh.vertices).copy()
    # push the vertex farthest out across the tube, past its other side
    k = int(np.argmax(np.linalg.norm(v[:, :2], axis=1)))
    centre = v[k].copy()
    centre[:2] *= 1.0 / np.linalg.norm(centre[:2])  # tube centre, radius 1
    v[k] = v[k] + 2.5 * (centre - v[k])
    pushed = mesh_from(v, np.asarray(mesh.triangles))
    assert pushed.is_edge_manifold(False)
    assert check_same(pushed) > 0 and not is_watertight(pushed)


def test_triangle_folded_over_its_neighbour():
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, 20)
    v = np.asarray(sphere.vertices).copy()
    tris = np.asarray(sphere.triangles)
    t0 = tris[len(tris) // 2]
    # the neighbour across edge (t0[0], t0[1]) and its far corner
    ngb = [t for t in tris if set(t0[:2]) <= set(t) and t2set(t) != t2set(t0)][0]
    far = [i for i in ngb if i not in t0[:2]][0]
    mid = 0.5 * (v[t0[0]] + v[t0[1]])
    # move t0's third corner across the shared edge, onto the neighbour
    v[t0[2]] = mid + 0.7 * (v[far] - mid)
    folded = mesh_from(v, tris)
    assert folded.is_edge_manifold(False)
    check_same(folded)


def t2set(t) -> frozenset:
    return frozenset(int(i) for i in t)


def test_coplanar_grids_overlapping():
    def grid(offset):
        n = 12
        g = np.linspace(0, 1, n)
        x, y = np.meshgrid(g, g, indexing="ij")
        v = np.stack([x.ravel() + offset[0], y.ravel() + offset[1], np.zeros(n * n)], axis=1)
        idx = np.arange(n * n).reshape(n, n)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel()
        return mesh_from(v, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))

    alone = grid((0, 0))
    assert check_same(alone) == 0  # coplanar neighbours touch along edges, but share vertices
    for off in ((0.5, 0.5), (1 / 22, 0.0), (1 / 11, 1 / 11), (1.0, 0.0)):  # half a cell, exact vertex overlap, touching
        assert check_same(alone + grid(off)) > 0


def test_lattice_soups_with_ties():
    """Integer corners: exact coplanarity and exact touching everywhere."""
    rng = np.random.default_rng(5)
    for k in range(4):
        v = rng.integers(0, 4, (600, 3)).astype(float)
        if k % 2:
            v[:, 2] = 0.0
        tris = np.arange(600).reshape(200, 3)
        tris[rng.random((200, 3)) < 0.2] = rng.integers(0, 600, 1)[0]  # some shared vertex indices
        check_same(mesh_from(v, tris))


def test_soup_of_very_unequal_triangles():
    """Large triangles (tested against all, off the grid) among small ones."""
    rng = np.random.default_rng(7)
    n = 400
    centres = rng.random((n, 1, 3)) * 4
    sizes = rng.lognormal(-1.5, 1.0, (n, 1, 1))
    v = (centres + sizes * rng.standard_normal((n, 3, 3))).reshape(-1, 3)
    tris = np.arange(3 * n).reshape(n, 3)
    big = np.array([[-1.0, -1, 2], [6, -1, 2], [-1, 6, 2.1]])  # one triangle across everything
    v = np.concatenate([v, big, big + [0, 0, 0.05]])
    tris = np.concatenate([tris, [[3 * n, 3 * n + 1, 3 * n + 2], [3 * n + 3, 3 * n + 4, 3 * n + 5]]])
    mesh = mesh_from(v, tris)
    found = self_intersecting_pairs(v, tris)
    assert (found[:, 1] == n).sum() > 5  # the big triangle crosses many small ones
    check_same(mesh)


def test_mostly_collapsed_triangles():
    """More than half the triangles collapsed to points (on the surfaces and
    off them): still Open3D's answer."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, 12)
    sphere += o3d.geometry.TriangleMesh.create_sphere(1.0, 12).translate((0.5, 0.0, 0.0))
    v = np.asarray(sphere.vertices)
    rng = np.random.default_rng(11)
    n = 2 * len(sphere.triangles)
    spots = np.concatenate([v[rng.integers(0, len(v), n // 2)], rng.uniform(-1, 1, (n - n // 2, 3))])
    points = np.repeat(spots, 3, axis=0)
    tris = np.concatenate([np.asarray(sphere.triangles), len(v) + np.arange(3 * n).reshape(n, 3)])
    assert check_same(sphere) > 0
    assert check_same(mesh_from(np.concatenate([v, points]), tris)) > 0


# --------------------------------------------------------------------------
# watertight, the report hook, and input checks


def test_is_watertight_on_open_and_non_manifold_meshes():
    box = o3d.geometry.TriangleMesh.create_box()
    open_box = mesh_from(np.asarray(box.vertices), np.asarray(box.triangles)[:-1])
    assert not is_watertight(open_box) and not open_box.is_watertight()
    fin = mesh_from(
        np.concatenate([np.asarray(box.vertices), [[0.5, 0.5, 3.0]]]),
        np.concatenate([np.asarray(box.triangles), [[4, 5, 8]]]),
    )  # a fin on an edge: three triangles on one edge
    assert not is_watertight(fin) and not fin.is_watertight()
    assert is_watertight(box) and box.is_watertight()
    empty = o3d.geometry.TriangleMesh()
    assert is_watertight(empty) == empty.is_watertight()


def test_mesh_report_counts_by_default():
    a = o3d.geometry.TriangleMesh.create_sphere(1.0, 15)
    b = o3d.geometry.TriangleMesh.create_sphere(1.0, 15)
    b.translate((0.8, 0.0, 0.0))
    for mesh in (a, a + b):
        rep = mesh_report(mesh)
        assert rep["self_intersections"] == len(open3d_pairs(mesh))
        assert rep["watertight"] == mesh.is_watertight()
    rep = mesh_report(a + b, self_intersections=False)
    assert rep["self_intersections"] is None and rep["watertight"]  # topology only, when switched off


@pytest.mark.parametrize(
    "verts, tris, match",
    [
        (np.zeros((3, 2)), [[0, 1, 2]], r"\(V, 3\)"),
        ([[0, 0, 0], [1, 0, np.nan], [0, 1, 0]], [[0, 1, 2]], "NaN"),
        (np.zeros((3, 3)), [[0, 1, 3]], r"\[0, 3\)"),
        (np.zeros((3, 3)), [[0, 1]], r"\(F, 3\)"),
        (np.zeros((3, 3)), [[0.0, 1.0, 2.0]], "integer"),
    ],
)
def test_bad_input_is_a_value_error(verts, tris, match):
    with pytest.raises(ValueError, match=match):
        self_intersecting_pairs(verts, tris)


def test_bad_mesh_is_a_value_error():
    with pytest.raises(ValueError, match="TriangleMesh"):
        is_watertight(np.zeros((3, 3)))


def test_tiny_inputs():
    assert self_intersecting_pairs(np.zeros((0, 3)), np.zeros((0, 3), int)).shape == (0, 2)
    assert self_intersecting_pairs(np.eye(3), [[0, 1, 2]]).shape == (0, 2)


def test_timing_300k_triangles():
    """Not asserted: printed for the record (run with -s)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, 275)
    v = np.asarray(mesh.vertices)
    v = v + 1e-3 * np.random.default_rng(0).standard_normal(v.shape)
    tris = np.asarray(mesh.triangles)
    t0 = time.perf_counter()
    pairs = self_intersecting_pairs(v, tris)
    dt = time.perf_counter() - t0
    print(f"\nself_intersecting_pairs: {len(tris)} triangles, {len(pairs)} pairs, {dt:.2f} s")
    assert len(tris) > 300_000


def test_many_cells_tested_in_parallel_chunks_find_every_pair():
    """A mesh large enough for many parallel chunks of cells (18 here) gives Open3D's pairs: none
    lost or counted twice at a chunk's edge."""
    a = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 90, 45)
    b = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 90, 45).translate((0.3, 0.0, 0.05))
    c = o3d.geometry.TriangleMesh.create_sphere(0.4, 40).translate((-0.5, 0.2, 0.0))
    mesh = a + b + c
    assert len(mesh.triangles) > 20_000
    assert check_same(mesh) > 500


@pytest.mark.parametrize("sort", ["counting", "comparison"])
def test_cells_sorted_either_way_give_open3ds_pairs(monkeypatch, sort):
    """The grid's entries sorted by cell by counting (a grid of few cells an entry) or by comparison (two
    clusters far apart: a grid of many empty cells) give Open3D's pairs."""
    from o3drbf.mesh import intersections

    calls = []
    by_cell = intersections._by_cell
    monkeypatch.setattr(intersections, "_by_cell", lambda *a: calls.append(1) or by_cell(*a))
    a = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 40, 20)
    b = o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 40, 20).translate((0.3, 0.0, 0.05))
    mesh = a + b
    if sort == "comparison":
        mesh = mesh + o3d.geometry.TriangleMesh.create_sphere(0.3, 10).translate((400.0, 300.0, 200.0))
    assert check_same(mesh) > 100
    assert bool(calls) == (sort == "counting")


def _vertex_soup(seed, n_vertices, n_triangles):
    """Triangles of three distinct vertices drawn from a few: fans, pinches, non-manifold edges, repeats."""
    rng = np.random.default_rng(seed)
    return np.array([rng.choice(n_vertices, 3, replace=False) for _ in range(n_triangles)], dtype=np.int64)


def _open3d_nonmanifold(verts, tris):
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris.astype(np.int32)))
    return np.sort(np.asarray(mesh.get_non_manifold_vertices()))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("n_vertices, n_triangles", [(6, 4), (8, 10), (12, 20), (30, 40)])
def test_nonmanifold_vertices_are_open3ds_on_soups(seed, n_vertices, n_triangles):
    tris = _vertex_soup(seed, n_vertices, n_triangles)
    verts = np.random.default_rng(seed).normal(size=(n_vertices, 3))
    np.testing.assert_array_equal(nonmanifold_vertices(tris, n_vertices), _open3d_nonmanifold(verts, tris))


def test_nonmanifold_vertices_of_pinched_and_glued_meshes():
    sphere = o3d.geometry.TriangleMesh.create_sphere(1.0, 12)
    verts, tris = np.asarray(sphere.vertices), np.asarray(sphere.triangles).astype(np.int64)
    assert nonmanifold_vertices(tris, len(verts)).size == 0
    # two spheres glued at one vertex: that vertex's link is two circles
    glued = np.vstack([tris, tris + len(verts)])
    glued[glued == len(verts) + 5] = 5
    both = np.vstack([verts, verts + [2.0, 0, 0]])
    assert nonmanifold_vertices(glued, len(both)).tolist() == [5] == _open3d_nonmanifold(both, glued).tolist()
    # an open mesh (a fan cut open) stays manifold, as in Open3D; an unused vertex is skipped
    cut = tris[np.any(tris == 0, axis=1)][1:]
    assert nonmanifold_vertices(cut, len(verts) + 1).tolist() == _open3d_nonmanifold(np.vstack([verts, [[9, 9, 9]]]), cut).tolist() == []
    # mesh_report's vertex_manifold follows it
    glued_mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(both), o3d.utility.Vector3iVector(glued.astype(np.int32)))
    assert mesh_report(glued_mesh)["vertex_manifold"] is False and not glued_mesh.is_vertex_manifold()
