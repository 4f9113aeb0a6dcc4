"""Refitter: one dense factorization updated by the Woodbury identity, against fresh dense solves."""

import numpy as np
import pytest

from o3drbf.constraints.robust import robust_reweight
from o3drbf.pipeline import fit, surface_of
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import Gaussian, MultiOrder, ThinPlate
from o3drbf.rbf.sums import polynomial_basis
from o3drbf.solvers import Refitter, solve

from conftest import ROBUST_KERNEL as KERNEL, radial_error, sphere_constraints
from test_solve import reference as full_reference


def problem(n=300, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = d * np.where(np.arange(n) < n - n // 10, 0.7, 0.8)[:, None]
    y = np.where(np.arange(n) < n - n // 10, 0.0, -1.0)
    lam = np.where(y == 0, 1e-3, 2.0)
    return x, y, lam


def reference(kernel, x, y, lam):
    """numpy.linalg.solve of the full saddle-point matrix of the kept constraints (finite lambda)."""
    keep = np.isfinite(lam)
    return full_reference(kernel, x[keep], y[keep], lam[keep])


@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), Gaussian(0.3)], ids=repr)
def test_woodbury_update_equals_a_fresh_solve(kernel):
    x, y, lam0 = problem()
    session = Refitter(kernel, x, y, lam0, method="dense")
    keep, first = session.solve()
    assert keep.all() and "update" not in first.info
    w_ref, p_ref = reference(kernel, x, y, lam0)
    np.testing.assert_allclose(first.weights, w_ref, rtol=1e-7, atol=1e-7 * np.abs(w_ref).max())
    lam = lam0.copy()
    lam[[3, 50, 51, 120]] *= [10.0, 1e3, 1e6, 2.5]  # down-weighted
    lam[[7, 200]] = np.inf  # dropped
    keep, sol = session.solve(lam)
    assert sol.info.get("update") == "woodbury" and sol.info["changed"] == 6
    assert keep.sum() == len(x) - 2 and not keep[7] and not keep[200]
    w_ref, p_ref = reference(kernel, x, y, lam)
    assert len(sol.weights) == len(w_ref)
    np.testing.assert_allclose(sol.weights, w_ref, rtol=1e-6, atol=1e-7 * np.abs(w_ref).max())
    np.testing.assert_allclose(sol.poly, p_ref, rtol=1e-6, atol=1e-9)
    assert sol.residual < 1e-8
    # its residual is that of the kept system, as a fresh solve measures it
    fresh = solve(kernel, x[keep], y[keep], lam[keep], method="dense")
    assert sol.residual == pytest.approx(fresh.residual, abs=1e-9)


def test_many_changes_solve_afresh_and_agree():
    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem()
    session = Refitter(kernel, x, y, lam0, method="dense", max_changed=5)
    session.solve()
    lam = lam0 * 3.0  # every constraint changed: beyond max_changed
    keep, sol = session.solve(lam)
    assert "update" not in sol.info and keep.all()
    w_ref, _ = reference(kernel, x, y, lam)
    np.testing.assert_allclose(sol.weights, w_ref, rtol=1e-6, atol=1e-7 * np.abs(w_ref).max())


def test_non_dense_methods_and_indefinite_kernels_solve_afresh():
    x, y, lam0 = problem(n=200)
    lam = lam0.copy()
    lam[5] = np.inf
    for kernel, method in ((ThinPlate(), "dense"), (MultiOrder(10, 0.01), "iterative")):
        session = Refitter(kernel, x, y, lam0, method=method)
        session.solve()
        keep, sol = session.solve(lam)
        assert "update" not in sol.info and not keep[5]
        w_ref, _ = reference(kernel, x, y, lam)
        np.testing.assert_allclose(sol.weights, w_ref, rtol=1e-5, atol=1e-6 * np.abs(w_ref).max())


def test_bad_smoothing_is_refused():
    x, y, lam0 = problem(n=100)
    session = Refitter(MultiOrder(10, 0.01), x, y, lam0, method="dense")
    for bad in (lam0[:-1], np.where(np.arange(100) == 3, np.nan, lam0), -lam0):
        with pytest.raises(ValueError, match="smoothing"):
            session.solve(bad)


def test_robust_refits_by_update_equal_refits_by_fresh_fits():
    """The robust loop on a sphere with 3 % gross outliers: the Woodbury refits give the fresh refits' surface."""
    dirty, pts, k = sphere_constraints(0.03, noise=0.005, seed=4)
    norm = Normalization.identity()
    session = Refitter(KERNEL, dirty.points, dirty.values, dirty.smoothing, method="dense")
    updates = []

    def refit(smoothing=None):
        keep, sol = session.solve(smoothing)
        updates.append(sol.info.get("update"))
        return surface_of(sol, dirty.points[keep], KERNEL, norm), sol

    fresh = robust_reweight(lambda c: fit(c, KERNEL, norm, solver="dense"), dirty, noise_scale=0.005)
    updated = robust_reweight(lambda c: fit(c, KERNEL, norm, solver="dense"), dirty, noise_scale=0.005, first=refit(),
                              refit=refit)
    assert updated[2].rounds == fresh[2].rounds >= 1 and updates[1:] == ["woodbury"] * updated[2].rounds
    np.testing.assert_array_equal(updated[2].weights, fresh[2].weights)
    g = np.random.default_rng(3).uniform(-1, 1, (400, 3))
    assert np.abs(updated[0].evaluate_box(g) - fresh[0].evaluate_box(g)).max() < 1e-7
    assert radial_error(updated[0], pts) == pytest.approx(radial_error(fresh[0], pts), rel=1e-6)


def assert_matches_dense(kernel, x, y, lam, sol):
    """The fitted function of ``sol`` against a dense solve of the same system (independent: Cholesky, no
    fast products), at 300 points of the box, to 1e-3 of its largest value."""
    from o3drbf.rbf.sums import kernel_sum

    dense = solve(kernel, x, y, lam, method="dense")
    g = np.random.default_rng(5).uniform(-0.9, 0.9, (300, 3))
    q = polynomial_basis(g, kernel.polynomial_degree)
    f_fast = kernel_sum(kernel, x, sol.weights, g) + q @ sol.poly
    f_dense = kernel_sum(kernel, x, dense.weights, g) + q @ dense.poly
    assert np.abs(f_fast - f_dense).max() < 1e-3 * np.abs(f_dense).max()


def test_fast_refits_start_from_the_previous_solution_and_agree_with_a_dense_solve():
    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem(n=8000, seed=2)  # above the preconditioner's exact coarse level (6,000)
    lam0 = np.where(y == 0, 1e-5, 2.0)
    session = Refitter(kernel, x, y, lam0, method="fast")
    _, first = session.solve()
    lam = lam0.copy()
    lam[[10, 11, 400]] *= 1e3
    lam[[5, 2000]] = np.inf
    keep, sol = session.solve(lam)
    assert sol.method == "fast" and sol.info["left_out"] == 2 and keep.sum() == len(x) - 2
    cold = solve(kernel, x[keep], y[keep], lam[keep], method="fast")
    print(f"fast iterations: first {first.iterations}, warm refit {sol.iterations}, cold solve of the refit {cold.iterations}")
    assert sol.iterations <= 0.6 * cold.iterations  # measured 13 vs 32 (31 without the start)
    # the fitted function against a dense solve of the kept system (independent: Cholesky, no fast products)
    assert_matches_dense(kernel, x[keep], y[keep], lam[keep], sol)


def test_memory_limits_are_checked_before_anything_is_built():
    x, y, lam0 = problem(n=200)
    with pytest.raises(MemoryError, match="dense solve of 200 constraints needs about"):
        Refitter(MultiOrder(10, 0.01), x, y, lam0, method="dense", memory_limit=1000)
    session = Refitter(MultiOrder(10, 0.01), x, y, lam0, method="fast", memory_limit=10**6)
    with pytest.raises(MemoryError, match="fast solve of 200 constraints needs about"):
        session.solve()
    assert session.operator is None


def test_refits_reuse_back_substitutions_and_stay_exact(monkeypatch):
    """A sequence of refits with overlapping changed sets (the robust loop's pattern), each against numpy."""
    from o3drbf.solvers import dense

    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem()
    q = polynomial_basis(x, kernel.polynomial_degree)
    factor = dense.DenseFactor(kernel, x, lam0, q)
    calls = []
    real = dense.sla.cho_solve
    monkeypatch.setattr(dense.sla, "cho_solve", lambda f, b, **k: (calls.append(b.shape[1]), real(f, b, **k))[1])
    monkeypatch.setattr(dense, "MAX_KEPT_COLUMNS", 4)
    for changed, scale in (([3, 50], 10.0), ([3, 50, 51], 1e3), ([3, 50, 51], np.inf), ([9, 60, 61, 62, 63], 5.0)):
        lam = lam0.copy()
        lam[changed] *= scale
        w, p, k = factor.solve(y, lam)
        w_ref, p_ref = reference(kernel, x, y, lam)
        assert k == len(changed)
        np.testing.assert_allclose(w[np.isfinite(lam)], w_ref, rtol=1e-6, atol=1e-7 * np.abs(w_ref).max())
        np.testing.assert_allclose(p, p_ref, rtol=1e-6, atol=1e-9)
    # [y, Q] once, then only the constraints not seen before: 2, 1, none, 5 (the cache of 4 is reset).
    assert calls == [1 + q.shape[1], 2, 1, 5]


@pytest.mark.parametrize("n", [1, 2, 7, 8, 301])
def test_lower_kernel_matrix_is_the_full_matrix_lower_triangle(n):
    from o3drbf.rbf.sums import kernel_matrix

    x = np.random.default_rng(n).uniform(-1, 1, (n, 3))
    kernel = MultiOrder(10, 0.01)
    full = kernel_matrix(kernel, x)
    lower = kernel_matrix(kernel, x, lower=True)
    il = np.tril_indices(n)
    np.testing.assert_array_equal(lower[il], full[il])
    np.testing.assert_allclose(full, full.T, rtol=0, atol=0)
    with pytest.raises(ValueError, match="omit y"):
        kernel_matrix(kernel, x, x, lower=True)


def test_fast_refits_reuse_the_first_refits_preconditioner_set_to_the_new_smoothing():
    from o3drbf.solvers.fast import TwoLevel, fast_operator, spatial_order

    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem(n=8000, seed=2)
    lam0 = np.where(y == 0, 1e-5, 2.0)
    session = Refitter(kernel, x, y, lam0, method="fast")
    _, first = session.solve()
    assert "preconditioner" not in session.start and "preconditioner_object" not in first.info  # (no refit may follow)
    lam = lam0.copy()
    lam[[10, 11, 400]] *= 1e3
    session.solve(lam)
    prec = session.start["preconditioner"]
    lam[[12, 13]] *= 1e3
    keep, sol = session.solve(lam)
    assert session.start["preconditioner"] is prec and sol.residual <= 1e-6
    # its local step is the one a new preconditioner for that smoothing builds (independent: built afresh)
    # a coarse centre's too (the coarse level factored again); the preconditioner works on the centres in
    # spatial order (fast.spatial_order), so lambda goes to it in that order
    order = spatial_order(x)
    lam[order[prec.coarse[[0, 7]]]] = 1e6
    prec.set_smoothing(lam[order])
    fresh = TwoLevel(prec.fast, lam[order])
    assert np.array_equal(prec.near_diag, fresh.near_diag)
    assert abs(prec.near - fresh.near).max() == 0
    r = np.random.default_rng(4).normal(size=len(x))
    assert np.abs(prec(r) - fresh(r)).max() <= 1e-10 * np.abs(fresh(r)).max()
    # a plain solve keeps no preconditioner (it would hold its memory)
    op = fast_operator(kernel, x, eps=1e-7)
    assert "preconditioner_object" not in solve(kernel, x, y, lam0, method="fast").info and op.n == len(x)


def test_a_refitter_expecting_refits_keeps_the_first_preconditioner_for_them():
    """With ``refits`` the first solve's preconditioner is kept and the first refit sets it to its smoothing
    (no new one built); the refit still solves its system (against a dense solve of the kept constraints)."""
    from o3drbf.solvers.fast import precondition

    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem(n=8000, seed=2)
    lam0 = np.where(y == 0, 1e-5, 2.0)
    session = Refitter(kernel, x, y, lam0, method="fast", refits=True)
    session.solve()
    prec = session.start["preconditioner"]
    built = []
    init = precondition.TwoLevel.__init__
    precondition.TwoLevel.__init__ = lambda self, *a, **k: built.append(1) or init(self, *a, **k)
    try:
        lam = lam0.copy()
        lam[[10, 11, 400]] *= 1e3
        lam[[5, 2000]] = np.inf
        keep, sol = session.solve(lam)
    finally:
        precondition.TwoLevel.__init__ = init
    assert session.start["preconditioner"] is prec and not built
    assert_matches_dense(kernel, x[keep], y[keep], lam[keep], sol)


def test_fast_refits_start_from_the_last_residual_moved_by_the_smoothing_change(monkeypatch):
    """A refit's FGMRES starts from the last solve's true residual less the smoothing's change times its
    weights, without a product: that is the start's residual in the new system (checked against direct
    sums).  A refit at another tolerance (other products) finds its residual by a product."""
    from o3drbf.rbf.sums import kernel_sum
    from o3drbf.solvers import DROPPED_SMOOTHING, fast
    from o3drbf.solvers.fast import solver

    kernel = MultiOrder(10, 0.01)
    x, y, lam0 = problem(n=8000, seed=2)
    lam0 = np.where(y == 0, 1e-5, 2.0)
    session = Refitter(kernel, x, y, lam0, method="fast")
    session.solve()
    order = fast.spatial_order(x)
    xo, yo, q = x[order], y[order], polynomial_basis(x[order], kernel.polynomial_degree)

    def residual(z, lam):  # [y; 0] - K z by direct sums (independent of the grid's products)
        w, p = z[:len(x)], z[len(x):]
        return np.concatenate([yo - kernel_sum(kernel, xo, w, xo) - lam * w - q @ p, -q.T @ w])

    starts = []
    fgmres = solver.fgmres
    monkeypatch.setattr(solver, "fgmres", lambda *a, **k: starts.append(k["start"]) or fgmres(*a, **k))
    lam = lam0.copy()
    lam[[10, 11, 400]] *= 1e3
    lam[[5, 2000]] = np.inf
    keep, sol = session.solve(lam)
    assert keep.sum() == len(x) - 2 and sol.residual <= 1e-6
    x0, r0 = starts[-1]
    big = np.where(np.isfinite(lam), lam, DROPPED_SMOOTHING * lam[np.isfinite(lam)].max())[order]
    truth = residual(x0, big)
    assert r0 is not None and np.abs(r0 - truth).max() <= 1e-6 * np.abs(truth).max()
    session.options["rtol"] = 1e-4  # looser products than the last solve's: no residual to move
    session.solve(lam)
    assert starts[-1][0] is not None and starts[-1][1] is None


def test_fast_solves_run_in_spatial_order_and_answer_in_the_callers():
    """solve_fast permutes the system to fast.spatial_order and back: the weights match a dense solve's in the
    caller's order, a start x0 is taken in the caller's order, and an operator on other orders is refused."""
    from o3drbf.solvers import fast, solve_fast

    kernel = MultiOrder(10, 0.01)
    x, y, lam = problem(n=4000, seed=3)
    assert not np.array_equal(fast.spatial_order(x), np.arange(len(x)))
    dense = solve(kernel, x, y, lam, method="dense")
    sol = solve_fast(kernel, x, y, lam, rtol=1e-8)
    np.testing.assert_allclose(sol.weights, dense.weights, rtol=0, atol=1e-4 * np.abs(dense.weights).max())
    again = solve_fast(kernel, x, y, lam, rtol=1e-8, start={"x0": np.concatenate([sol.weights, sol.poly])})
    assert again.iterations <= 1
    with pytest.raises(ValueError, match="spatial_order"):
        solve_fast(kernel, x, y, lam, operator=fast.fast_operator(kernel, x))
