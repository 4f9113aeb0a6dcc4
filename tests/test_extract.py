"""Marching cubes on the narrow band against the full grid and analytic truth."""

import numpy as np
import pytest

from o3drbf.extract import evaluate_grid, extract_mesh, grid_for
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.prep.normalize import Normalization
from o3drbf.synthetic.shapes import Torus
from o3drbf.surface import ImplicitSurface


class Analytic:
    """A stand-in surface with f = -signed distance of a torus (f > 0 inside)."""

    def __init__(self, shape):
        self.shape = shape
        self.normalization = Normalization(center=np.array([1.0, 2.0, 3.0]), scale=2.0)
        self.metadata = {}
        self.centres = np.array([[-1.0, -1.0, -0.5], [1.0, 1.0, 0.5]])

    def evaluate_box(self, x, gradient=False, approximate=False):
        x = np.asarray(x, float)
        v = -self.shape.signed_distance(x)
        if not gradient:
            return v
        h = 1e-6
        g = np.column_stack([(-self.shape.signed_distance(x + h * e) + self.shape.signed_distance(x - h * e)) / (2 * h) for e in np.eye(3)])
        return v, g


def test_band_matches_full_grid_signs():
    s = Analytic(Torus(0.6, 0.2))
    for res in (33, 64, 96):
        origin, h, shape = grid_for([[-1, -1, -0.5], [1, 1, 0.5]], res, multiple=8)
        band, exact = evaluate_grid(s.evaluate_box, origin, h, shape)
        full, _ = evaluate_grid(s.evaluate_box, origin, h, shape, band=False)
        assert ((band > 0) != (full > 0)).sum() == 0
        assert exact.mean() < 0.6  # it really is a band
        # every grid cell crossing the surface has all 8 corners evaluated exactly
        crossing = np.zeros(np.array(shape) - 1, bool)
        corners = [full[a : a + shape[0] - 1, b : b + shape[1] - 1, c : c + shape[2] - 1] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
        crossing = (np.minimum.reduce(corners) < 0) & (np.maximum.reduce(corners) > 0)
        ex = [exact[a : a + shape[0] - 1, b : b + shape[1] - 1, c : c + shape[2] - 1] for a in (0, 1) for b in (0, 1) for c in (0, 1)]
        assert np.logical_and.reduce(ex)[crossing].all()


def test_mesh_of_an_analytic_torus_is_closed_genus_one_and_accurate():
    torus = Torus(0.6, 0.2)
    s = Analytic(torus)
    mesh = extract_mesh(s, resolution=64, bounds=s.normalization.inverse(np.array([[-1, -1, -0.4], [1, 1, 0.4]])))
    assert mesh.is_watertight() and mesh.is_edge_manifold()
    assert mesh.euler_poincare_characteristic() == 0
    v = s.normalization.forward(np.asarray(mesh.vertices))
    h = 2 / 64
    assert np.abs(torus.signed_distance(v)).max() < 0.1 * h + 1e-3
    # outward normals
    n = np.asarray(mesh.vertex_normals)
    g = np.column_stack([(torus.signed_distance(v + 1e-6 * e) - torus.signed_distance(v - 1e-6 * e)) / 2e-6 for e in np.eye(3)])
    assert (np.einsum("ij,ij->i", n, g) > 0.99).all()
    # triangles wound outward too: positive signed volume equal to the torus volume
    # (2 pi^2 R r^2 in the box; data = box / scale with scale 2, so divided by 8), and
    # each face normal agrees with the analytic outward normal at its centroid
    t = np.asarray(mesh.triangles)
    w = np.asarray(mesh.vertices)
    a, b, c = w[t[:, 0]], w[t[:, 1]], w[t[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert volume == pytest.approx(2 * np.pi**2 * 0.6 * 0.2**2 / 8, rel=0.02)
    face_n = np.cross(b - a, c - a)
    cen = s.normalization.forward((a + b + c) / 3)
    gc = np.column_stack([(torus.signed_distance(cen + 1e-6 * e) - torus.signed_distance(cen - 1e-6 * e)) / 2e-6 for e in np.eye(3)])
    assert (np.einsum("ij,ij->i", face_n, gc) > 0).mean() > 0.999


def test_open_surface_in_a_box_and_capping():
    s = Analytic(Torus(0.6, 0.2))
    half = s.normalization.inverse(np.array([[0.0, -1, -0.4], [1, 1, 0.4]]))
    opened = extract_mesh(s, resolution=48, bounds=half, closed=False)
    capped = extract_mesh(s, resolution=48, bounds=half, closed=True)
    assert not opened.is_watertight()
    assert capped.is_watertight()
    assert np.asarray(opened.vertices)[:, 0].min() >= half[0, 0] - 1e-9


def test_voxel_size_sets_spacing_and_errors():
    s = Analytic(Torus(0.6, 0.2))
    bounds = s.normalization.inverse(np.array([[-1, -1, -0.4], [1, 1, 0.4]]))
    m = extract_mesh(s, voxel_size=0.025, bounds=bounds, normals="grid")
    e = np.asarray(m.vertices)
    assert len(e) > 1000
    with pytest.raises(RuntimeError, match="No surface found at level 5"):
        extract_mesh(s, resolution=32, bounds=bounds, level=5.0)
    with pytest.raises(ValueError, match="resolution must be"):
        extract_mesh(s, resolution=1, bounds=bounds)
    with pytest.raises(ValueError, match="bounds must be"):
        extract_mesh(s, resolution=32, bounds=[[0, 0, 0], [0, 1, 1]])
    with pytest.raises(ValueError, match="normals must be"):
        extract_mesh(s, resolution=32, bounds=bounds, normals="smooth")


def test_rbf_surface_extraction_chunked_memory_path():
    # a real ImplicitSurface evaluated through the NumPy reference and the compiled path give the same mesh
    rng = np.random.default_rng(0)
    p, n = Torus(0.6, 0.25).sample(600, seed=1)
    from o3drbf.solvers import solve

    x = np.vstack([p, p + 0.08 * n])
    y = np.r_[np.zeros(600), -np.ones(600)]
    k = MultiOrder(10, 0.01)
    sol = solve(k, x, y, 1e-3)
    s = ImplicitSurface(k, x, sol.weights, sol.poly, Normalization.identity(), {"bounds": [[-1, -1, -0.4], [1, 1, 0.4]]})
    m = extract_mesh(s, resolution=40)
    assert m.is_watertight()
    assert m.euler_poincare_characteristic() == 0
    assert rng is not None


# -- the grid (particle-mesh) evaluator used for meshing ----------------------------------------
def _fitted_torus(n=1500):
    from o3drbf.solvers import solve

    p, nrm = Torus(0.6, 0.2).sample(n, seed=4)
    c = np.vstack([p, p[::10] + 0.05 * nrm[::10]])
    y = np.r_[np.zeros(len(p)), -np.ones(len(p[::10]))]
    kernel = MultiOrder(3.0, 0.01)
    lam = np.r_[np.full(len(p), 0.03 * kernel.value_at_zero), np.full(len(p[::10]), 2.0)]
    sol = solve(kernel, c, y, lam, method="dense")
    return ImplicitSurface(kernel, c, sol.weights, sol.poly)


def test_grid_evaluator_mesh_matches_exact_evaluation_within_a_fraction_of_a_voxel():
    """The default meshing evaluator (grid sums, >= 1,000 centres) against exact direct sums
    (no tables): same triangles, vertices within 2e-2 voxel, normals within 3e-3 rad (the grid's
    gradients are about ten times less accurate than its values, MESH_EPS)."""
    from scipy.spatial import cKDTree

    from o3drbf.extract import mesh_evaluator

    s = _fitted_torus()
    fast_ev = mesh_evaluator(s)
    assert fast_ev.kind == "grid"

    def exact(pts, gradient=False):
        return s.evaluate_box(pts, gradient=gradient)

    res = 48
    box = [[-1, -1, -0.4], [1, 1, 0.4]]
    fast_mesh = extract_mesh(s, resolution=res, bounds=box)
    ref_mesh = extract_mesh(s, resolution=res, bounds=box, evaluator=exact)
    h = 2.0 / res
    v, r = np.asarray(fast_mesh.vertices), np.asarray(ref_mesh.vertices)
    assert len(v) == len(r) and len(fast_mesh.triangles) == len(ref_mesh.triangles)
    d, j = cKDTree(r).query(v)
    assert d.max() < 2e-2 * h, d.max() / h  # (values snapped off grid corners move up to 1e-2 h)
    n_fast, n_ref = np.asarray(fast_mesh.vertex_normals), np.asarray(ref_mesh.vertex_normals)[j]
    assert np.abs(n_fast - n_ref).max() < 3e-3, np.abs(n_fast - n_ref).max()
    # Below the threshold (and for surfaces with their own evaluator) nothing changes.
    assert mesh_evaluator(s, min_centres=10**6).kind == "table"


def test_a_refit_shares_the_first_fits_meshing_grid_sum_with_its_own_weights():
    """A robust refit (the same constraints, some left out, new weights) is evaluated by the first fit's
    meshing grid sum with its own weights, zero at the centres it lacks: no new grid sum, and f and
    grad f as the refit's direct sums give them, within the grid's tolerance (MESH_EPS of max |f|,
    ten times that for gradients).  Centres that are not those of the grid sum get a grid of their own."""
    from o3drbf.extract import MESH_EPS, mesh_evaluator
    from o3drbf.solvers import solve

    first = _fitted_torus()
    grid = mesh_evaluator(first)
    keep = np.ones(len(first.centres), bool)
    keep[::7] = False  # left out, as a robust refit drops constraints
    c = first.centres[keep]
    y = np.where(np.arange(len(first.centres)) < 1500, 0.0, -1.0)[keep]
    sol = solve(first.kernel, c, y, 0.05 * first.kernel.value_at_zero, method="dense")
    refit = ImplicitSurface(first.kernel, c, sol.weights, sol.poly)
    shared = mesh_evaluator(refit, shared=(grid, np.flatnonzero(keep)))
    assert shared.kind == "grid" and shared.operator is grid.operator and refit.meshing is shared
    pts = c[::5] + np.random.default_rng(0).normal(scale=0.03, size=(len(c[::5]), 3))
    f, g = shared(pts, gradient=True)
    f_ref, g_ref = refit.evaluate_box(pts, gradient=True)
    scale = np.abs(f_ref).max()
    assert np.abs(f - f_ref).max() < MESH_EPS * scale, np.abs(f - f_ref).max() / scale
    assert np.abs(g - g_ref).max() < 10 * MESH_EPS * np.abs(g_ref).max(), np.abs(g - g_ref).max() / np.abs(g_ref).max()
    np.testing.assert_array_equal(first.meshing(pts), grid(pts))  # the first fit's values unchanged
    # Places that do not hold the refit's centres: a grid sum of its own, still right.
    other = ImplicitSurface(first.kernel, c, sol.weights, sol.poly)
    own = mesh_evaluator(other, shared=(grid, np.flatnonzero(keep)[::-1]))
    assert own.kind == "grid" and own.operator is not grid.operator
    assert np.abs(own(pts) - f_ref).max() < MESH_EPS * scale
    beyond = ImplicitSurface(first.kernel, c, sol.weights, sol.poly)  # places past the grid sum's centres: not shared
    assert mesh_evaluator(beyond, shared=(grid, np.flatnonzero(keep) + len(first.centres))).operator is not grid.operator


class Ball:
    """f = R^2 - |x|^2 in box coordinates: a ball whose f bends across each cell, so straight-line
    interpolation between grid corners puts the vertices inside it (by about h^2 / (8 R))."""

    def __init__(self, radius):
        self.radius = radius
        self.normalization = Normalization(center=np.zeros(3), scale=1.0)
        self.metadata = {}
        self.centres = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])

    def evaluate_box(self, x, gradient=False, approximate=False):
        x = np.asarray(x, float)
        v = self.radius**2 - (x * x).sum(axis=1)
        return (v, -2 * x) if gradient else v


@pytest.mark.parametrize("refine", [True, False])
def test_vertices_are_moved_onto_the_surface_along_their_edges(refine):
    res = 24
    h = 2.0 / res
    ball = Ball(3.3 * h)  # 3.3 cells across its radius
    mesh = extract_mesh(ball, resolution=res, bounds=[[-1, -1, -1], [1, 1, 1]], evaluator=ball.evaluate_box, refine=refine)
    assert mesh.is_watertight()
    err = np.linalg.norm(np.asarray(mesh.vertices), axis=1) - ball.radius
    if refine:
        assert np.median(np.abs(err)) < 0.001 * h  # on the sphere, to the false-position steps' accuracy ...
        assert np.abs(err).max() < 0.05 * h  # ... or held a tenth of an edge off a corner
    else:
        assert err.mean() < -0.01 * h  # straight-line interpolation: inside the ball
    # every vertex still on a grid edge: two of its coordinates are grid nodes
    idx = (np.asarray(mesh.vertices) - (-1.0)) / h
    on_node = np.abs(idx - np.rint(idx)) < 1e-5  # float32 vertices
    assert (on_node.sum(axis=1) >= 2).all()



def test_vertices_that_stopped_moving_take_no_more_steps(monkeypatch):
    """A vertex whose last step moved it less than REFINE_TOL of its edge (a Newton step, with the gradient for
    its normal: less than NEWTON_DONE) is not evaluated again: the last step evaluates fewer points than the
    first, and the vertices stay within REFINE_TOL cells of where every step for every vertex puts them (normals
    within the turn of a NEWTON_DONE move along the edge).  A ball 19 cells in radius."""
    import o3drbf.extract as ex

    res = 64
    h = 2.0 / res
    ball = Ball(0.6)
    calls = []

    def counted(x, gradient=False):
        calls.append(len(x))
        return ball.evaluate_box(x, gradient=gradient)

    def run():
        calls.clear()
        mesh = extract_mesh(ball, resolution=res, bounds=[[-1, -1, -1], [1, 1, 1]], evaluator=counted)
        return np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), list(calls)

    v, n, c = run()
    tol, newton_done = ex.REFINE_TOL, ex.NEWTON_DONE
    monkeypatch.setattr(ex, "REFINE_TOL", 0.0)
    monkeypatch.setattr(ex, "NEWTON_DONE", 0.0)
    v_all, n_all, c_all = run()
    refine = c_all[-3:]  # the three steps of every vertex, after the grid's evaluations
    assert refine[0] == refine[1] == refine[2] == len(v_all)
    # the first step (every vertex), the second, the last (the vertices still moving only), then the gradients
    # of the vertices that stopped after the first step
    assert c[-4] == len(v) and c[-2] < 0.5 * len(v) and c[-1] + c[-3] == len(v)
    assert c[-2] < 0.15 * len(v)  # Newton's second step leaves few vertices a third (false position: 45 %)
    assert 0 < np.abs(v - v_all).max() < tol * h
    turn = np.degrees(newton_done * h / ball.radius)  # the normal's turn over a NEWTON_DONE move along the edge
    assert np.degrees(np.arccos(np.clip((n * n_all).sum(axis=1), -1, 1))).max() < turn
    err = np.abs(np.linalg.norm(v, axis=1) - ball.radius)
    assert np.median(err) < 1e-3 * h
