"""DenseFactor in mixed precision (single-precision Cholesky, refined in double) against double-precision truths."""

import numpy as np
import pytest

from o3drbf.rbf.compiled import direct_matrix, lower_matrix_single, lower_pair, lower_single
from o3drbf.rbf.kernels import MultiOrder
from o3drbf.rbf.sums import kernel_matrix, polynomial_basis
from o3drbf.solvers import dense
from o3drbf.solvers.dense import MIXED_MIN, DenseFactor

from test_solve import reference

KERNEL = MultiOrder(10, 0.01)


def problem(n=MIXED_MIN + 200, seed=0):
    """Points on two spheres (surface 0, exterior -1), smoothing as a fit has it."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    inner = np.arange(n) < n - n // 10
    x = d * np.where(inner, 0.7, 0.8)[:, None]
    y = np.where(inner, 0.0, -1.0)
    lam = np.where(inner, 4e-3 * KERNEL.value_at_zero, 2.0)
    return x, y, lam


def test_lower_single_is_the_lower_triangle_in_float32_and_its_norm():
    a = np.asfortranarray(np.random.default_rng(1).standard_normal((37, 37)))
    out, norm = lower_single(a)
    assert out.dtype == np.float32 and out.flags.f_contiguous
    np.testing.assert_array_equal(np.tril(out), np.tril(a).astype(np.float32))
    symmetric = np.tril(a) + np.tril(a, -1).T  # what the lower triangle stands for
    assert norm == pytest.approx(np.linalg.norm(symmetric), rel=1e-12)


def test_lower_pair_is_the_matrix_and_its_single_copy_bit_for_bit():
    x, _, lam = problem(300)
    a, single, norm = lower_pair(KERNEL, x, lam)
    two_pass = direct_matrix(KERNEL, x, x, lower=True)
    two_pass[np.diag_indices(len(x))] += lam
    single_two_pass, norm_two_pass = lower_single(two_pass)
    assert a.flags.f_contiguous and single.flags.f_contiguous and single.dtype == np.float32
    np.testing.assert_array_equal(np.tril(a), np.tril(two_pass))
    np.testing.assert_array_equal(np.tril(single), np.tril(single_two_pass))
    assert norm == norm_two_pass
    # and the numpy kernel: the lower triangle of Phi + diag(lambda)
    np.testing.assert_allclose(np.tril(a), np.tril(kernel_matrix(KERNEL, x, compiled=False) + np.diag(lam)), rtol=1e-12, atol=0)


def test_lower_matrix_single_is_the_rounded_lower_triangle_bit_for_bit():
    """Evaluated straight into float32: the same numbers as the double matrix (NumPy kernel, independent of
    the compiled loops) plus the diagonal, rounded once."""
    x, _, lam = problem(300)
    single = lower_matrix_single(KERNEL, x, lam)
    assert single.dtype == np.float32 and single.flags.f_contiguous
    np.testing.assert_array_equal(np.tril(single), np.tril(lower_pair(KERNEL, x, lam)[1]))
    numpy_double = kernel_matrix(KERNEL, x, compiled=False) + np.diag(lam)
    np.testing.assert_allclose(np.tril(single), np.tril(numpy_double), rtol=1e-7, atol=0)
    with pytest.raises(ValueError, match="diagonal must have shape"):
        lower_matrix_single(KERNEL, x, lam[:-1])
    with pytest.raises(ValueError, match="NaN or infinite"):
        lower_matrix_single(KERNEL, np.where(np.arange(300)[:, None] == 3, np.nan, x), lam)


def test_lower_pair_refuses_bad_input_in_one_line():
    x, _, lam = problem(20)
    with pytest.raises(ValueError, match="diagonal must have shape"):
        lower_pair(KERNEL, x, lam[:-1])
    with pytest.raises(ValueError, match="NaN or infinite"):
        lower_pair(KERNEL, x, np.where(np.arange(20) == 3, np.nan, lam))


def test_mixed_solve_matches_a_float64_numpy_solve():
    x, y, lam = problem()
    q = polynomial_basis(x, KERNEL.polynomial_degree)
    factor = DenseFactor(KERNEL, x, lam, q)
    assert factor.precision == "mixed" and factor.single.dtype == np.float32
    w, p, _ = factor.solve(y)
    w_ref, p_ref = reference(KERNEL, x, y, lam)
    # float32 alone is good to ~1e-4 here; the refined solve is as close as two double solves are
    np.testing.assert_allclose(w, w_ref, rtol=0, atol=1e-9 * np.abs(w_ref).max())
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-9 * max(np.abs(p_ref).max(), 1.0))
    assert factor.residual(y, lam, w, p) < 1e-12
    # the kept matrix's residual is the kernel's own: the same (w, p) in the numpy matrix
    a = kernel_matrix(KERNEL, x, compiled=False) + np.diag(lam)
    r = np.r_[a @ w + q @ p - y, q.T @ w]
    assert np.linalg.norm(r) / np.linalg.norm(y) == pytest.approx(factor.residual(y, lam, w, p), abs=1e-13)


def test_mixed_woodbury_update_matches_a_fresh_float64_solve():
    x, y, lam0 = problem()
    q = polynomial_basis(x, KERNEL.polynomial_degree)
    factor = DenseFactor(KERNEL, x, lam0, q, precision="mixed")
    lam = lam0.copy()
    lam[[3, 50, 51, 120]] *= [10.0, 1e3, 1e6, 2.5]
    lam[[7, 200]] = np.inf
    w, p, changed = factor.solve(y, lam)
    assert changed == 6 and factor.precision == "mixed"
    keep = np.isfinite(lam)
    w_ref, p_ref = reference(KERNEL, x[keep], y[keep], lam[keep])
    np.testing.assert_allclose(w[keep], w_ref, rtol=0, atol=1e-9 * np.abs(w_ref).max())
    assert (w[~keep] == 0).all()
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-9 * max(np.abs(p_ref).max(), 1.0))


def test_a_refinement_that_stalls_refactors_in_double(monkeypatch):
    x, y, lam = problem()
    q = polynomial_basis(x, KERNEL.polynomial_degree)
    factor = DenseFactor(KERNEL, x, lam, q, precision="mixed")
    monkeypatch.setattr(dense, "REFINE_RTOL", 0.0)  # unreachable: the refinement stops shrinking first
    w, p, _ = factor.solve(y)
    assert factor.precision == "double" and factor.single is None
    w_ref, _ = reference(KERNEL, x, y, lam)
    np.testing.assert_allclose(w, w_ref, rtol=0, atol=1e-9 * np.abs(w_ref).max())


def test_small_systems_stay_double():
    x, y, lam = problem(n=300)
    factor = DenseFactor(KERNEL, x, lam, polynomial_basis(x, KERNEL.polynomial_degree))
    assert factor.precision == "double"
    with pytest.raises(ValueError, match="precision must be"):
        DenseFactor(KERNEL, x, lam, polynomial_basis(x, 1), precision="half")
