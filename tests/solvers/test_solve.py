"""The regularized fit against an independent dense solve and analytic limits."""

import numpy as np
import pytest

from o3drbf.rbf.kernels import Gaussian, MultiOrder, ThinPlate
from o3drbf.solvers import ConvergenceWarning, solve
from o3drbf.rbf.sums import kernel_matrix, kernel_sum, polynomial_basis

KERNELS = [MultiOrder(10, 0.01), MultiOrder(40, 0.025), Gaussian(0.3), ThinPlate()]


def problem(rng, n=400):
    d = rng.standard_normal((n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = 0.7 * d[: n - n // 10]
    exterior = 0.8 * d[n - n // 10 :]
    x = np.vstack([surface, exterior])
    y = np.r_[np.zeros(len(surface)), -np.ones(len(exterior))]
    return x, y


def reference(kernel, x, y, lam):
    """Plain numpy.linalg.solve of the full saddle-point matrix (NumPy kernel path)."""
    n = len(x)
    q = polynomial_basis(x, kernel.polynomial_degree)
    m = q.shape[1]
    a = np.zeros((n + m, n + m))
    a[:n, :n] = kernel_matrix(kernel, x, compiled=False) + np.diag(lam)
    a[:n, n:] = q
    a[n:, :n] = q.T
    s = np.linalg.solve(a, np.r_[y, np.zeros(m)])
    return s[:n], s[n:]


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: repr(k))
def test_dense_matches_independent_solve(kernel, rng):
    x, y = problem(rng)
    lam = np.where(y == 0, 1e-3, 2.0)
    sol = solve(kernel, x, y, lam, method="dense")
    w, p = reference(kernel, x, y, lam)
    assert np.allclose(sol.weights, w, rtol=1e-6, atol=1e-8 * np.abs(w).max())
    assert np.allclose(sol.poly, p, rtol=1e-6, atol=1e-9)
    assert sol.residual < 1e-10


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: repr(k))
def test_lambda_zero_interpolates(kernel, rng):
    x, y = problem(rng, 300)
    sol = solve(kernel, x, y, 0.0, method="dense")
    f = kernel_sum(kernel, x, sol.weights, x) + polynomial_basis(x, kernel.polynomial_degree) @ sol.poly
    assert np.max(np.abs(f - y)) < 1e-8 * np.max(np.abs(y))


# f(c_i) = y_i - lambda_i w_i with per-point lambda and the large-lambda
# least-squares limit are checked for every solver in test_solver_properties.py.


def test_thinplate_reproduces_linear_functions(rng):
    x = rng.uniform(-1, 1, (200, 3))
    y = 0.3 + x @ np.array([1.0, -2.0, 0.5])
    sol = solve(ThinPlate(), x, y, 0.0, method="dense")
    assert np.allclose(sol.weights, 0, atol=1e-8)
    assert np.allclose(sol.poly, [0.3, 1.0, -2.0, 0.5], atol=1e-8)


@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), ThinPlate()], ids=repr)
def test_iterative_agrees_with_dense(kernel, rng):
    x, y = problem(rng, 500)
    lam = np.where(y == 0, 1e-3, 2.0)
    dense = solve(kernel, x, y, lam, method="dense")
    it = solve(kernel, x, y, lam, method="iterative", rtol=1e-12, max_iterations=3000)
    probe = rng.uniform(-1, 1, (200, 3))
    q = polynomial_basis(probe, kernel.polynomial_degree)
    fd = kernel_sum(kernel, x, dense.weights, probe) + q @ dense.poly
    fi = kernel_sum(kernel, x, it.weights, probe) + q @ it.poly
    assert it.iterations > 0 and it.method == "iterative"
    assert np.max(np.abs(fi - fd)) < 1e-6 * np.max(np.abs(fd))


def test_iterative_warns_when_it_cannot_converge(rng):
    x, y = problem(rng, 300)
    with pytest.warns(ConvergenceWarning, match="did not reach"):
        sol = solve(MultiOrder(10, 0.01), x, y, 0.0, method="iterative", rtol=1e-14, max_iterations=5)
    assert sol.residual > 1e-14


def test_dense_refuses_what_does_not_fit(rng):
    x, y = problem(rng, 200)
    with pytest.raises(MemoryError, match=r"needs about .* GB but the limit is .* method='fast'"):
        solve(MultiOrder(), x, y, 0.0, method="dense", memory_limit=1000)


def test_bad_input_errors(rng):
    x, y = problem(rng, 50)
    k = MultiOrder()
    with pytest.raises(ValueError, match=r"values must have shape \(50,\)"):
        solve(k, x, y[:-1])
    with pytest.raises(ValueError, match="NaN"):
        solve(k, x, np.r_[y[:-1], np.nan])
    with pytest.raises(ValueError, match="smoothing must be finite and >= 0"):
        solve(k, x, y, -np.ones(50))
    with pytest.raises(ValueError, match="method must be one of"):
        solve(k, x, y, method="magic")
    with pytest.raises(ValueError, match=r"centres must have shape \(N, 3\)"):
        solve(k, x[:, :2], y)
    with pytest.raises(ValueError, match="coplanar"):
        solve(ThinPlate(), np.c_[x[:, :2], np.zeros(50)], y)
    with pytest.raises(ValueError, match="at least 5 constraints"):
        solve(ThinPlate(), x[:4], y[:4])


def test_dense_blas_threads_follow_the_system_size_never_the_load(monkeypatch):
    from threadpoolctl import threadpool_info, threadpool_limits

    from o3drbf.solvers import base

    assert base.busy_machine(load=5.0, cores=2) and not base.busy_machine(load=2.4, cores=2)
    assert not base.busy_machine(load=9.0, cores=1)  # one core: nothing to give up

    def blas_threads():
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    small, large = base.DENSE_THREADS_MIN - 1, base.DENSE_THREADS_MIN
    with threadpool_limits(limits=2, user_api="blas"):
        monkeypatch.setattr(base.os, "cpu_count", lambda: 2)
        for load in (50.0, 0.1):
            monkeypatch.setattr(base.os, "getloadavg", lambda load=load: (load, load, load))
            with base.dense_blas_threads(small):
                assert blas_threads() == {1}
            assert blas_threads() == {2}
            with base.dense_blas_threads(large):
                assert blas_threads() == {2}


@pytest.mark.parametrize("n", [300, 2_100])
def test_dense_solve_is_the_same_to_the_bit_on_a_busy_and_an_idle_machine(monkeypatch, n):
    """A tiny reconstruction's mesh once moved by 4e-14 between runs in one process: the dense
    factorization took one BLAS thread or two as the load average crossed the cores."""
    from threadpoolctl import threadpool_limits

    from o3drbf.solvers import base

    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (n, 3))
    y = rng.standard_normal(n)
    answers = []
    with threadpool_limits(limits=2, user_api="blas"):
        monkeypatch.setattr(base.os, "cpu_count", lambda: 2)
        for load in (50.0, 0.1):
            monkeypatch.setattr(base.os, "getloadavg", lambda load=load: (load, load, load))
            sol = solve(MultiOrder(0.5, 0.01), x, y, smoothing=1e-3, method="dense")
            answers.append(np.concatenate([sol.weights, sol.poly]))
    assert np.array_equal(answers[0], answers[1])
