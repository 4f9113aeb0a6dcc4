"""Fast products, fast solve and fast evaluator (o3drbf.solvers.fast) against the dense reference."""

from __future__ import annotations

import os

import numpy as np
import pytest

pytest.importorskip("fmm3dpy")

from scipy.spatial import cKDTree  # noqa: E402

from o3drbf.solvers import fast  # noqa: E402
from o3drbf.rbf.kernels import Gaussian, MultiOrder, ThinPlate  # noqa: E402
from o3drbf.synthetic.shapes import Torus  # noqa: E402
from o3drbf.solvers import ConvergenceWarning, solve  # noqa: E402
from o3drbf.rbf.sums import kernel_matrix, kernel_sum  # noqa: E402


def torus_problem(n, seed=0, offset=0.05):
    """Torus surface constraints (f = 0, lambda 1e-3) + 10% exterior ones (f = -1, lambda 2)."""
    ns = int(round(n / 1.1))
    ne = n - ns
    p, nrm = Torus().sample(ns, seed=seed)
    idx = np.random.default_rng(seed + 1).choice(ns, ne, replace=False)
    c = np.vstack([p, p[idx] + offset * nrm[idx]])
    y = np.r_[np.zeros(ns), -np.ones(ne)]
    lam = np.r_[np.full(ns, 1e-3), np.full(ne, 2.0)]
    return c, y, lam


class DenseSum:
    """The FastSum interface on a dense matrix: isolates the preconditioner from FMM error."""

    def __init__(self, kernel, centres):
        self.kernel, self.centres, self.n = kernel, centres, len(centres)
        self.matrix = kernel_matrix(kernel, centres, order="C")
        self.phi0 = kernel.value_at_zero
        self.eps = 1e-15
        self.info = {"mode": "dense"}
        from scipy.spatial import cKDTree

        self.tree = cKDTree(centres)

    def matvec(self, w, eps=None):
        return self.matrix @ w

    def from_subset(self, subset):
        cols = self.matrix[:, subset]
        return lambda w, eps=None: cols @ w

    def evaluate(self, w, targets, gradient=False, eps=None, subset=None):
        cen = self.centres if subset is None else self.centres[subset]
        return kernel_sum(self.kernel, cen, w, targets, gradient=gradient)


KERNELS = {
    "multiorder-10": MultiOrder(10.0, 0.01),
    "multiorder-3.16": MultiOrder(10**0.5, 0.01),
    "multiorder-complex": MultiOrder(40.0, 0.025),
    "gaussian": Gaussian(0.05),
}


@pytest.fixture(scope="module")
def problem3k():
    return torus_problem(3000)


@pytest.fixture(scope="module")
def dense3k(problem3k):
    """Dense kernel matrices, built once per kernel."""
    cache = {}

    def get(name):
        if name not in cache:
            cache[name] = kernel_matrix(KERNELS[name], problem3k[0])
        return cache[name]

    return get


# -- products -----------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(KERNELS))
@pytest.mark.parametrize("eps", [1e-4, 1e-8])
def test_product_matches_dense(problem3k, dense3k, name, eps):
    kernel = KERNELS[name]
    c = problem3k[0]
    w = np.random.default_rng(7).normal(size=len(c))
    ref = dense3k(name) @ w
    got = fast.FastSum(kernel, c, eps=eps).matvec(w)
    err = np.linalg.norm(got - ref) / np.linalg.norm(ref)
    # fmm3dpy and the truncations deliver ~eps/30; allow eps itself.
    assert err < eps, f"{name}: relative error {err:.1e} at eps {eps:g}"


def test_short_range_term_is_sparse_and_complex_case_is_one_pair(problem3k):
    c = problem3k[0]
    real = fast.FastSum(MultiOrder(10.0, 0.01), c, eps=1e-6)
    assert real._short is not None and real.info["short_nnz"] > 0
    assert len(real._terms) == 1  # Laplace + medium Yukawa by FMM only
    cplx = fast.FastSum(MultiOrder(40.0, 0.025), c, eps=1e-6)
    assert cplx._short is None and len(cplx._terms) == 1 and cplx._terms[0][2]


def test_sparse_budget_falls_back_to_fmm(problem3k, dense3k):
    c = problem3k[0]
    kernel = KERNELS["multiorder-10"]
    w = np.random.default_rng(8).normal(size=len(c))
    fs = fast.FastSum(kernel, c, eps=1e-6, sparse_budget=10)
    assert fs._short is None and len(fs._terms) == 2
    ref = dense3k("multiorder-10") @ w
    assert np.linalg.norm(fs.matvec(w) - ref) / np.linalg.norm(ref) < 1e-6


@pytest.mark.parametrize("name", ["multiorder-10", "multiorder-complex", "gaussian"])
def test_sum_from_a_subset_of_centres(problem3k, dense3k, name):
    """The preconditioner's coarse-to-fine update (Phi[:, C] z_C) when the block is not stored."""
    kernel = KERNELS[name]
    c = problem3k[0]
    subset = np.sort(np.random.default_rng(13).choice(len(c), 300, replace=False))
    z = np.random.default_rng(14).normal(size=300)
    got = fast.FastSum(kernel, c, eps=1e-6).from_subset(subset)(z)
    ref = dense3k(name)[:, subset] @ z
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 1e-6


def test_helper_process_gives_the_same_product():
    c = torus_problem(1500, seed=15)[0]
    w = np.random.default_rng(16).normal(size=len(c))
    kernel = KERNELS["multiorder-10"]
    one = fast.FastSum(kernel, c, eps=1e-6, workers=1).matvec(w)
    two = fast.FastSum(kernel, c, eps=1e-6, workers=2).matvec(w)
    np.testing.assert_allclose(two, one, rtol=1e-12, atol=1e-14 * np.abs(one).max())


def test_duplicate_centres_keep_the_self_term():
    c = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.3, 0.1, -0.2], [0.5, 0.5, 0.5]])
    kernel = MultiOrder(10.0, 0.01)
    w = np.array([1.0, -2.0, 0.5, 0.25])
    got = fast.FastSum(kernel, c, eps=1e-8).matvec(w)
    np.testing.assert_allclose(got, kernel_matrix(kernel, c) @ w, rtol=1e-7)


def test_confluent_kernel_is_refused():
    with pytest.raises(ValueError, match="confluent"):
        fast.FastSum(MultiOrder(20.0, 0.025), np.random.default_rng(0).uniform(-1, 1, (50, 3)))


def test_too_wide_gaussian_is_refused(problem3k):
    with pytest.raises(ValueError, match="sigma"):
        fast.FastSum(Gaussian(1.0), problem3k[0], sparse_budget=10**5)


# -- evaluator ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["multiorder-10", "multiorder-complex", "gaussian"])
def test_evaluator_values_and_gradients(problem3k, name):
    kernel = KERNELS[name]
    c = problem3k[0]
    w = np.random.default_rng(9).normal(size=len(c))
    rng = np.random.default_rng(10)
    m = 2000
    targets = np.vstack([rng.uniform(-1.1, 1.1, (m, 3)), c[:20], c[100:120] + 1e-3])
    ev = fast.make_evaluator(kernel, c, w, eps=1e-6)
    vals, grads = ev(targets, True)
    ref_v, ref_g = kernel_sum(kernel, c, w, targets, gradient=True)
    assert np.linalg.norm(vals - ref_v) / np.linalg.norm(ref_v) < 1e-6
    assert np.linalg.norm(grads - ref_g) / np.linalg.norm(ref_g) < 1e-5
    # targets on centres: the self term phi(0) is included.  Pointwise to eps of
    # max |f| (the grid backend spreads its error evenly; fmm3dpy gave ~eps / 30).
    np.testing.assert_allclose(vals[m : m + 20], ref_v[m : m + 20], rtol=1e-5, atol=1e-6 * np.abs(ref_v).max())
    np.testing.assert_allclose(ev(targets[:300], False), ref_v[:300], rtol=1e-5, atol=1e-6 * np.abs(ref_v).max())


def test_an_evaluator_shares_another_evaluators_grid_sums_over_a_superset_of_its_centres(problem3k):
    """``make_evaluator(shared=(ev, index))``: a refit's centres (some of the first fit's left out) and weights are
    evaluated by the first evaluator's grid sums (no new one), f and grad f as direct sums of the refit's own
    centres give them; the first evaluator is unchanged.  Centres not at ``index``, or another ``eps``: new sums."""
    kernel = KERNELS["multiorder-10"]
    c = problem3k[0]
    w = np.random.default_rng(9).normal(size=len(c))
    first = fast.make_evaluator(kernel, c, w, eps=1e-6)
    keep = np.ones(len(c), bool)
    keep[::5] = False
    index = np.flatnonzero(keep)
    w2 = np.random.default_rng(19).normal(size=len(index))
    ev = fast.make_evaluator(kernel, c[keep], w2, eps=1e-6, shared=(first, index))
    assert ev.fast_sum is first.fast_sum and ev.weights.shape == (len(c),) and (ev.weights[~keep] == 0).all()
    targets = np.random.default_rng(10).uniform(-1.1, 1.1, (1500, 3))
    vals, grads = ev(targets, True)
    ref_v, ref_g = kernel_sum(kernel, c[keep], w2, targets, gradient=True)
    assert np.linalg.norm(vals - ref_v) / np.linalg.norm(ref_v) < 1e-6
    assert np.linalg.norm(grads - ref_g) / np.linalg.norm(ref_g) < 1e-5
    first_v = kernel_sum(kernel, c, w, targets)
    assert np.linalg.norm(first(targets) - first_v) / np.linalg.norm(first_v) < 1e-6
    for other in (fast.make_evaluator(kernel, c[keep], w2, eps=1e-6, shared=(first, index[::-1])),
                  fast.make_evaluator(kernel, c[keep], w2, eps=1e-5, shared=(first, index))):
        assert other.fast_sum is not first.fast_sum and other.weights.shape == (len(index),)
        assert np.linalg.norm(other(targets) - ref_v) / np.linalg.norm(ref_v) < 1e-5


def test_evaluator_chunks_and_thinplate_direct(problem3k):
    c = problem3k[0][:500]
    w = np.random.default_rng(11).normal(size=len(c))
    targets = np.random.default_rng(12).uniform(-1, 1, (1000, 3))
    ev = fast.make_evaluator(MultiOrder(10.0, 0.01), c, w, eps=1e-8, chunk=400)
    ref = kernel_sum(MultiOrder(10.0, 0.01), c, w, targets)
    assert np.linalg.norm(ev(targets) - ref) / np.linalg.norm(ref) < 1e-7
    tp = fast.make_evaluator(ThinPlate(), c, w)
    np.testing.assert_allclose(tp(targets), kernel_sum(ThinPlate(), c, w, targets), rtol=1e-12)


# -- solve --------------------------------------------------------------------------------
def _agreement(kernel, n, rtol, seed=2, backend="auto"):
    c, y, lam = torus_problem(n, seed=seed)
    dense = solve(kernel, c, y, lam, method="dense")
    sol = fast.solve(kernel, c, y, lam, rtol=rtol, preconditioner={"exact_below": 0}, backend=backend)
    assert sol.method == "fast" and sol.residual <= rtol and sol.info["converged"]
    assert sol.info["preconditioner"]["coarse"] < 0.2 * len(c)
    assert sol.info["constraint"] < 1e-12  # Q^T w = 0 exactly (constraint preconditioner)
    x = np.random.default_rng(3).uniform(-1, 1, (10000, 3))
    f_dense = kernel_sum(kernel, c, dense.weights, x) + dense.poly[0]
    f_fast = kernel_sum(kernel, c, sol.weights, x) + sol.poly[0]
    err = np.abs(f_fast - f_dense).max() / np.abs(f_dense).max()
    assert err < 1e-6, f"max relative difference {err:.1e}"
    return sol


@pytest.mark.parametrize("name,n,rtol", [("multiorder-10", 3300, 1e-8), ("multiorder-complex", 1600, 1e-9)])
def test_fast_solve_matches_dense(name, n, rtol):
    """f at 10,000 test points agrees with the dense (Cholesky) fit to 1e-6 relative,
    with the two-level preconditioner forced on (coarse N/8).  The residual-to-f
    amplification is ~100 for delta 10 and ~200 for the complex case (measured:
    rtol 1e-8 gave 1.9e-6 there), hence its tighter rtol."""
    _agreement(KERNELS[name], n, rtol)


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("O3DRBF_SLOW") != "1", reason="N = 8,000 proof of issue 4 (~1-2 min): set O3DRBF_SLOW=1")
@pytest.mark.parametrize("backend", ["fmm", "grid"])
def test_fast_solve_matches_dense_8k(backend):
    """Issue 4's proof: at N = 8,000 the fast f matches the dense one to 1e-6 at 10,000 points
    (grid measured: 4.9e-7 in 11 s, dense 50 s)."""
    sol = _agreement(KERNELS["multiorder-10"], 8000, 1e-8, backend=backend)
    assert (sol.info["split"].get("split") == "grid") == (backend == "grid")


def test_solve_entry_point_and_gaussian():
    kernel = Gaussian(0.08)
    c, y, lam = torus_problem(2000, seed=4)
    sol = solve(kernel, c, y, lam, method="fast", rtol=1e-8, progress=True)
    dense = solve(kernel, c, y, lam, method="dense")
    assert sol.method == "fast" and sol.residual <= 1e-8
    np.testing.assert_allclose(sol.weights, dense.weights, rtol=0, atol=1e-5 * np.abs(dense.weights).max())


def test_unreachable_tolerance_warns_with_residual():
    c, y, lam = torus_problem(2000, seed=5)
    with pytest.warns(ConvergenceWarning, match=r"residual \d\.\d+e-\d+"):
        sol = fast.solve(MultiOrder(10.0, 0.01), c, y, lam, rtol=1e-10, max_iterations=2,
                         preconditioner={"exact_below": 0})
    assert sol.iterations == 2 and sol.residual > 1e-10 and not sol.info["converged"]


def test_thinplate_is_refused():
    with pytest.raises(ValueError, match="thinplate"):
        fast.solve(ThinPlate(), np.random.default_rng(0).uniform(-1, 1, (100, 3)), np.zeros(100), 0.0)


def test_memory_refused_up_front():
    c, y, lam = torus_problem(500)
    with pytest.raises(MemoryError, match="limit"):
        fast.solve(MultiOrder(), c, y, lam, memory_limit=10**6)


def test_iteration_count_nearly_flat():
    """FGMRES iterations to 1e-6 at N = 2,000 and 8,000, coarse level N/8.

    Measured (this preconditioner): 8-9 and 10.  Near-field alone gives 16 -> 28
    (x1.75), Jacobi 57 -> 85 (measurements.md): the two-level count must stay
    within x1.4 and below 15.  Dense products isolate the preconditioner from FMM
    error (the FMM products gave the same counts at 4k)."""
    kernel = MultiOrder(10.0, 0.01)
    counts = []
    for n in (2000, 8000):
        c, y, lam = torus_problem(n, seed=6)
        sol = fast.solve(kernel, c, y, lam, rtol=1e-6, operator=DenseSum(kernel, c),
                         preconditioner={"exact_below": 0, "max_coarse": n // 8})
        assert sol.info["converged"]
        counts.append(sol.iterations)
    assert max(counts) < 15, counts
    assert counts[1] <= 1.4 * counts[0], counts


def test_nested_coarse_level_restores_the_count():
    """A coarse level above ``max_coarse`` is solved by nested FGMRES steps preconditioned by
    the same scheme (here 6,000 -> 750 nested -> 93 nested -> 11 by Cholesky).  Truth: the dense
    solution, and the count of an exact Cholesky coarse level on the same N / 8 centres;
    capping the Cholesky level at 60 centres instead (ratio 100, as 600k centres
    with the 6,000 cap) needs markedly more iterations.  Measured: 12 / 29 / 12
    (one nested step instead of 8 fails this test)."""
    kernel = MultiOrder(10.0, 0.01)
    n = 6000
    c, y, lam = torus_problem(n, seed=7)
    op = DenseSum(kernel, c)
    counts = {}
    for name, pre in {"cholesky": {"max_coarse": n // 8, "nested": 0},
                      "capped": {"max_coarse": 60, "nested": 0, "post_coarse": False},
                      "nested": {"max_coarse": 60, "nested": 8, "nested_ratio": 8}}.items():
        sol = fast.solve(kernel, c, y, lam, rtol=1e-8, operator=op, max_iterations=100,
                         preconditioner={"exact_below": 0, **pre})
        counts[name] = sol.iterations
        assert sol.info["converged"], name
        if name == "nested":
            info = sol.info["preconditioner"]
            assert info["coarse_solve"].startswith("8 nested") and info["inner"]["coarse_solve"].startswith("8 nested")
            assert info["inner"]["inner"]["coarse_solve"] == "Cholesky" and info["inner"]["inner"]["coarse"] < 60
            ref = solve(kernel, c, y, lam, method="dense")
            x = np.random.default_rng(3).uniform(-1, 1, (2000, 3))
            f_ref = kernel_sum(kernel, c, ref.weights, x) + ref.poly[0]
            f = kernel_sum(kernel, c, sol.weights, x) + sol.poly[0]
            assert np.abs(f - f_ref).max() < 1e-6 * np.abs(f_ref).max()
    assert counts["nested"] <= counts["cholesky"] + 2, counts
    assert counts["capped"] >= counts["nested"] + 3, counts


# -- grid (particle-mesh) backend -----------------------------------------------------------
GRID_KERNELS = ["multiorder-10", "multiorder-3.16", "multiorder-complex"]


@pytest.mark.parametrize("name", GRID_KERNELS)
@pytest.mark.parametrize("eps", [1e-3, 1e-7])
def test_grid_product_matches_dense(problem3k, dense3k, name, eps):
    """Gaussian-split grid + sparse near part against the dense matrix, all three regimes."""
    kernel = KERNELS[name]
    c = problem3k[0]
    w = np.random.default_rng(7).normal(size=len(c))
    ref = dense3k(name) @ w
    g = fast.GridSum(kernel, c, eps=eps)
    err = np.linalg.norm(g.matvec(w) - ref) / np.linalg.norm(ref)
    assert err < eps, f"{name}: relative error {err:.1e} at eps {eps:g}"
    assert err > 1e-3 * eps  # really an approximation (not silently a dense product)


def test_grid_looser_products_and_subset(problem3k, dense3k):
    """Products asked at 1e-3 come from a looser (cheaper) companion and stay within 1e-3;
    the coarse-to-fine update Phi[:, C] z_C is right at both accuracies."""
    kernel = KERNELS["multiorder-10"]
    c = problem3k[0]
    a = dense3k("multiorder-10")
    g = fast.GridSum(kernel, c, eps=1e-7)
    w = np.random.default_rng(8).normal(size=len(c))
    ref = a @ w
    tight = np.linalg.norm(g.matvec(w) - ref) / np.linalg.norm(ref)
    loose = np.linalg.norm(g.matvec(w, eps=1e-3) - ref) / np.linalg.norm(ref)
    assert tight < 1e-7 and 10 * tight < loose < 1e-3, (tight, loose)
    assert g._tiers[1e-3].mesh.shape < g.mesh.shape
    subset = np.random.default_rng(13).choice(len(c), 300, replace=False)  # unsorted on purpose
    z = np.random.default_rng(14).normal(size=300)
    ref = a[:, subset] @ z
    apply = g.from_subset(subset)
    assert np.linalg.norm(apply(z) - ref) / np.linalg.norm(ref) < 1e-7
    assert np.linalg.norm(apply(z, 1e-2) - ref) / np.linalg.norm(ref) < 1e-2


def test_sums_at_fixed_targets_and_a_small_subsets_own_grid(problem3k, dense3k):
    """``GridSum.at``: the sum at fixed targets, inside the grid and far beyond it (summed directly), is the
    direct sum's to the tolerance.  The coarse-to-fine update from a tenth of the centres sums them on a grid of
    their own, coarser than the centres' companion at the same tolerance, and matches the dense product."""
    kernel = KERNELS["multiorder-10"]
    c = problem3k[0]
    g = fast.GridSum(kernel, c, eps=1e-6)
    w = np.random.default_rng(31).normal(size=len(c))
    t = np.vstack([np.random.default_rng(32).uniform(-1, 1, (500, 3)), [[5.0, 5.0, 5.0], [-6.0, 0.0, 2.0]]])
    ref = kernel_sum(kernel, c, w, t)
    at = g.at(t)
    got = at(w)
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 1e-6
    np.testing.assert_allclose(got[-2:], ref[-2:], rtol=1e-12)  # the far ones: the direct sum
    np.testing.assert_array_equal(at(w), got)
    subset = np.random.default_rng(33).choice(len(c), len(c) // 10, replace=False)
    z = np.random.default_rng(34).normal(size=len(subset))
    dense = dense3k("multiorder-10")[:, subset] @ z
    apply = g.from_subset(subset)
    for e, tol in ((1e-2, 1e-2), (None, 1e-6)):
        assert np.linalg.norm(apply(z, e) - dense) / np.linalg.norm(dense) < tol
    own = apply.sums[1e-2].operator
    assert own.n == len(subset) and all(a < b for a, b in zip(own.mesh.shape, g._tier(1e-2).mesh.shape))


@pytest.mark.parametrize("eps", [1e-3, 1e-7])
def test_near_field_summed_on_the_fly_matches_the_stored_matrix_and_dense(problem3k, dense3k, eps):
    """A grid sum whose near field is summed on the fly (no stored matrix, as at a million
    centres) gives the stored-matrix product to the rounding of its stored entries (single precision,
    each rounded once: 1e-8 of the product), and so the dense one to eps; its looser companions and its
    coarse-to-fine update Phi[:, C] z_C too (with far centres summed directly)."""
    kernel = KERNELS["multiorder-10"]
    c = np.vstack([problem3k[0], [[4.0, 4.0, 4.0], [-4.0, 3.0, 1.0]]])  # two far centres (outside the grid)
    a = np.vstack([np.column_stack([dense3k("multiorder-10"), kernel_matrix(kernel, problem3k[0], c[-2:])]),
                   kernel_matrix(kernel, c[-2:], c)])
    stored, fly = fast.GridSum(kernel, c, eps=eps, store=True), fast.GridSum(kernel, c, eps=eps, store=False)
    assert fly.store is False and fly.info["near_field"] == "summed on the fly" and len(fly.outside) == 2
    w = np.random.default_rng(21).normal(size=len(c))
    ref = a @ w
    for e in (None, 1e-3):
        got, want = fly.matvec(w, eps=e), stored.matvec(w, eps=e)
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-8
        assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < max(eps, e or 0)
    assert fly._near_m is None and all(t._near_m is None for t in fly.__dict__.get("_tiers", {}).values())
    subset = np.r_[np.random.default_rng(22).choice(len(c) - 2, 300, replace=False), len(c) - 1]
    z = np.random.default_rng(23).normal(size=len(subset))
    ref = a[:, subset] @ z
    for e in (None, 1e-2):
        got, want = fly.from_subset(subset)(z, e), stored.from_subset(subset)(z, e)
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-8
        assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < max(eps, e or 0)


def test_the_stored_near_field_is_single_precision_each_entry_rounded_once(problem3k):
    """The products' stored near field (and its looser companions', restricted from it) keeps float32
    entries: each the double-precision table value rounded once, on the same pattern (two thirds of
    the memory, and of the bytes each product reads)."""
    kernel = KERNELS["multiorder-10"]
    g = fast.GridSum(kernel, problem3k[0], eps=1e-6, store=True)
    near = g.near
    double = g.cells.matrix(g._cc, g.tab, g.dr)  # the same entries, kept in double
    assert near.dtype == np.float32 and double.dtype == np.float64
    np.testing.assert_array_equal(near.indptr, double.indptr)
    np.testing.assert_array_equal(near.indices, double.indices)
    np.testing.assert_array_equal(near.data, double.data.astype(np.float32))
    tier = g._tier(1e-3)
    assert tier._near_parent is g and tier.near.dtype == np.float32 and tier.near.nnz < near.nnz


@pytest.mark.parametrize("store", [True, False])
@pytest.mark.parametrize("block", [True, False])
def test_rows_of_a_product_at_some_centres(problem3k, dense3k, store, block, monkeypatch):
    """``GridSum.rows``: a product's rows at a subset of the centres, far ones (outside the grid) among them,
    are the full product's rows to rounding (the product's stored near field: single precision, 1e-8 of
    the product) and the dense rows to the tolerance, at the operator's accuracy
    and at a looser companion's; the far centres are summed as the product sums them (never by a grid
    enlarged to reach them), with their stored block or without it."""
    import o3drbf.solvers.fast.grid as grid_module

    monkeypatch.setattr(grid_module, "DIRECT_PAIRS", 0)  # a far target summed by :meth:`at` would enlarge the grid
    kernel = KERNELS["multiorder-10"]
    c = np.vstack([problem3k[0], [[4.0, 4.0, 4.0], [-4.0, 3.0, 1.0]]])
    a = np.vstack([np.column_stack([dense3k("multiorder-10"), kernel_matrix(kernel, problem3k[0], c[-2:])]),
                   kernel_matrix(kernel, c[-2:], c)])
    g = fast.GridSum(kernel, c, eps=1e-6, store=store)
    g.OUTSIDE_BLOCK_BYTES = None if block else 0
    assert len(g.outside) == 2 and (g._outside_block() is not None) is block
    subset = np.r_[len(c) - 1, np.random.default_rng(41).choice(len(c) - 2, 400, replace=False), len(c) - 2]
    w = np.random.default_rng(42).normal(size=len(c))
    ref = a[subset] @ w
    for e, tol in ((None, 1e-6), (1e-3, 1e-3), (1e-2, 1e-2)):
        shape = g._tier(e).mesh.shape
        got = g.rows(subset, eps=e)(w)
        assert g._tier(e).mesh.shape == shape
        np.testing.assert_allclose(got, g.matvec(w, eps=e)[subset], rtol=0, atol=(1e-8 if store else 1e-12) * np.abs(ref).max())
        assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < tol
        np.testing.assert_allclose(got[[0, -1]], ref[[0, -1]], rtol=1e-12)  # the far ones


def test_grid_duplicates_and_targets_outside_the_centres_box():
    rng = np.random.default_rng(17)
    c = np.vstack([rng.uniform(-0.5, 0.5, (400, 3)), np.zeros((2, 3))])
    kernel = MultiOrder(10.0, 0.01)
    w = rng.normal(size=len(c))
    g = fast.GridSum(kernel, c, eps=1e-6)
    ref = kernel_matrix(kernel, c) @ w
    assert np.linalg.norm(g.matvec(w) - ref) / np.linalg.norm(ref) < 1e-6
    far = rng.uniform(-1.5, 1.5, (500, 3))  # outside the centres' grid: a larger one is built
    vals = g.evaluate(w, far)
    ref = kernel_sum(kernel, c, w, far)
    assert np.linalg.norm(vals - ref) / np.linalg.norm(ref) < 1e-6


def test_operator_choice():
    c = torus_problem(1000)[0]
    assert isinstance(fast.fast_operator(MultiOrder(10.0, 0.01), c, eps=1e-7), fast.GridSum)
    assert isinstance(fast.fast_operator(MultiOrder(10.0, 0.01), c, eps=1e-10), fast.FastSum)
    assert isinstance(fast.fast_operator(MultiOrder(10.0, 0.01), c, eps=1e-7, backend="fmm"), fast.FastSum)
    assert isinstance(fast.fast_operator(Gaussian(0.05), c, eps=1e-6), fast.FastSum)
    with pytest.raises(ValueError, match="backend"):
        fast.fast_operator(MultiOrder(), c, backend="gpu")
    with pytest.raises(ValueError, match="multi-order"):
        fast.GridSum(Gaussian(0.05), c)
    with pytest.raises(MemoryError, match="grid"):
        fast.GridSum(MultiOrder(10.0, 0.01), c, budget=10**5)


def test_grid_solve_matches_dense():
    """fast.solve on grid products (relaxed to the looser companions as the residual
    falls) agrees with the dense fit: f at 10,000 points to 1e-5 relative at rtol 1e-7."""
    kernel = KERNELS["multiorder-10"]
    c, y, lam = torus_problem(3300, seed=2)
    dense = solve(kernel, c, y, lam, method="dense")
    sol = fast.solve(kernel, c, y, lam, rtol=1e-7, preconditioner={"exact_below": 0}, backend="grid")
    assert sol.info["split"]["split"] == "grid" and sol.residual <= 1e-7
    x = np.random.default_rng(3).uniform(-1, 1, (10000, 3))
    f_dense = kernel_sum(kernel, c, dense.weights, x) + dense.poly[0]
    f_fast = kernel_sum(kernel, c, sol.weights, x) + sol.poly[0]
    err = np.abs(f_fast - f_dense).max() / np.abs(f_dense).max()
    assert err < 1e-5, f"max relative difference {err:.1e}"


def test_mesh_tolerance_moves_the_surface_by_about_the_asked_fraction_of_a_cell():
    # a fast solve stopped at mesh_tolerance against the dense solve of the same system (independent truth)
    from o3drbf.rbf.sums import polynomial_basis
    from o3drbf.solvers import solve

    n = 8000
    rng = np.random.default_rng(3)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = np.arange(n) < n - n // 10
    x = d * np.where(surface, 0.7, 0.8)[:, None]
    y = np.where(surface, 0.0, 0.1)  # signed distance: |grad f| ~ 1
    lam = np.where(surface, 1e-5, 2.0)
    kernel = MultiOrder(10, 0.01)
    cell = 2.0 / 512  # (below the tolerance's cap)
    rtol = fast.mesh_tolerance(y, cell)
    assert rtol == pytest.approx(fast.MESH_SHIFT * cell * np.sqrt(n) / np.linalg.norm(y))
    assert rtol > 10 * fast.SOLVE_RTOL  # looser than a solve to the default tolerance
    loose = fast.solve(kernel, x, y, lam, rtol=rtol)
    exact = solve(kernel, x, y, lam, method="dense")
    q = polynomial_basis(x, kernel.polynomial_degree)
    f_loose = kernel_sum(kernel, x, loose.weights, x) + q @ loose.poly
    f_exact = kernel_sum(kernel, x, exact.weights, x) + q @ exact.poly
    shift = np.sqrt(np.mean((f_loose - f_exact)[surface] ** 2)) / cell  # |grad f| ~ 1: a value error is a shift
    print(f"rtol {rtol:.2e}: {loose.iterations} iterations, rms shift {shift:.2e} cells")
    assert fast.MESH_SHIFT / 20 <= shift <= 2 * fast.MESH_SHIFT  # about the fraction asked (0.64 of it when written)
    assert fast.mesh_tolerance(np.zeros(10), cell) == fast.SOLVE_RTOL
    assert fast.mesh_tolerance(y, 1e3) == fast.RELAX_CAP


@pytest.mark.slow
def test_relaxed_products_leave_no_gap_between_the_recurrence_and_the_true_residual():
    """The relaxed products' errors add up in a cycle's true residual: where the recurrence reaches rtol the
    true residual must be there too, not above it (FGMRES would restart and take more steps).  Truth: the
    true residual the solve reports, computed at full accuracy.  At 20,000 centres with products relaxed
    as ``eps ||r_0|| / ||r_j||`` (scale 1) the recurrence reached 9.2e-7 at step 27, the true residual
    was above 1e-6, and a restart took 3 more steps."""
    from o3drbf.solvers.fast import tolerance

    assert tolerance.relax_scale(20_000) < 1 == tolerance.relax_scale(10_000)  # short cycles (the 10k scan) show no gap
    c, y, lam = torus_problem(20_000, seed=3)
    lam[: int(round(20_000 / 1.1))] = 1e-5
    order = fast.spatial_order(c)
    sol = fast.solve(MultiOrder(10.0, 0.005), c[order], y[order], lam[order], rtol=1e-6)
    history = np.array(sol.info["history"])
    assert sol.info["converged"] and sol.residual <= 1e-6
    assert not (history[:-1] <= 1e-6).any(), f"the recurrence reached rtol at step {np.argmax(history <= 1e-6) + 1} of {len(history)}"


def test_coarse_level_grows_with_n_up_to_what_cholesky_takes():
    """The coarse level: every centre up to exact_below, N/8 capped at max(6,000, N/20) and 16,000 (a Cholesky;
    a max_coarse above COARSE_MAX is refused), nested only when asked."""
    from o3drbf.solvers.fast.precondition import COARSE_MAX, TwoLevel, TwoLevelSettings, coarse_size

    st = TwoLevelSettings()
    assert coarse_size(2_500, st) == (2_500, 0)  # exact
    assert coarse_size(40_000, st) == (5_000, 0)  # N / 8
    assert coarse_size(111_339, st) == (6_000, 0)  # the cap's floor (N / 20 = 5,566)
    assert coarse_size(200_000, st) == (200_000 // 20, 0)
    assert coarse_size(333_206, st) == (16_000, 0)
    assert coarse_size(1_000_000, st) == (16_000, 0) and st.max_coarse <= COARSE_MAX
    assert coarse_size(333_206, TwoLevelSettings(max_coarse=6000, nested=8)) == (41_650, 8)  # the nested level, asked for
    c, _, lam = torus_problem(500, seed=1)
    with pytest.raises(ValueError, match="max_coarse"):
        TwoLevel(fast.fast_operator(MultiOrder(10.0, 0.01), c, eps=1e-4), lam, max_coarse=COARSE_MAX + 1)


def test_coarse_centres_do_not_depend_on_the_order():
    """The two-level preconditioner's coarse centres: about the count asked for, one a voxel (the point nearest
    its centre), the same points whatever order the centres come in (the fast solve reorders them in space)."""
    from o3drbf.solvers.fast.precondition import _uniform_subset

    p, _ = Torus().sample(20_000, seed=7)
    idx = _uniform_subset(p, 2000)
    assert abs(len(idx) - 2000) <= 100 and np.array_equal(idx, np.unique(idx))
    for seed in (0, 1):
        perm = np.random.default_rng(seed).permutation(len(p))
        assert np.array_equal(np.sort(perm[_uniform_subset(p[perm], 2000)]), idx)
    # nearest their voxels' centres, not the voxels' first points: no close pairs across voxel walls (the
    # 5 % quantile of the gap to the nearest other coarse centre is 0.63 of the median; 0.40 for first points)
    gaps = cKDTree(p[idx]).query(p[idx], k=2)[0][:, 1]
    assert np.quantile(gaps, 0.05) > 0.55 * np.median(gaps)


def test_a_long_solve_is_not_cut_by_an_early_restart():
    """A weakly preconditioned system that needs more than 50 FGMRES iterations: the default cycle
    (fgmres.RESTART, 100) keeps its Krylov space and converges in fewer iterations than cycles of 50
    (57 against 68 when written, 61 against 66 with the local radius from a sample of 1,000 centres; with
    the default at 50 the two would be the same), to the dense solution."""
    kernel = MultiOrder(10.0, 0.01)
    c, y, lam = torus_problem(4000, seed=3)
    op = DenseSum(kernel, c)
    pre = {"exact_below": 0, "max_coarse": 40, "cap_floor": 40, "inner": 2, "post_coarse": False}
    runs = {r: fast.solve(kernel, c, y, lam, rtol=1e-9, operator=op, max_iterations=300, preconditioner=pre,
                          **({} if r is None else {"restart": r})) for r in (None, 50)}
    assert all(s.info["converged"] for s in runs.values())
    assert 50 < runs[None].iterations < runs[50].iterations, {r: s.iterations for r, s in runs.items()}
    ref = solve(kernel, c, y, lam, method="dense")
    x = np.random.default_rng(4).uniform(-1, 1, (2000, 3))
    f_ref = kernel_sum(kernel, c, ref.weights, x) + ref.poly[0]
    f = kernel_sum(kernel, c, runs[None].weights, x) + runs[None].poly[0]
    assert np.abs(f - f_ref).max() < 1e-6 * np.abs(f_ref).max()


def test_the_second_coarse_correction_leaves_no_residual_at_the_coarse_centres():
    """With a capped coarse level the preconditioner corrects the coarse weights again after the local
    step, from the residual left at the coarse centres: with exact products (a dense stand-in) that
    residual is then zero (up to the rounding of the Cholesky factor, kept in single precision), which the one-sided scheme leaves
    large.  The solve with it reaches the dense solution.  A coarse level that is not capped takes the
    second correction from its stored coarse-to-fine block, and none without one.  (What it saves, fewer iterations at the mesh tolerance from about 30,000
    centres, is measured by benchmarks/fast_system.py: benchmarks/recorded/fast_solver.md, sessions 22-23.)"""
    from o3drbf.solvers.fast.precondition import TwoLevel

    kernel = MultiOrder(10.0, 0.01)
    c, y, lam = torus_problem(4000, seed=5)
    op = DenseSum(kernel, c)
    r = np.random.default_rng(6).standard_normal(len(c))
    pre = {"exact_below": 0, "max_coarse": 100, "cap_floor": 100}
    left = {}
    for post in (True, False):
        p = TwoLevel(op, lam, post_coarse=post, **pre)
        assert p.info["post_coarse"] is post
        z = p(r)
        left[post] = np.linalg.norm((r - op.matrix @ z - lam * z)[p.coarse]) / np.linalg.norm(r[p.coarse])
    assert left[True] < 1e-4 and left[False] > 1e-2, left
    # Not capped: the correction takes the coarse rows from the stored coarse-to-fine block, with the same effect;
    # with neither a cap nor a stored block, no second correction.
    uncapped = {"exact_below": 0, "max_coarse": len(c) // 8}
    p = TwoLevel(op, lam, **uncapped)
    assert p.info["post_coarse"] and p.info["coarse_update"] == "dense block"
    z = p(r)
    assert np.linalg.norm((r - op.matrix @ z - lam * z)[p.coarse]) < 1e-4 * np.linalg.norm(r[p.coarse])
    assert TwoLevel(op, lam, dense_budget=0, **uncapped).info["post_coarse"] is False
    sol = fast.solve(kernel, c, y, lam, rtol=1e-9, operator=op, max_iterations=300, preconditioner=pre)
    assert sol.info["converged"] and sol.info["preconditioner"]["post_coarse"]
    ref = solve(kernel, c, y, lam, method="dense")
    x = np.random.default_rng(4).uniform(-1, 1, (2000, 3))
    f_ref = kernel_sum(kernel, c, ref.weights, x) + ref.poly[0]
    f = kernel_sum(kernel, c, sol.weights, x) + sol.poly[0]
    assert np.abs(f - f_ref).max() < 1e-6 * np.abs(f_ref).max()


def test_the_local_step_is_damped_more_where_the_kernel_is_flat_over_the_near_radius():
    """Between two coarse corrections, a local step damped by 2 over-corrects where the kernel is flat over the
    near radius (phi(R) / phi(0) near 0.9, as at a million centres): the solve stalls.  Damped by
    ``post_damping / (1 - phi(R) / phi(0))`` it converges to the dense solution."""
    from o3drbf.solvers.fast.precondition import TwoLevelSettings

    kernel = MultiOrder(2.0, 0.05)
    c, y, lam = torus_problem(4000, seed=5)
    op = DenseSum(kernel, c)
    pre = {"exact_below": 0, "max_coarse": 100, "cap_floor": 100}
    with pytest.warns(ConvergenceWarning):
        stalled = fast.solve(kernel, c, y, lam, rtol=1e-9, operator=op, max_iterations=100,
                             preconditioner={**pre, "post_damping": 0.0})
    assert stalled.info["preconditioner"]["damping"] == 2.0 and not stalled.info["converged"]
    sol = fast.solve(kernel, c, y, lam, rtol=1e-9, operator=op, max_iterations=100, preconditioner=pre)
    info = sol.info["preconditioner"]
    flat = float(kernel(np.array([info["near_radius"]]))[0]) / kernel.value_at_zero
    assert flat > 0.85 and info["post_coarse"]
    assert info["damping"] == pytest.approx(TwoLevelSettings().post_damping / (1 - flat), rel=1e-12)
    assert sol.info["converged"] and sol.iterations < 60, sol.iterations
    ref = solve(kernel, c, y, lam, method="dense")
    x = np.random.default_rng(4).uniform(-1, 1, (2000, 3))
    f_ref = kernel_sum(kernel, c, ref.weights, x) + ref.poly[0]
    f = kernel_sum(kernel, c, sol.weights, x) + sol.poly[0]
    assert np.abs(f - f_ref).max() < 1e-6 * np.abs(f_ref).max()


def test_the_coarse_level_factors_the_full_coarse_matrix_from_its_lower_triangle():
    """The coarse matrix is evaluated on its lower triangle only (all a lower Cholesky factorization reads):
    the factor equals that of the full matrix Phi_CC + Lambda_C, at the start and after new smoothing."""
    import scipy.linalg as sla

    from o3drbf.rbf.sums import kernel_matrix
    from o3drbf.solvers.fast.precondition import TwoLevel

    kernel = MultiOrder(10.0, 0.01)
    c, y, lam = torus_problem(4000, seed=7)
    p = TwoLevel(DenseSum(kernel, c), lam, exact_below=0, max_coarse=300, cap_floor=300)
    lam2 = lam.copy()
    lam2[p.coarse[:5]] *= 10.0
    for step in (0, 1):
        if step:
            p.set_smoothing(lam2)
        xc = c[p.coarse]
        full = kernel_matrix(kernel, xc) + np.diag((lam, lam2)[step][p.coarse])
        want = np.tril(sla.cho_factor(full, lower=True)[0])
        assert p.factor.dtype == np.float32  # kept in single precision (COARSE_SINGLE)
        np.testing.assert_allclose(np.tril(p.factor), want, rtol=0, atol=1e-6 * np.abs(want).max())


def test_a_coarse_matrix_single_precision_cannot_factor_is_factored_in_double():
    """The Hilbert matrix of order 10 (condition 1.6e13) breaks single precision's Cholesky factorization
    down (LAPACK's spotrf fails), not double's: the coarse factor then comes from the double one, kept in
    single precision, and still factors the matrix to that precision."""
    import scipy.linalg as sla

    from o3drbf.solvers.fast import precondition

    h = sla.hilbert(10)
    assert sla.lapack.spotrf(np.asfortranarray(h.astype(np.float32)), lower=1)[1] != 0
    c = precondition.coarse_factor(np.asfortranarray(h.copy()))
    low = np.tril(c).astype(float)
    assert c.dtype == np.float32 and np.abs(low @ low.T - h).max() < 1e-6


def test_the_coarse_factor_of_the_kernel_is_that_of_its_double_matrix(monkeypatch):
    """coarse_matrix_factor evaluates the coarse matrix straight into single precision: the factor is the
    one coarse_factor makes of the double matrix, bit for bit.  Where single precision's factorization
    breaks down, the double matrix is made and factored in double (as coarse_factor does)."""
    import scipy.linalg as sla

    from o3drbf.rbf.sums import kernel_matrix
    from o3drbf.solvers.fast import precondition

    kernel = MultiOrder(10.0, 0.01)
    c, _, lam = torus_problem(900, seed=4)
    a = kernel_matrix(kernel, c) + np.diag(lam)
    got = precondition.coarse_matrix_factor(kernel, c, lam)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(np.tril(got), np.tril(precondition.coarse_factor(np.asfortranarray(a.copy()))))
    spotrf = sla.lapack.spotrf
    calls = []

    def failing(*args, **kwargs):  # single precision "breaks down" once: the double path takes over
        calls.append(1)
        out = spotrf(*args, **kwargs)
        return (out[0], 1) if len(calls) == 1 else out

    monkeypatch.setattr(sla.lapack, "spotrf", failing)
    fallback = precondition.coarse_matrix_factor(kernel, c, lam)
    assert len(calls) == 1 and fallback.dtype == np.float32  # not tried in single again
    want = np.tril(sla.cho_factor(a, lower=True)[0])
    np.testing.assert_allclose(np.tril(fallback), want, rtol=0, atol=1e-6 * np.abs(want).max())


def test_the_coarse_to_fine_block_is_stored_in_single_precision_and_updates_as_the_double_one():
    """The stored (N, |C|) block is float32 (half the bytes against the dense budget); its coarse-to-fine
    update agrees with the double matrix's product (NumPy kernel) to single precision."""
    from o3drbf.rbf.sums import kernel_matrix
    from o3drbf.solvers.fast.precondition import TwoLevel

    kernel = MultiOrder(10.0, 0.01)
    c, _, lam = torus_problem(4000, seed=5)
    p = TwoLevel(DenseSum(kernel, c), lam, exact_below=0, max_coarse=400, cap_floor=400)
    assert p.block is not None and p.block.dtype == np.float32 and p.info["coarse_update"] == "dense block"
    zc = np.random.default_rng(1).normal(size=len(p.coarse))
    want = kernel_matrix(kernel, c, c[p.coarse], compiled=False) @ zc
    want[p.coarse] += lam[p.coarse] * zc
    got = p._coarse_to_fine(zc)
    assert got.dtype == np.float64
    assert np.abs(got - want).max() <= 1e-5 * np.abs(want).max()
    small = TwoLevel(DenseSum(kernel, c), lam, exact_below=0, max_coarse=400, cap_floor=400, dense_budget=4 * 4000 * 400 - 1)
    assert small.block is None and small.info["coarse_update"] == "fast sum"


def test_the_coarse_factor_reads_only_the_lower_triangle():
    """What lies above the diagonal of the coarse matrix is never written (its pages never touched): the
    factor neither reads it nor warns about it, whatever it holds (here 1e300 and NaN)."""
    import warnings

    from o3drbf.rbf.sums import kernel_matrix
    from o3drbf.solvers.fast import precondition

    c, _, lam = torus_problem(700, seed=2)
    a = kernel_matrix(MultiOrder(10.0, 0.01), c) + np.diag(lam)
    want = precondition.coarse_factor(np.asfortranarray(a.copy()))
    dirty = np.asfortranarray(a.copy())
    upper = np.triu_indices(len(a), 1)
    dirty[upper] = np.where(upper[0] % 2, 1e300, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = precondition.coarse_factor(dirty)
    np.testing.assert_array_equal(np.tril(got), np.tril(want))


def test_the_coarse_solve_in_single_precision_matches_the_double_one():
    """The coarse factor, factored in double and kept in single precision, solves the coarse system to
    about single precision times the factor's condition; in double (``COARSE_SINGLE`` off) to rounding."""
    from o3drbf.rbf.sums import kernel_matrix
    from o3drbf.solvers.fast import precondition

    kernel = MultiOrder(10.0, 0.01)
    c, _, lam = torus_problem(1500, seed=3)
    a = kernel_matrix(kernel, c) + np.diag(lam)
    b = np.random.default_rng(0).normal(size=len(c))
    want = np.linalg.solve(a, b)
    single = precondition.coarse_factor(np.tril(a))
    x = precondition.coarse_solve(single, b)
    assert single.dtype == np.float32 and x.dtype == np.float64
    err = np.linalg.norm(x - want) / np.linalg.norm(want)
    assert 1e-9 < err < 1e-3  # single precision: far from exact, far below a preconditioner's needs
    precondition.COARSE_SINGLE = False
    try:
        double = precondition.coarse_factor(np.tril(a))
    finally:
        precondition.COARSE_SINGLE = True
    assert double.dtype == np.float64
    assert np.linalg.norm(precondition.coarse_solve(double, b) - want) / np.linalg.norm(want) < 1e-9
