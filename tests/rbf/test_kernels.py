"""The basis functions against independent truths: closed-form limits,
the Fourier symbol (numerical Hankel transform), finite differences."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from o3drbf.rbf.kernels import KERNELS, Gaussian, MultiOrder, ThinPlate, make_kernel
from o3drbf.rbf.sums import kernel_matrix, kernel_sum

# (delta, tau): real, confluent (4 tau^2 delta^2 = 1), near-confluent, complex regimes
CASES = [(10.0, 0.01), (3.1623, 0.01), (5.0, 0.025), (20.0, 0.025), (40.0, 0.0125), (20.0, 0.0249999), (40.0, 0.025)]


@pytest.mark.parametrize("delta,tau", CASES)
def test_value_at_zero_matches_closed_form(delta, tau):
    k = MultiOrder(delta, tau)
    expected = 1.0 / (4 * math.pi * delta * math.sqrt(1 + 2 * delta * tau))
    r = np.array([0.0, 1e-12, 1e-9])
    assert np.allclose(k(r), expected, rtol=1e-12, atol=0)


@pytest.mark.parametrize("delta,tau", CASES)
def test_derivative_vanishes_at_zero_and_matches_finite_differences(delta, tau):
    k = MultiOrder(delta, tau)
    assert k.derivative(np.array([0.0]))[0] == 0.0
    assert abs(k.derivative(np.array([1e-9]))[0]) < 1e-9 * abs(k.derivative_over_r(np.array([0.0]))[0]) * 10
    r = np.array([0.003, 0.02, 0.3, 1.5])
    h = 1e-6
    fd = (k(r + h) - k(r - h)) / (2 * h)
    assert np.allclose(k.derivative(r), fd, rtol=1e-6, atol=0)


@pytest.mark.parametrize("delta,tau", CASES)
def test_regimes_and_continuity_across_the_taylor_switch(delta, tau):
    k = MultiOrder(delta, tau)
    disc = 1 - 4 * tau**2 * delta**2
    assert k.regime == ("confluent" if abs(disc) < 1e-12 else "real" if disc > 0 else "complex")
    a = abs(k.decay_rates[0])
    r = np.array([0.999e-3 / a, 1.001e-3 / a])
    v = k(r)
    # phi is smooth: across the switch the change is the true O(r^2) change, ~ 1e-6 * phi(0) at most.
    assert abs(v[0] - v[1]) < 1e-6 * v[0]
    d = k.derivative_over_r(r)
    assert abs(d[0] - d[1]) < 1e-5 * abs(d[0])


@pytest.mark.parametrize("delta,tau", [(10.0, 0.01), (20.0, 0.025), (40.0, 0.025), (3.1623, 0.01)])
def test_fourier_symbol_by_hankel_transform(delta, tau):
    """phi_hat(k) = 4 pi / k * int_0^inf phi(r) r sin(k r) dr = 1 / (delta^2 k^2 + k^4 + tau^2 k^6).

    The Laplace part 1/(4 pi delta^2 r) (transform 1/(delta^2 k^2)) is
    subtracted analytically; the rest decays exponentially."""
    kern = MultiOrder(delta, tau)
    c = 4 * math.pi * delta**2
    rmax = 60.0 / min(abs(kern.decay_rates[0].real), abs(kern.decay_rates[1].real))
    for k in (1.0, 7.0, 20.0):
        def integrand(r):
            return (kern(np.array([r]))[0] - 1.0 / (c * r)) * r * math.sin(k * r) if r > 0 else 0.0

        integral, _ = quad(integrand, 0, rmax, limit=4000)
        transform = 4 * math.pi / k * integral + 1.0 / (delta**2 * k**2)
        expected = 1.0 / (delta**2 * k**2 + k**4 + tau**2 * k**6)
        assert transform == pytest.approx(expected, rel=1e-5)
        assert kern.fourier_symbol(k) == pytest.approx(expected, rel=1e-14)


def test_far_field_is_a_newton_potential():
    k = MultiOrder(10.0, 0.01)
    r = np.array([5.0, 10.0])
    assert np.allclose(k(r), 1 / (4 * math.pi * 100 * r), rtol=1e-12)


def test_confluent_limit_formula():
    """At 4 tau^2 delta^2 = 1: phi = 1/(4 pi delta^2 r) [1 - e^{-ar}(1 + ar/2)], a = 1/(sqrt 2 tau)."""
    delta, tau = 20.0, 0.025
    k = MultiOrder(delta, tau)
    assert k.regime == "confluent"
    a = 1 / (math.sqrt(2) * tau)
    r = np.array([0.01, 0.05, 0.3, 2.0])
    expected = (1 - np.exp(-a * r) * (1 + a * r / 2)) / (4 * math.pi * delta**2 * r)
    assert np.allclose(k(r), expected, rtol=1e-12)
    # and the neighbours on both sides converge to it
    for t in (tau * (1 - 1e-7), tau * (1 + 1e-7)):
        assert np.allclose(MultiOrder(delta, t)(r), expected, rtol=1e-5)


@pytest.mark.parametrize("delta,tau", [(10.0, 0.01), (40.0, 0.025)])
def test_kernel_matrix_is_positive_definite(delta, tau, rng):
    x = rng.uniform(-1, 1, (300, 3))
    a = kernel_matrix(MultiOrder(delta, tau), x)
    assert np.linalg.eigvalsh(a).min() > 0


def test_gaussian_fourier_symbol_and_gradient():
    g = Gaussian(0.3)
    k = 4.0
    integral, _ = quad(lambda r: g(np.array([r]))[0] * r * math.sin(k * r), 0, 10, limit=400)
    assert 4 * math.pi / k * integral == pytest.approx(g.fourier_symbol(k), rel=1e-8)
    r = np.array([0.05, 0.2, 0.7])
    fd = (g(r + 1e-6) - g(r - 1e-6)) / 2e-6
    assert np.allclose(g.derivative(r), fd, rtol=1e-6)


def test_thinplate():
    t = ThinPlate()
    r = np.array([0.0, 0.5, 2.0])
    assert np.allclose(t(r), r**3)
    assert np.allclose(t.derivative(r), 3 * r**2)
    assert t.polynomial_degree == 1 and not t.positive_definite


@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), MultiOrder(3.1623, 0.01), MultiOrder(40, 0.025), Gaussian(0.2), ThinPlate()])
def test_compiled_and_numpy_sums_agree(kernel, rng):
    c = rng.uniform(-1, 1, (400, 3))
    x = rng.uniform(-1, 1, (300, 3))
    x[:3] = c[:3]
    x[3] = c[4] + 1e-7
    w = rng.standard_normal(400)
    v1, g1 = kernel_sum(kernel, c, w, x, gradient=True)
    v0, g0 = kernel_sum(kernel, c, w, x, gradient=True, compiled=False, chunk_bytes=8 * 400 * 7)
    assert np.allclose(v1, v0, rtol=1e-12, atol=1e-12 * np.abs(v0).max())
    assert np.allclose(g1, g0, rtol=1e-10, atol=1e-10 * np.abs(g0).max())
    # and the gradient is the gradient: central differences of the sum
    h = 1e-6
    e = np.eye(3)
    fd = np.column_stack([(kernel_sum(kernel, c, w, x[:20] + h * e[i]) - kernel_sum(kernel, c, w, x[:20] - h * e[i])) / (2 * h) for i in range(3)])
    assert np.allclose(g1[:20], fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_make_kernel_and_errors():
    assert make_kernel("multiorder", delta=5, tau=0.02) == MultiOrder(5, 0.02)
    assert make_kernel("Gaussian", sigma=0.3) == Gaussian(0.3)
    assert set(KERNELS) == {"multiorder", "thinplate", "gaussian"}
    k = MultiOrder(7, 0.02)
    assert make_kernel(**k.to_dict()) == k
    with pytest.raises(ValueError, match="unknown kernel 'cubic'"):
        make_kernel("cubic")
    with pytest.raises(ValueError, match="takes parameters"):
        make_kernel("thinplate", delta=3)
    for bad in (0, -1, float("nan"), float("inf"), 1e5, "x"):
        with pytest.raises(ValueError, match="delta"):
            MultiOrder(bad, 0.01)
    with pytest.raises(ValueError, match="tau"):
        MultiOrder(10, 0)
    with pytest.raises(ValueError, match="sigma"):
        Gaussian(-1)


@pytest.mark.parametrize("delta,tau", CASES)
def test_tabulated_kernel_matches_the_exact_one(delta, tau, rng):
    """The meshing tables: phi within 1e-8 pointwise, sums within 1e-8, gradients within 1e-5."""
    from o3drbf.rbf.compiled import KernelTable, _table_eval

    k = MultiOrder(delta, tau)
    table = KernelTable(k)
    r = np.concatenate([[0.0, 1e-9], np.geomspace(1e-6, 30.0, 3000)])
    got = np.array([_table_eval(x, *table.args(), True) for x in r])
    assert np.max(np.abs(got[:, 0] / k(r) - 1)) < 1e-8
    dor = k.derivative_over_r(r)
    assert np.max(np.abs(got[:, 1] - dor)) < 1e-5 * np.max(np.abs(dor))
    c = rng.uniform(-1, 1, (300, 3))
    x = rng.uniform(-1, 1, (200, 3))
    x[:2] = c[:2]
    w = rng.standard_normal(300)
    v0, g0 = kernel_sum(k, c, w, x, gradient=True, compiled=False)
    v1, g1 = kernel_sum(k, c, w, x, gradient=True, table=table)
    assert np.max(np.abs(v1 - v0)) < 1e-8 * np.max(np.abs(v0))
    assert np.max(np.abs(g1 - g0)) < 1e-5 * np.max(np.abs(g0))


@pytest.mark.parametrize("order", ["F", "C"])
@pytest.mark.parametrize("kernel", [MultiOrder(10, 0.01), Gaussian(0.2), ThinPlate()])
def test_compiled_kernel_matrix_is_the_numpy_one_in_either_order(kernel, order, rng):
    from o3drbf.rbf.sums import kernel_matrix

    x = rng.uniform(-1, 1, (70, 3))
    y = rng.uniform(-1, 1, (40, 3))
    y[0] = x[0]  # r = 0, and r tiny (the series branch)
    y[1] = x[1] + 1e-7
    ref = kernel_matrix(kernel, x, y, compiled=False)
    got = kernel_matrix(kernel, x, y, order=order)
    assert got.shape == (70, 40) and got.flags[order + "_CONTIGUOUS"]
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-13 * np.abs(ref).max())


@pytest.mark.parametrize("order", ["F", "C"])
def test_a_single_precision_kernel_matrix_is_the_double_one_rounded_once(order, rng):
    from o3drbf.rbf.sums import kernel_matrix

    kernel = MultiOrder(10, 0.01)
    x = rng.uniform(-1, 1, (70, 3))
    y = rng.uniform(-1, 1, (40, 3))
    y[0] = x[0]
    double = kernel_matrix(kernel, x, y, order=order)
    single = kernel_matrix(kernel, x, y, order=order, dtype=np.float32)
    assert single.dtype == np.float32 and single.flags[order + "_CONTIGUOUS"]
    np.testing.assert_array_equal(single, double.astype(np.float32))
    np.testing.assert_array_equal(kernel_matrix(kernel, x, y, compiled=False, dtype=np.float32), single)
    with pytest.raises(ValueError, match="dtype must be float64"):
        from o3drbf.rbf.compiled import direct_matrix

        direct_matrix(kernel, x, x, lower=True, dtype=np.float32)


@pytest.mark.parametrize("order", ["F", "C"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_tabulated_kernel_matrix_is_the_exact_one_to_the_tables_accuracy(order, dtype, rng):
    """kernel_matrix(table=...) (the preconditioner's coarse-to-fine block): every entry within 1e-8 of the
    exact matrix's largest (and within float32's rounding in single precision), in either order."""
    from o3drbf.rbf.compiled import KernelTable

    kernel = MultiOrder(10, 0.01)
    x = rng.uniform(-1, 1, (70, 3))
    y = rng.uniform(-1, 1, (40, 3))
    y[0] = x[0]  # r = 0 (the series)
    y[1] = x[1] + 1e-7
    exact = kernel_matrix(kernel, x, y, compiled=False)
    got = kernel_matrix(kernel, x, y, order=order, dtype=dtype, table=KernelTable(kernel))
    assert got.shape == (70, 40) and got.dtype == dtype and got.flags[order + "_CONTIGUOUS"]
    tol = 1e-8 if dtype == np.float64 else 1e-7
    assert np.abs(got - exact).max() < tol * np.abs(exact).max()
