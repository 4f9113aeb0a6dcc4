"""The same properties of the regularized fit, checked for every solver.

Each solver (dense Cholesky, GMRES, fast products + two-level FGMRES) must
satisfy the equations of method.md section 2 at the centres, reach the
analytic limits, be invariant where the equations are, and let per-point
smoothing discount an outlier.  The truths are the equations themselves
(f(c_i) = y_i - lambda_i w_i, Q^T w = 0), an independent least-squares fit
(numpy.linalg.lstsq) and the fit without the outlier.
"""

from __future__ import annotations

import numpy as np
import pytest

from o3drbf.rbf.kernels import MultiOrder, ThinPlate
from o3drbf.rbf.sums import kernel_sum, polynomial_basis
from o3drbf.solvers import fast, solve

MULTIORDER = MultiOrder(10.0, 0.01)

#: Tolerance of f at the centres, relative to max |y|.  The Krylov methods stop
#: at a relative residual (iterative 1e-12, fast 1e-10); f's error is about
#: 1-3x that at the centres (measured: fast 1.7e-10).
TOL = {"dense": 1e-9, "iterative": 1e-8, "fast": 1e-8}


def _fit(method: str, kernel, x, y, lam):
    if method == "fast":
        # exact_below=0: the real two-level preconditioner even at this small N
        # (by default it is an exact Cholesky below 3,000 centres).
        sol = fast.solve(kernel, x, y, lam, rtol=1e-10, max_iterations=400, preconditioner={"exact_below": 0})
        assert sol.method == "fast" and sol.iterations >= 1
        assert "FMM" in sol.info["split"]["split"] or sol.info["split"]["split"] == "grid"  # fast products
        assert sol.info["preconditioner"]["coarse"] < len(x)  # a coarse level, not an exact factor
        return sol
    sol = solve(kernel, x, y, lam, method=method, rtol=1e-12 if method == "iterative" else None, max_iterations=3000)
    assert sol.method == method
    assert (sol.iterations > 0) == (method == "iterative")
    return sol


@pytest.fixture(params=["dense", "iterative", "fast"])
def method(request):
    return request.param


def _problem(n: int = 300, seed: int = 7):
    """Surface samples (y = 0) on a sphere of radius 0.7 and exterior ones (y = -1) at 0.8."""
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    k = n - n // 10
    return np.vstack([0.7 * d[:k], 0.8 * d[k:]]), np.r_[np.zeros(k), -np.ones(n - k)]


def _f(kernel, sol, x, at):
    return kernel_sum(kernel, x, sol.weights, at) + polynomial_basis(at, kernel.polynomial_degree) @ sol.poly


def test_lambda_zero_interpolates(method):
    x, y = _problem()
    sol = _fit(method, MULTIORDER, x, y, np.zeros(len(x)))
    assert np.abs(_f(MULTIORDER, sol, x, x) - y).max() < TOL[method]


def test_per_point_smoothing_obeys_the_equations(method):
    """f(c_i) = y_i - lambda_i w_i (first block row) and Q^T w = 0 (second)."""
    x, y = _problem()
    lam = np.random.default_rng(1).uniform(0.0, 0.01, len(x))
    sol = _fit(method, MULTIORDER, x, y, lam)
    assert np.abs(_f(MULTIORDER, sol, x, x) - (y - lam * sol.weights)).max() < TOL[method]
    assert abs(sol.weights.sum()) < TOL[method]
    assert np.abs(lam * sol.weights).max() > 100 * TOL[method]  # the smoothing did relax the fit


@pytest.mark.parametrize("kernel", [MULTIORDER, ThinPlate()], ids=["multiorder", "thinplate"])
def test_large_lambda_tends_to_the_least_squares_polynomial(method, kernel):
    """As lambda -> inf, w = (y - Q p) / lambda + O(lambda^-2) and Q^T w = 0 make
    p the least-squares fit of y; f deviates from it by about |Phi r| / lambda
    (r the least-squares residual)."""
    if method == "fast" and isinstance(kernel, ThinPlate):
        pytest.skip("the fast solver supports the multi-order and Gaussian bases only (test_fast checks the refusal)")
    x, y = _problem()
    y = y + 0.3 * x[:, 0] - 0.2 * x[:, 2]  # a linear trend for the thin-plate's linear part to find
    lam = 1e6
    sol = _fit(method, kernel, x, y, np.full(len(x), lam))
    q = polynomial_basis(x, kernel.polynomial_degree)
    p_ls = np.linalg.lstsq(q, y, rcond=None)[0]
    probe = np.vstack([x, np.random.default_rng(2).uniform(-1, 1, (50, 3))])
    r = y - q @ p_ls
    bound = 1e-8 + 10 * np.abs(kernel_sum(kernel, x, r, probe)).max() / lam
    assert bound < 1e-3 * np.abs(r).max()  # the limit is reached, not just approached
    assert np.allclose(sol.poly, p_ls, rtol=0, atol=bound)
    f_ls = polynomial_basis(probe, kernel.polynomial_degree) @ p_ls
    assert np.abs(_f(kernel, sol, x, probe) - f_ls).max() < bound


def test_invariances(method):
    """Translating the centres leaves the weights (radial kernel, constant
    polynomial); adding c to y adds c to p and leaves w; scaling y scales w and p."""
    x, y = _problem()
    lam = np.where(y == 0, 1e-3, 0.1)
    base = _fit(method, MULTIORDER, x, y, lam)
    scale = np.abs(base.weights).max()
    moved = _fit(method, MULTIORDER, x + np.array([0.13, -0.21, 0.05]), y, lam)
    assert np.abs(moved.weights - base.weights).max() < 1e3 * TOL[method] * scale
    raised = _fit(method, MULTIORDER, x, y + 0.4, lam)
    assert np.abs(raised.weights - base.weights).max() < 1e3 * TOL[method] * scale
    assert abs(raised.poly[0] - (base.poly[0] + 0.4)) < 1e3 * TOL[method]
    scaled = _fit(method, MULTIORDER, x, 3.0 * y, lam)
    assert np.abs(scaled.weights - 3.0 * base.weights).max() < 3e3 * TOL[method] * scale
    assert abs(scaled.poly[0] - 3.0 * base.poly[0]) < 3e3 * TOL[method]


def test_per_point_smoothing_discounts_an_outlier(method):
    """A surface sample pushed out to radius 0.85: with lambda = 0 the fit
    passes through it; with a large lambda on it alone the fit is the fit
    without it (lambda -> inf removes the constraint), and f there obeys
    f = y - lambda w."""
    x, y = _problem()
    out = np.array([[0.0, 0.0, 0.85]])
    xo, yo = np.vstack([x, out]), np.r_[y, 0.0]
    without = _fit(method, MULTIORDER, x, y, np.zeros(len(x)))
    forced = _fit(method, MULTIORDER, xo, yo, np.zeros(len(xo)))
    lam = np.zeros(len(xo))
    lam[-1] = 1e4
    discounted = _fit(method, MULTIORDER, xo, yo, lam)
    f_without = float(_f(MULTIORDER, without, x, out)[0])
    f_forced = float(_f(MULTIORDER, forced, xo, out)[0])
    f_disc = float(_f(MULTIORDER, discounted, xo, out)[0])
    assert abs(f_forced) < TOL[method]  # interpolated: the outlier bends the surface through it
    assert abs(f_without) > 0.05  # the outlier is off the surface of the others
    assert abs(f_disc - f_without) < 1e-2 * abs(f_without)
    assert abs(f_disc - (0.0 - lam[-1] * discounted.weights[-1])) < 1e3 * TOL[method]
    probe = np.array([[0.0, 0.0, 0.7], [0.1, 0.0, 0.75], [0.0, 0.1, 0.8]])  # near the outlier
    err_disc = np.abs(_f(MULTIORDER, discounted, xo, probe) - _f(MULTIORDER, without, x, probe)).max()
    err_forced = np.abs(_f(MULTIORDER, forced, xo, probe) - _f(MULTIORDER, without, x, probe)).max()
    assert err_disc < 1e-2 * err_forced
