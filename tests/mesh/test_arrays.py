"""o3drbf.mesh.arrays: one reading of every mesh form, the shared ray-casting
scene and the edge table, against hand-counted meshes."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from o3drbf.mesh.arrays import mesh_arrays, raycasting_scene, triangle_components, unique_edges

TETRA_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def _box():
    return o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)  # [0, 1]^3, 8 vertices, 12 triangles


def test_every_mesh_form_gives_the_same_arrays(tmp_path):
    box = _box()
    v, f = np.asarray(box.vertices), np.asarray(box.triangles)
    path = tmp_path / "box.ply"
    assert o3d.io.write_triangle_mesh(str(path), box)
    forms = {
        "legacy": box,
        "tensor": o3d.t.geometry.TriangleMesh.from_legacy(box),
        "pair": (v.tolist(), f.tolist()),
        "path": path,
        "str path": str(path),
    }
    for name, form in forms.items():
        verts, tris = mesh_arrays(form)
        assert verts.dtype == np.float64 and tris.dtype == np.int64, name
        np.testing.assert_allclose(verts, v, atol=1e-6, err_msg=name)  # the file stores float32
        np.testing.assert_array_equal(tris, f, err_msg=name)


@pytest.mark.parametrize(
    "mesh,message",
    [
        (np.zeros((4, 3)), "must be an open3d.geometry.TriangleMesh"),
        ((np.zeros((0, 3)), np.zeros((0, 3), int)), r"empty \(no vertices\)"),
        ((TETRA_V, np.zeros((0, 3), int)), "4 vertices but no triangles"),
        ((TETRA_V[:, :2], TETRA_F), r"vertices must have shape \(V, 3\)"),
        ((TETRA_V, TETRA_F.astype(float)), "triangles must be integers"),
        ((np.where(np.eye(4, 3, dtype=bool), np.nan, TETRA_V), TETRA_F), "NaN or infinite coordinates"),
        ((TETRA_V, TETRA_F + 1), r"triangle indices outside \[0, 4\)"),
    ],
    ids=["not a mesh", "empty", "no triangles", "2-D", "float triangles", "nan", "bad index"],
)
def test_bad_meshes_raise_one_line_naming_the_problem(mesh, message):
    with pytest.raises(ValueError, match=message):
        mesh_arrays(mesh)
    with pytest.raises(ValueError, match="^truth "):
        mesh_arrays(mesh, "truth")


def test_missing_file():
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        mesh_arrays("/nonexistent/mesh.ply")


def test_scene_hits_the_box_where_it_is():
    v, f = mesh_arrays(_box())
    scene = raycasting_scene(v, f)
    rays = o3d.core.Tensor(np.array([[0.5, 0.5, -1.0, 0, 0, 1], [0.25, 0.75, 3.0, 0, 0, -1], [2.0, 2.0, -1, 0, 0, 1]], np.float32))
    hit = scene.cast_rays(rays)["t_hit"].numpy()
    np.testing.assert_allclose(hit[:2], [1.0, 2.0], atol=1e-6)
    assert np.isinf(hit[2])
    q = o3d.core.Tensor(np.array([[0.5, 0.5, 3.0]], np.float32))
    assert scene.compute_distance(q).numpy()[0] == pytest.approx(2.0, abs=1e-6)


def test_empty_scene_misses_everything():
    scene = raycasting_scene(np.zeros((0, 3)), np.zeros((0, 3), int))
    hit = scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, -1, 0, 0, 1]], np.float32)))["t_hit"].numpy()
    assert np.isinf(hit).all()


def test_edges_of_a_tetrahedron_and_a_box():
    edges, side, counts = unique_edges(TETRA_F)
    assert edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]  # all 6 pairs, sorted
    assert counts.tolist() == [2] * 6
    for t in range(len(TETRA_F)):
        for k in range(3):  # side k is opposite corner k
            pair = sorted([TETRA_F[t, (k + 1) % 3], TETRA_F[t, (k + 2) % 3]])
            assert edges[side[t, k]].tolist() == pair
    v, f = mesh_arrays(_box())
    edges, _, counts = unique_edges(f)
    assert len(edges) == 18 and (counts == 2).all()  # 12 cube edges + 6 face diagonals; V - E + F = 2
    assert len(v) - len(edges) + len(f) == 2
    open_edges, _, open_counts = unique_edges(f[:-1])  # one triangle off: its 3 edges are now boundary
    assert len(open_edges) == 18 and (open_counts == 1).sum() == 3


@pytest.mark.parametrize("seed", range(4))
def test_edges_of_triangle_soups_are_a_sort_of_the_sides(seed):
    """unique_edges against a plain sort of the sides' (lower, higher) vertex pairs, on soups with fans of
    hundreds of triangles at one vertex (sorted by merging) and triangles that repeat a vertex."""
    rng = np.random.default_rng(seed)
    tris = rng.integers(0, 40, (300, 3))
    fan = np.c_[np.full(200, 7), rng.integers(0, 300, (200, 2))]  # vertex 7: over 400 sides
    tris = np.vstack([tris, fan, [[5, 5, 5], [3, 9, 3]]])
    edges, side, counts = unique_edges(tris)
    a, b = np.roll(tris, -1, axis=1).ravel(), np.roll(tris, -2, axis=1).ravel()
    pairs = np.c_[np.minimum(a, b), np.maximum(a, b)]
    expected, inverse, expected_counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    assert np.array_equal(edges, expected) and np.array_equal(counts, expected_counts)
    assert np.array_equal(side.ravel(), inverse.ravel())


def test_triangle_components_are_open3ds_clusters():
    """Pieces joined through shared edges, numbered as Open3D's cluster_connected_triangles numbers them."""
    pieces = [o3d.geometry.TriangleMesh.create_torus().translate((3.0 * i, 0, 0)) for i in range(3)]
    pieces.append(o3d.geometry.TriangleMesh.create_sphere(0.2).translate((0, 0, 4)))
    mesh = pieces[0]
    for p in pieces[1:]:
        mesh += p
    order = np.random.default_rng(0).permutation(len(mesh.triangles))  # pieces interleaved in the list
    mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[order])
    n, labels = triangle_components(np.asarray(mesh.triangles))
    ref, _, _ = mesh.cluster_connected_triangles()
    assert n == 4
    assert np.array_equal(labels, np.asarray(ref))


def test_triangles_sharing_only_a_corner_are_two_pieces():
    tris = np.array([[0, 1, 2], [0, 3, 4], [1, 2, 5]])  # the second touches the first at vertex 0 only
    n, labels = triangle_components(tris)
    assert n == 2
    assert labels.tolist() == [0, 1, 0]


def test_mesh_arrays_removals_are_open3ds():
    """``keep_triangles`` and ``without_degenerate_triangles`` give, in the same order, the vertices, normals,
    colours and triangles Open3D's ``remove_triangles_by_mask``, ``remove_degenerate_triangles`` and
    ``remove_unreferenced_vertices`` leave; ``to_open3d``/``from_open3d`` carry all of them."""
    import open3d as o3d

    from o3drbf.mesh.arrays import MeshArrays

    rng = np.random.default_rng(0)
    verts = rng.normal(size=(40, 3))
    tris = rng.integers(0, 30, size=(60, 3))  # vertices 30-39 unused; some triangles name a vertex twice
    tris[:5, 1] = tris[:5, 0]
    normals, colors = rng.normal(size=(40, 3)), rng.uniform(size=(40, 3))
    ours = MeshArrays(verts, tris, normals, colors)
    assert (ours.triangles[:, 0] == ours.triangles[:, 1]).sum() >= 5

    def same(a: MeshArrays, b) -> None:
        for name in ("vertices", "triangles", "vertex_normals", "vertex_colors"):
            np.testing.assert_array_equal(getattr(a, name), np.asarray(getattr(b, name)), err_msg=name)

    theirs = ours.to_open3d()
    theirs.remove_degenerate_triangles()
    theirs.remove_unreferenced_vertices()
    same(ours.without_degenerate_triangles(), theirs)
    keep = rng.uniform(size=60) < 0.5
    theirs = ours.to_open3d()
    theirs.remove_triangles_by_mask(~keep)
    theirs.remove_unreferenced_vertices()
    same(ours.keep_triangles(keep), theirs)
    same(MeshArrays.from_open3d(theirs), theirs)
    assert len(ours.keep_triangles(keep).vertices) < 30


def test_ply_written_by_o3drbf_is_checked_record_by_record(tmp_path, monkeypatch):
    """A .ply is read back before its rename and every record compared: a writer that drops a byte leaves no file."""
    import open3d as o3d

    import o3drbf.io.files as files
    from o3drbf.mesh.arrays import MeshArrays

    mesh = MeshArrays.from_open3d(o3d.geometry.TriangleMesh.create_sphere(1.0, 8).compute_vertex_normals())
    files.write_mesh(tmp_path / "ok.ply", mesh)
    back = o3d.io.read_triangle_mesh(str(tmp_path / "ok.ply"))
    np.testing.assert_array_equal(np.asarray(back.vertices), mesh.vertices)
    np.testing.assert_array_equal(np.asarray(back.triangles), mesh.triangles)
    np.testing.assert_array_equal(np.asarray(back.vertex_normals), mesh.vertex_normals)
    write = files._write_ply

    def short(path, m, fields):
        records = write(path, m, fields)
        with open(path, "r+b") as fh:
            fh.truncate(fh.seek(0, 2) - 1)
        return records

    monkeypatch.setattr(files, "_write_ply", short)
    with pytest.raises(OSError, match="read back"):
        files.write_mesh(tmp_path / "bad.ply", mesh)
    assert not (tmp_path / "bad.ply").exists()
