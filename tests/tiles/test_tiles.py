"""Tiled reconstruction (o3drbf.tiles): partition of unity, tiled surface, Dask, welding."""

from __future__ import annotations

import numpy as np
import pytest

from o3drbf.prep.sampling import mean_spacing
from o3drbf.synthetic.shapes import Torus
from o3drbf.tiles.extract import extract_tiled
from o3drbf.tiles.fit import TILE_DEFAULTS, fit_tiled, surface_tile_cap, tile_count
from o3drbf.tiles.partition import Partition, kd_split, wendland, wendland_derivative
from o3drbf.tiles.surface import TiledSurface

distributed = pytest.importorskip("distributed")

SMALL = Torus(0.7, 0.25)
LONG = Torus(8.0, 0.6)


@pytest.fixture(scope="module")
def client():
    """One real LocalCluster (2 processes x 1 thread) for the whole module."""
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, memory_limit="2GiB", dashboard_address=":0")
    c = distributed.Client(cluster)
    yield c
    c.close()
    cluster.close()


@pytest.fixture(scope="module")
def small():
    pts, nrm = SMALL.sample(2500, seed=1)
    return pts, nrm


@pytest.fixture(scope="module")
def small_tiled(small):
    pts, nrm = small
    return fit_tiled(pts, nrm, tiles=4, client="synchronous", surface_count_per_tile=None, global_count=300)


@pytest.fixture(scope="module")
def long_torus():
    pts, nrm = LONG.sample(6000, seed=2)
    return pts, nrm


LONG_OPTIONS = {"tiles": 6, "surface_count_per_tile": 900, "global_count": 600, "seed": 3}


@pytest.fixture(scope="module")
def long_cluster(long_torus, client):
    pts, nrm = long_torus
    surf = fit_tiled(pts, nrm, client=client, **LONG_OPTIONS)
    stats = {}
    mesh = extract_tiled(surf, resolution=96, client=client, stats=stats)
    return surf, mesh, stats


# -- partition ---------------------------------------------------------------------
def test_wendland_values_and_derivative():
    r = np.array([0.0, 0.25, 0.5, 1.0, 1.5])
    # (1 - r)^4 (4 r + 1) by hand.
    assert np.allclose(wendland(r), [1.0, 0.75**4 * 2.0, 0.5**4 * 3.0, 0.0, 0.0])
    x = np.linspace(0.01, 1.2, 50)
    fd = (wendland(x + 1e-6) - wendland(x - 1e-6)) / 2e-6
    assert np.allclose(wendland_derivative(x), fd, atol=1e-6)


def test_kd_split_balances_points_and_partitions_the_box():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(7000, 3)) * [3.0, 1.0, 0.5]
    root = np.array([pts.min(0) - 1, pts.max(0) + 1])
    lo, hi = kd_split(pts, 7, root)
    counts = [np.all((pts >= a) & (pts < b), axis=1).sum() for a, b in zip(lo, hi)]
    assert sum(counts) == len(pts) and max(counts) - min(counts) <= 2
    assert np.isclose(np.prod(hi - lo, axis=1).sum(), np.prod(root[1] - root[0]))
    # Random points of the root box: in exactly one cell, and covered by the supports.
    x = rng.uniform(root[0], root[1], size=(5000, 3))
    inside = np.stack([np.all((x >= a) & (x < b), axis=1) for a, b in zip(lo, hi)], axis=1)
    assert (inside.sum(1) == 1).all()
    part = Partition.from_cells(lo, hi, overlap=0.25)
    w = part.weights(x)
    assert (w.sum(1) > 0).all()
    assert (w[inside] > 0).all()
    with pytest.raises(ValueError, match="overlap"):
        Partition.from_cells(lo, hi, overlap=0.0, min_overlap=0.0)


def test_tile_count_rule():
    assert tile_count(1_000_000) == 17
    assert tile_count(100, tiles="auto") == 1
    assert tile_count(1000, tiles=3) == 3
    with pytest.raises(ValueError, match="tiles"):
        tile_count(1000, tiles="many")
    assert tile_count(10_000_000, surface_cap=21) == 21 and tile_count(100_000, surface_cap=21) == 2
    assert tile_count(10_000_000, tiles=400, surface_cap=21) == 400  # a count given is kept


def test_surface_cap_counts_the_voxels_the_surface_crosses():
    """Truth: an axis-aligned square crosses exactly (side / voxel)^2 voxels; a sphere about 1.5 A / s^2
    (a plane of normal n crosses (|nx| + |ny| + |nz|) A / s^2 voxels; the mean of that over directions is 1.5)."""
    rng = np.random.default_rng(0)
    u = rng.uniform(0.0, 1.0, (200_000, 2))
    square = np.c_[u, np.full(len(u), 0.3)]
    cell = 0.02 / 0.75  # voxels of 0.02: 50 x 50 = 2500
    assert surface_tile_cap(square, cell, 100) == 25
    assert surface_tile_cap(square, cell, 2400) == 2
    assert surface_tile_cap(square, cell, None) is None
    v = rng.normal(size=(400_000, 3))
    sphere = v / np.linalg.norm(v, axis=1, keepdims=True)
    voxels = surface_tile_cap(sphere, 0.05 / 0.75, 1)  # ~80 samples per voxel area; thin slivers of voxels get none
    assert 0.93 < voxels / (1.5 * 4 * np.pi / 0.05**2) < 1.0


def test_auto_tiles_stop_at_what_the_mesh_shows_and_dense_tiles_are_subsampled():
    """Auto tiles capped by the surface at the mesh's resolution; a tile denser than its constraints need
    fits from a subsample, and every point is still counted once as kept."""
    pts, nrm = SMALL.sample(12_000, seed=3)
    common = dict(client="synchronous", global_count=200, surface_count_per_tile=25, outliers="none", resolution=10, points_per_tile=300)
    s = fit_tiled(pts, nrm, **common)
    m = s.metadata
    uncapped = tile_count(len(pts), "auto", 300)
    assert uncapped == 40 and 1 <= m["tile_count"] < uncapped
    limit = TILE_DEFAULTS["support_points_per_constraint"] * 25
    assert all(t["used"] == min(t["points"], limit) for t in m["tiles"]) and m["subsampled_tiles"] >= 1
    assert m["kept"] == len(pts) and m["outliers"] == 0
    assert np.abs(s(pts)).mean() < 0.01


# -- tiled surface ---------------------------------------------------------------------
def test_value_is_the_partition_of_unity_formula(small_tiled):
    s = small_tiled
    x = np.random.default_rng(1).uniform(-1.0, 1.0, size=(500, 3)) * [1.0, 1.0, 0.4]
    xb = s.normalization.forward(x)
    w = s.partition.weights(xb)
    g = np.stack([t.evaluate_box(xb) for t in s.tiles], axis=1)
    expected = s.base.evaluate_box(xb) + (w * g).sum(1) / w.sum(1)
    assert np.allclose(s(x), expected, rtol=1e-12, atol=1e-12)


def test_gradient_matches_finite_differences_and_f_is_continuous_at_borders(small_tiled):
    s = small_tiled
    pts, nrm = SMALL.sample(300, seed=4)
    eps = 1e-6
    fd = np.stack([(s(pts + eps * e) - s(pts - eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
    g = s.gradient(pts)
    assert np.abs(fd - g).max() < 1e-5 * np.abs(g).max()
    # Across a cut between two cells (and a support's edge) f changes by O(distance).
    cut = s.normalization.inverse(s.partition.hi[0])[0]
    y = pts.copy()
    y[:, 0] = cut
    d = np.array([1e-9, 0, 0])
    assert np.abs(s(y + d) - s(y - d)).max() < 1e-6


def test_save_load_round_trip_and_validation(small_tiled, tmp_path):
    s = small_tiled
    path = s.save(tmp_path / "tiled.npz")
    back = TiledSurface.load(path)
    x = np.random.default_rng(2).uniform(-1, 1, size=(200, 3))
    assert np.array_equal(back(x), s(x))
    assert back.metadata["tile_count"] == 4
    with np.load(path) as data:
        arrays = dict(data)
    arrays["weights"] = arrays["weights"][:-1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match="corrupt tiled model"):
        TiledSurface.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="must end in .npz"):
        s.save(tmp_path / "tiled.bin")


# -- global vs tiled ---------------------------------------------------------------------
def test_tiled_fit_agrees_with_the_global_fit(small, small_tiled):
    from o3drbf.extract import extract_mesh
    from o3drbf.mesh.metrics import chamfer
    from o3drbf.pipeline import reconstruct

    pts, nrm = small
    spacing = mean_spacing(pts)
    glob = reconstruct(pts, nrm, surface_count=None, auto=True, resolution=48, extract=False).surface
    s = small_tiled
    x, xn = SMALL.sample(3000, seed=7)
    fg, gg = glob.evaluate(x, gradient=True)
    ft = s(x)
    w = s.partition.weights(s.normalization.forward(x))
    border = (w / w.sum(1, keepdims=True)).max(1) < 0.999
    assert 200 < border.sum() < len(x) - 200
    # |f_tiled - f_global| / |grad f_global|: distance between the zero sets, on the true surface.
    d = np.abs(ft - fg) / np.linalg.norm(gg, axis=1)
    for part in (~border, border):
        assert d[part].max() < 0.25 * spacing
        assert d[part].mean() < 0.05 * spacing
    # Inside / outside agree with the truth on both sides of the surface.
    for off in (0.05, -0.05):
        assert (np.sign(s(x + off * xn)) == -np.sign(off)).all()
    bounds = glob.metadata["bounds"]
    mg = extract_mesh(glob, resolution=48, bounds=bounds)
    mt = extract_tiled(s, resolution=48, bounds=bounds, client="synchronous")
    assert chamfer(mg, mt, n_samples=20000)["l1"] < 0.05 * spacing


# -- a long torus across tiles, on a real cluster --------------------------------------------
def test_long_torus_is_one_closed_genus_one_piece(long_cluster):
    surf, mesh, stats = long_cluster
    # The torus crosses several tiles (and several cuts).
    owners = [t["points"] for t in surf.metadata["tiles"]]
    assert len(owners) == 6 and min(owners) > 500
    assert mesh.is_watertight() and mesh.is_edge_manifold() and mesh.is_vertex_manifold()
    v, f = len(mesh.vertices), np.asarray(mesh.triangles)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    e = len(np.unique(edges, axis=0))
    assert v - e + len(f) == 0  # genus 1
    labels, counts, _ = mesh.cluster_connected_triangles()
    assert len(counts) == 1
    assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)  # no double faces
    assert stats["vertices_before_weld"] > stats["vertices"] and stats["weld_mismatch"] == 0.0
    # Time and peak memory measured on each of the two worker processes, for the fit and the meshing.
    for record in (surf.metadata["workers"], stats["workers"]):
        assert len(record) == 2 and all(name.startswith("tcp://") for name in record)
    assert sum(w["tasks"] for w in surf.metadata["workers"].values()) == 6
    assert sum(w["tasks"] for w in stats["workers"].values()) == 12  # coarse and fine pass per tile
    assert all(50 * 2**20 < w["peak_rss"] < 2 * 2**30 for w in stats["workers"].values())  # memory_limit 2 GiB
    # Outward faces (positive volume) and close to the true torus.
    verts = np.asarray(mesh.vertices)
    vol = np.einsum("ij,ij->i", verts[f[:, 0]], np.cross(verts[f[:, 1]], verts[f[:, 2]])).sum() / 6
    assert np.isclose(vol, 2 * np.pi**2 * 8.0 * 0.6**2, rtol=0.05)
    assert np.abs(LONG.signed_distance(verts)).max() < 0.05


def test_cluster_result_equals_single_process_result(long_torus, long_cluster):
    pts, nrm = long_torus
    surf, mesh, _ = long_cluster
    ref = fit_tiled(pts, nrm, client="synchronous", **LONG_OPTIONS)
    assert np.array_equal(ref.base.weights, surf.base.weights)
    for a, b in zip(ref.tiles, surf.tiles):
        assert np.array_equal(a.weights, b.weights) and np.array_equal(a.poly, b.poly)
    m2 = extract_tiled(ref, resolution=96, client="synchronous")
    assert np.array_equal(np.asarray(m2.vertices), np.asarray(mesh.vertices))
    assert np.array_equal(np.asarray(m2.triangles), np.asarray(mesh.triangles))


def test_command_line_helpers():
    from o3drbf.options import count_or_auto
    from o3drbf.tiles.run import reconstruct_tiled

    assert count_or_auto("auto") == "auto" and count_or_auto("3") == 3
    for bad in ("0", "x"):
        with pytest.raises(ValueError, match="expected .auto. or a (whole )?number"):
            count_or_auto(bad)
    pts, nrm = SMALL.sample(800, seed=9)
    surf, mesh, stats = reconstruct_tiled(pts, nrm, tiles=2, scheduler="synchronous", resolution=24,
                                          surface_count_per_tile=200, global_count=100)
    assert stats["tiles"] == 2 and len(surf.tiles) == 2
    assert mesh.is_edge_manifold(allow_boundary_edges=False) and stats["triangles"] == len(mesh.triangles)
    assert np.abs(SMALL.signed_distance(np.asarray(mesh.vertices))).max() < 0.05


def test_cli_tiles_synchronous(tmp_path):
    import open3d as o3d

    from o3drbf.cli import main
    from o3drbf.io.files import write_points
    from o3drbf.synthetic.shapes import Torus

    p, n = Torus(0.6, 0.25).sample(4000, seed=1)
    write_points(tmp_path / "t.ply", p, n)
    out = tmp_path / "m.ply"
    args = ["reconstruct", str(tmp_path / "t.ply"), "-o", str(out), "--tiles", "2", "--scheduler", "synchronous",
            "--resolution", "32", "--surface-count", "400", "-q"]
    assert main(args) == 0
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert mesh.is_watertight() and mesh.euler_poincare_characteristic() == 0
    assert main(args[:-1] + ["--kernel", "gaussian"]) == 2  # tiles need the multiorder kernel


def test_tiled_vertices_are_moved_onto_the_level_set_and_still_weld(small_tiled):
    """Refined like extract_mesh: |f| / |grad f| at the vertices falls, positions stay tile-independent."""
    s = small_tiled
    out = {}
    for refine in (False, True):
        stats = {}
        mesh = extract_tiled(s, resolution=40, client="synchronous", stats=stats, refine=refine)
        v = s.normalization.forward(np.asarray(mesh.vertices))
        f, g = s.evaluate_box(v, gradient=True)
        out[refine] = np.abs(f) / np.linalg.norm(g, axis=1)
        assert mesh.is_watertight() and stats["weld_mismatch"] == 0.0 and stats["vertices_before_weld"] > stats["vertices"]
    lattice_h = 2.0 / 40  # the box is 2 wide: roughly one lattice step
    print(f"median |f|/|grad f| at the vertices: straight lines {np.median(out[False]):.2e}, refined {np.median(out[True]):.2e} "
          f"(lattice step ~{lattice_h:.3f})")
    assert np.median(out[True]) < 0.1 * np.median(out[False])
    assert np.median(out[True]) < 1e-3 * lattice_h


def test_thin_band_meshes_like_every_node_exact(small_tiled):
    """The coarse band (undilated), the middle level and the fine sign-change cells give the mesh of marching cubes
    on every lattice node evaluated directly (vertices not refined, so both are marching cubes' own)."""
    from skimage.measure import marching_cubes

    from o3drbf.mesh.metrics import chamfer
    from o3drbf.tiles.extract import lattice_for

    s = small_tiled
    stats = {}
    thin = extract_tiled(s, resolution=96, client="synchronous", stats=stats, refine=False)
    lat = lattice_for(s, 96)
    idx = np.indices(lat["shape"]).reshape(3, -1).T
    values = s.evaluate_box(lat["origin"] + idx * lat["h"], approximate=True).reshape(lat["shape"])
    verts, faces, _, _ = marching_cubes(values, level=0.0)
    import open3d as o3d

    full = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(s.normalization.inverse(lat["origin"] + verts * lat["h"])),
                                     o3d.utility.Vector3iVector(faces))
    h = lat["h"] / s.normalization.scale  # a lattice step, data units
    d = chamfer(thin, full)
    print(f"exact nodes: thin band {stats['evaluated']:,} of {values.size:,}; Chamfer to every node's mesh {d['l1']:.2e}, "
          f"Hausdorff {d['hausdorff']:.2e} (lattice step {h:.3f})")
    assert stats["evaluated"] < 0.3 * values.size
    assert d["l1"] < 1e-3 * h and d["hausdorff"] < 0.05 * h
    assert len(thin.triangles) == len(faces) and thin.is_watertight()


def _first_of(i, lattice=None):
    return float(lattice["origin"][0]) + i


def test_shared_dicts_are_scattered_whole_under_fresh_keys(client):
    """A dict argument (the lattice, the settings) goes out as one object: scattering the dict itself keyed each item
    by its name ("origin", ...), the same in every pass, and one pass releasing them lost the next's ("lost dependencies")."""
    from o3drbf.tiles.cluster import run_tasks

    class Spy:
        def __init__(self, c):
            self.c, self.keys = c, []

        def scatter(self, data, **kw):
            out = self.c.scatter(data, **kw)
            self.keys += [f.key for f in (out.values() if isinstance(out, dict) else out)]
            return out

        def __getattr__(self, name):
            return getattr(self.c, name)

    spy = Spy(client)
    for _ in range(3):
        assert run_tasks(spy, _first_of, 3, {"lattice": {"origin": np.ones(3), "h": 0.5}}) == [1.0, 2.0, 3.0]
    assert len(spy.keys) == 3 and len(set(spy.keys)) == 3
    assert not {"origin", "h"} & set(map(str, spy.keys))
