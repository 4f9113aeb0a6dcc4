"""End to end: analytic shapes in, meshes out, checked against the truth."""

import numpy as np
import pytest

import o3drbf
from o3drbf.mesh.metrics import average_curvature, fitness_error
from o3drbf.synthetic.shapes import Sphere, Torus


def test_sphere_radius_recovered_within_one_percent():
    sphere = Sphere(radius=2.5, center=(10.0, -3.0, 4.0))
    p, n = sphere.sample(4000, seed=1)
    r = o3drbf.reconstruct(p, n, lambda_surface=1e-5, surface_count=1500, resolution=64)
    radii = np.linalg.norm(np.asarray(r.mesh.vertices) - sphere.center, axis=1)
    assert abs(radii.mean() / 2.5 - 1) < 0.01  # the radius, within 1%
    assert np.abs(radii / 2.5 - 1).max() < 0.02  # and no vertex sags more than 2% between samples
    # the implicit function itself: zero on the sphere, positive inside, negative outside
    q, _ = sphere.sample(200, seed=9)
    assert np.abs(r.surface(q)).max() < 0.01
    assert r.surface(np.array(sphere.center))[0] > 0
    assert r.surface(np.array(sphere.center) + [5.0, 0, 0])[0] < 0


@pytest.fixture(scope="module")
def torus_result():
    torus = Torus(0.6, 0.25)
    p, n = torus.sample(10_000, noise=0.002, seed=4)
    return torus, p, o3drbf.reconstruct(p, n, surface_count=1500, resolution=64)


def test_torus_is_watertight_manifold_genus_one(torus_result):
    torus, p, r = torus_result
    m = r.mesh
    assert m.is_watertight()  # Open3D's: no duplicates, no degenerate or self-intersecting triangles
    assert m.is_edge_manifold() and m.is_vertex_manifold()
    assert m.euler_poincare_characteristic() == 0
    assert len(m.cluster_connected_triangles()[1]) == 1
    d = np.abs(torus.signed_distance(np.asarray(m.vertices)))
    assert d.mean() < 0.004 and d.max() < 0.02


def test_stats_and_constraints_are_reported(torus_result):
    _, p, r = torus_result
    s = r.stats
    assert s["points"] == len(p)
    assert abs(s["surface_constraints"] - 1500) <= 31
    assert s["exterior_constraints"] == pytest.approx(150, abs=20)
    assert s["sphere_constraints"] == 64
    assert s["residual"] < 1e-10
    assert 0.02 < s["mean_spacing"] < 0.06
    c = r.constraints
    assert len(c) == s["surface_constraints"] + s["exterior_constraints"] + s["sphere_constraints"]
    # exterior constraints are outside the torus, surface constraints on it (data coordinates)
    torus = torus_result[0]
    assert (torus.signed_distance(c.select(1)) > 0.03).all()
    assert np.abs(torus.signed_distance(c.select(0))).max() < 0.01


def test_lambda_zero_interpolates_the_constraints():
    p, n = Torus(0.6, 0.25).sample(3000, seed=5)
    r = o3drbf.reconstruct(p, n, lambda_surface=0.0, lambda_exterior=0.0, surface_count=800, extract=False)
    c = r.constraints
    f = r.surface(c.points)
    assert np.max(np.abs(f - c.values)) < 1e-8 * np.max(np.abs(c.values))


def test_more_smoothing_is_smoother_and_fits_less():
    torus = Torus(0.6, 0.25)
    p, n = torus.sample(6000, noise=0.01, seed=6)
    curv, fit = [], []
    for lam in (1e-4, 3e-4, 1e-3, 3e-3):
        # denoise off: lambda's own effect (denoised constraints are already smooth)
        r = o3drbf.reconstruct(p, n, lambda_surface=lam, auto=False, surface_count=1500, resolution=64, denoise=False)
        curv.append(average_curvature(r.mesh))
        fit.append(fitness_error(p, r.mesh)["rms"])
    assert all(a > b for a, b in zip(curv, curv[1:])), curv
    assert all(a < b for a, b in zip(fit, fit[1:])), fit


def test_deterministic_and_accepts_open3d_point_clouds():
    import open3d as o3d

    p, n = Torus(0.6, 0.25).sample(3000, seed=7)
    a = o3drbf.reconstruct(p, n, surface_count=600, resolution=32)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    pcd.normals = o3d.utility.Vector3dVector(n)
    b = o3drbf.reconstruct(pcd, surface_count=600, resolution=32)
    assert np.array_equal(np.asarray(a.mesh.vertices), np.asarray(b.mesh.vertices))
    assert not b.stats["normals_estimated"]


def test_without_normals_they_are_estimated_and_logged(caplog):
    p, _ = Torus(0.6, 0.25).sample(4000, seed=8)
    with caplog.at_level("INFO", logger="o3drbf"):
        r = o3drbf.reconstruct(p, surface_count=800, resolution=48)
    assert "estimating and orienting normals" in caplog.text
    assert r.stats["normals_estimated"]
    assert r.mesh.euler_poincare_characteristic() == 0


@pytest.mark.parametrize("basis", ["thinplate", "gaussian"])
def test_other_bases_run(basis):
    p, n = Sphere(1.0).sample(2000, seed=2)
    extra = {"sigma": 0.3} if basis == "gaussian" else {}
    r = o3drbf.reconstruct(p, n, kernel=basis, surface_count=500, resolution=32, **extra)
    radii = np.linalg.norm(np.asarray(r.mesh.vertices), axis=1)
    assert abs(np.median(radii) - 1) < 0.05


def test_bad_input_gets_a_clear_error():
    p, n = Sphere(1.0).sample(200, seed=2)
    cases = [
        (np.zeros((0, 3)), None, {}, "points is empty"),
        (p[:5], n[:5], {}, "at least 10 needed"),
        (np.vstack([p[:-1], [[np.nan, 0, 0]]]), n, {}, "NaN"),
        (p[:, :2], None, {}, r"shape \(N, 3\)"),
        (p, n[:-1], {}, r"one row per point"),
        (p, np.zeros_like(n), {}, "zero-length"),
        (p, n, {"delta": 0}, "delta must be"),
        (p, n, {"tau": -1}, "tau must be"),
        (p, n, {"lambda_surface": -1e-3}, "lambda_surface must be"),
        (p, n, {"lambda_exterior": float("nan")}, "lambda_exterior must be"),
        (p, n, {"surface_count": 3}, "surface_count must be"),
        (p, n, {"exterior_offset": 2.0}, "exterior_offset must be"),
        (p, n, {"exterior_ratio": 1.5}, "exterior_ratio must be"),
        (p, n, {"basis": "spline"}, "unknown kernel"),
            (p, n, {"kernel": "gaussian", "delta": -5}, "delta does not apply to the 'gaussian' kernel"),
            (p, n, {"kernel": "thinplate", "sigma": 0.3}, "sigma does not apply"),
            (p, n, {"surface_cuont": 10}, "unknown option"),
        (p, n, {"solver": "magic"}, "solver must be one of"),
        (p, n, {"resolution": 1}, "resolution must be"),
        ("points.ply", None, {}, r"must be an \(N, 3\) array"),
    ]
    for pts, nrm, kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            o3drbf.reconstruct(pts, nrm, surface_count=kw.pop("surface_count", 100), **kw)


def test_oversmoothing_that_erases_the_surface_says_what_to_change():
    p, n = Torus(0.6, 0.25).sample(3000, seed=5)
    with pytest.raises(RuntimeError, match=r"No surface found.*lower lambda_surface"):
        o3drbf.reconstruct(p, n, lambda_surface=0.5, surface_count=500, resolution=32)


def test_fast_solver_gives_the_dense_surface():
    p, n = Torus(0.6, 0.25).sample(6000, seed=11)
    kw = dict(surface_count=2000, extract=False)
    dense = o3drbf.reconstruct(p, n, solver="dense", **kw)
    fast = o3drbf.reconstruct(p, n, solver="fast", **kw)
    assert fast.stats["solver"] == "fast" and fast.stats["iterations"] > 0
    probe = np.random.default_rng(0).uniform(-1, 1, (2000, 3))
    fd, ff = dense.surface(probe), fast.surface(probe)
    assert np.max(np.abs(ff - fd)) < 1e-4 * np.max(np.abs(fd))  # rtol 1e-6 solve, ~100x amplification in f


def test_repeated_points_are_merged_with_a_note():
    p, n = Sphere(1.0).sample(400, seed=2)
    r = o3drbf.reconstruct(np.vstack([p, p[:7]]), np.vstack([n, n[:7]]), surface_count=100, extract_mesh=False, outliers="none")
    assert r.report.duplicates_merged == 7 and r.report.points == 400 and r.report.input_points == 407


def test_the_robust_pass_and_marching_cubes_share_one_grid_sum(monkeypatch):
    """A meshed fit builds one meshing grid sum: the robust pass's first residuals come from it (no direct sum at
    the centres), marching cubes reuse it, and the result does not keep it."""
    from o3drbf.rbf import compiled
    from o3drbf.solvers import fast

    built = []
    real = fast.GridSum

    class Counting(real):
        def __init__(self, *args, **kwargs):
            built.append(kwargs.get("eps"))
            super().__init__(*args, **kwargs)

    def refused(*args, **kwargs):
        raise AssertionError("direct sums at the centres: the meshing grid was not used")

    monkeypatch.setattr(fast, "GridSum", Counting)
    monkeypatch.setattr(compiled, "direct_sum_at_centres", refused)
    p, n = Torus(0.6, 0.25).sample(6000, noise=0.002, seed=4)
    r = o3drbf.reconstruct(p, n, surface_count=1500, resolution=48)
    assert r.report.solver == "dense" and r.report.robust is not None and r.report.robust["rounds"] == 0
    assert built == [o3drbf.extract.MESH_EPS] and r.surface.meshing is None
    assert r.mesh.is_watertight()


def test_a_fit_with_a_fast_evaluator_takes_its_robust_residuals_from_the_meshing_grid(monkeypatch):
    """A fast-solved fit large enough for an evaluator of its own (here made small): the robust pass's
    residuals, f and grad f, come from the grid marching cubes use, not from a second grid of ten times
    the evaluator's accuracy built for gradients alone (the evaluator's, on its centres, tree and outside)."""
    from o3drbf.pipeline import fitting
    from o3drbf.solvers.fast import evaluator, grid

    built = []
    real = grid.GridSum.__init__

    def counting(self, *args, **kwargs):
        built.append("gradients" if {"outside", "neighbours"} <= set(kwargs) else "other")
        real(self, *args, **kwargs)

    monkeypatch.setattr(grid.GridSum, "__init__", counting)
    monkeypatch.setattr(fitting, "FAST_EVALUATION_MIN", 1000)
    p, n = Torus(0.6, 0.25).sample(6000, noise=0.002, seed=4)
    r = o3drbf.reconstruct(p, n, surface_count=1500, resolution=48, solver="fast")
    assert r.report.solver == "fast" and isinstance(r.surface.evaluator.fast_sum, evaluator.GridSum)
    assert r.report.robust is not None and r.report.robust["rounds"] == 0
    assert "other" in built and "gradients" not in built and r.surface.meshing is None
    assert r.mesh.is_watertight()


def test_the_meshing_grid_covers_the_lattice_from_the_start(monkeypatch):
    """A fast fit below FAST_EVALUATION_MIN without robust rounds: the meshing grid sum the robust pass
    builds covers marching cubes' lattice from the start, so one FFT grid serves the residuals and the mesh
    and one potential of the final weights serves both (a grid over the centres and a second potential on a
    larger one before).  The mesh lies on f = 0 by direct sums."""
    from o3drbf import extract
    from o3drbf.solvers.fast import fftgrid, grid

    evaluators, meshes, potentials = [], {}, []
    real_evaluator, real_mesh, real_potential = extract.mesh_evaluator, grid.GridSum._mesh, fftgrid.Mesh.potential

    def recording(*args, **kwargs):
        evaluators.append(real_evaluator(*args, **kwargs))
        return evaluators[-1]

    def mesh(self, lo, hi):
        m = real_mesh(self, lo, hi)
        meshes.setdefault(id(self), {})[id(m)] = m
        return m

    def potential(self, *args, **kwargs):
        potentials.append(id(self))
        return real_potential(self, *args, **kwargs)

    monkeypatch.setattr(extract, "mesh_evaluator", recording)
    monkeypatch.setattr(grid.GridSum, "_mesh", mesh)
    monkeypatch.setattr(fftgrid.Mesh, "potential", potential)
    p, n = Torus(0.6, 0.25).sample(6000, noise=0.002, seed=4)
    r = o3drbf.reconstruct(p, n, surface_count=1500, resolution=48, solver="fast")
    assert r.report.solver == "fast" and r.report.robust["rounds"] == 0 and r.mesh.is_watertight()
    ops = {id(e.operator) for e in evaluators}
    assert len(ops) == 1 and evaluators[0].kind == "grid"
    own = meshes[ops.pop()]
    assert len(own) == 1, len(own)
    assert potentials.count(next(iter(own))) == 1
    v = r.surface.normalization.forward(np.asarray(r.mesh.vertices))
    f, g = r.surface.evaluate_box(v, gradient=True)
    assert np.median(np.abs(f) / np.linalg.norm(g, axis=1)) < 0.01 * 2.0 / 48


def test_an_evaluator_of_its_own_is_enlarged_by_marching_cubes_not_during_the_fit(monkeypatch):
    """From FAST_EVALUATION_MIN (made 1,000 here) a fit's own evaluator is left on its centres' grid by the
    fit, whose solver structures are still alive there (the larger grid would add to the fit's peak memory);
    marching cubes enlarges it afterwards."""
    from o3drbf import build_constraints, choose_parameters
    from o3drbf.options import ExtractOptions, FitOptions
    from o3drbf.pipeline import fitting
    from o3drbf.pipeline.meshing import mesh_lattice_box, mesh_surface
    from o3drbf.pointset import PointSet

    monkeypatch.setattr(fitting, "FAST_EVALUATION_MIN", 1000)
    p, n = Torus(0.6, 0.25).sample(6000, noise=0.002, seed=4)
    data = PointSet.create(p, n)
    cset = build_constraints(data)
    lattice = mesh_lattice_box(cset, ExtractOptions(resolution=48))
    surface, _, _ = fitting.fit_surface(cset, choose_parameters(data, cset), FitOptions(solver="fast"), resolution=48,
                                        lattice=lattice)
    op = surface.evaluator.fast_sum
    assert not op.mesh.covers(lattice)
    mesh = mesh_surface(surface, ExtractOptions(resolution=48))
    assert op.mesh.covers(lattice) and mesh.is_watertight()


def _torus_with_strays():
    """15,000 points of a torus with 1 % noise, 3 % of them thrown off: a fit with robust rounds."""
    p, n = Torus().sample(15_000, noise=0.01, seed=3)
    rng = np.random.default_rng(4)
    strays = rng.choice(len(p), 450, replace=False)
    p[strays] += rng.normal(0.0, 0.08, (len(strays), 3))
    return p, n


def test_the_robust_refits_of_a_fast_evaluated_fit_are_loose_and_the_last_is_finished(monkeypatch):
    """Noisy points with 3 % strays, fast-solved and evaluated (made so from 1,000 centres): the robust
    refits solve to the loose tolerance of ``ROBUST_SHIFT`` (they only measure residuals), measure them on
    the meshing grid (no finer grid for gradients), and the last is solved on to the mesh's tolerance:
    the final surface solves the final constraints' system to that tolerance (its residual by direct
    sums), and so is the dense solve of them, to the accuracy that tolerance gives."""
    from o3drbf.pipeline import fitting
    from o3drbf.rbf.sums import kernel_sum, polynomial_basis
    from o3drbf.solvers import Refitter, solve
    from o3drbf.solvers.fast import grid
    from o3drbf.surface import ImplicitSurface

    built, tolerances = [], []
    real_grid, real_solve = grid.GridSum.__init__, Refitter.solve

    def counting(self, *args, **kwargs):
        built.append("gradients" if {"outside", "neighbours"} <= set(kwargs) else "other")
        real_grid(self, *args, **kwargs)

    def recording(self, smoothing=None):
        tolerances.append(self.options.get("rtol"))
        return real_solve(self, smoothing)

    monkeypatch.setattr(grid.GridSum, "__init__", counting)
    monkeypatch.setattr(Refitter, "solve", recording)
    monkeypatch.setattr(fitting, "FAST_EVALUATION_MIN", 1000)
    p, n = _torus_with_strays()
    r = o3drbf.reconstruct(p, n, resolution=48, solver="fast")
    rounds = r.report.robust["rounds"]
    assert r.report.solver == "fast" and rounds >= 1 and r.mesh.is_watertight()
    full, loose = tolerances[0], tolerances[1]
    assert loose > 2 * full and tolerances == [full] + [loose] * rounds + [full]
    assert "gradients" not in built
    assert r.report.residual <= full
    c = r.constraints  # the final fit's, data coordinates
    box = r.surface.normalization.forward(c.points)
    s = r.surface
    q = polynomial_basis(box, s.kernel.polynomial_degree)
    top = kernel_sum(s.kernel, box, s.weights, box) + c.smoothing * s.weights + q @ s.poly - c.values
    residual = np.sqrt(np.sum(top**2) + np.sum((q.T @ s.weights) ** 2)) / np.linalg.norm(c.values)
    assert residual < 1.5 * full < loose, (residual, full, loose)  # (the fast products' own error on top of the solve's)
    ref = solve(s.kernel, box, c.values, c.smoothing, method="dense")
    dense = ImplicitSurface(s.kernel, box, ref.weights, ref.poly, s.normalization)
    assert np.abs(s.evaluate_box(box) - dense.evaluate_box(box)).max() < 1e-3


def test_the_robust_refits_below_fast_evaluation_share_the_first_fits_meshing_grid(monkeypatch):
    """A fast fit below FAST_EVALUATION_MIN (no evaluator of its own) with robust rounds: its refits measure
    their residuals on the first fit's meshing grid sum with their own weights, and marching cubes meshes the
    final surface on it too: one meshing grid sum in all (the refits summed directly, and the final
    surface built another).  The mesh is the final surface's: its vertices lie on f = 0 by direct sums."""
    from o3drbf.extract import MESH_EPS
    from o3drbf.pipeline import fitting
    from o3drbf.solvers.fast import grid

    meshing = []
    real_grid = grid.GridSum.__init__

    def counting(self, kernel, centres, eps=grid.DEFAULT_EPS, *args, **kwargs):
        if eps == MESH_EPS and not args and set(kwargs) <= {"box"}:
            meshing.append(len(centres))
        real_grid(self, kernel, centres, eps, *args, **kwargs)

    monkeypatch.setattr(grid.GridSum, "__init__", counting)
    p, n = _torus_with_strays()
    r = o3drbf.reconstruct(p, n, resolution=48, solver="fast")
    assert r.report.solver == "fast" and len(r.surface.centres) < fitting.FAST_EVALUATION_MIN
    assert r.report.robust["rounds"] >= 1 and r.mesh.is_watertight()
    assert len(meshing) == 1, meshing
    v = r.surface.normalization.forward(np.asarray(r.mesh.vertices))
    f, g = r.surface.evaluate_box(v, gradient=True)
    assert np.median(np.abs(f) / np.linalg.norm(g, axis=1)) < 0.01 * 2.0 / 48  # on f = 0 within a hundredth of a cell


def test_the_robust_refits_of_a_fast_evaluated_fit_share_its_evaluators_grid_sums(monkeypatch):
    """From FAST_EVALUATION_MIN constraints (made 1,000 here) every surface has its own evaluator; a robust fit's
    refits (the first fit's centres, some left out) share the first fit's grid sums with their own weights: one
    evaluator grid sum in all, and the final surface evaluates as its own direct sums do."""
    from o3drbf.pipeline import fitting
    from o3drbf.solvers.fast import evaluator

    built = []
    real = evaluator.fast_operator

    def counting(kernel, centres, *args, **kwargs):
        built.append(len(centres))
        return real(kernel, centres, *args, **kwargs)

    monkeypatch.setattr(evaluator, "fast_operator", counting)
    monkeypatch.setattr(fitting, "FAST_EVALUATION_MIN", 1000)
    p, n = _torus_with_strays()
    r = o3drbf.reconstruct(p, n, resolution=48, solver="fast")
    assert r.report.robust["rounds"] >= 1 and r.mesh.is_watertight()
    assert len(built) == 1, built
    ev = r.surface.evaluator
    assert ev.fast_sum.n >= len(r.surface.centres) and ev.weights.shape == (ev.fast_sum.n,)
    x = r.surface.centres[::50]
    from o3drbf.rbf.sums import kernel_sum

    ref = kernel_sum(r.surface.kernel, r.surface.centres, r.surface.weights, x)
    assert np.abs(ev(x) - ref).max() < 1e-5 * np.abs(ref).max()
