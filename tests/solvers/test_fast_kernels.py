"""The compiled kernels under the grid products: spreading, the parallel sparse product, the far block."""

import numpy as np
import pytest
import scipy.sparse as sp

numba = pytest.importorskip("numba")

from o3drbf.rbf.kernels import MultiOrder  # noqa: E402
from o3drbf.rbf.sums import kernel_matrix  # noqa: E402
from o3drbf.solvers import fast  # noqa: E402
from o3drbf.solvers.fast.fftgrid import _gather, _spread  # noqa: E402
from o3drbf.solvers.fast.neighbours import csr_matvec  # noqa: E402


def spread_reference(pts, w, origin, h, s, half, shape):
    """Each point's Gaussian stencil added node by node (NumPy, no slabs)."""
    grid = np.zeros(shape)
    c = 1.0 / ((2 * np.pi) ** 1.5 * s**3)
    for p, wp in zip(pts, w):
        f = (p - origin) / h
        i0 = np.floor(f + 0.5).astype(int) - half
        idx = [np.arange(i0[a], i0[a] + 2 * half + 1) for a in range(3)]
        g = [np.exp(-((idx[a] - f[a]) * h) ** 2 / (2 * s * s)) for a in range(3)]
        grid[np.ix_(*idx)] += c * wp * g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :]
    return grid


def test_spread_by_slabs_matches_the_stencil_sum_and_not_the_thread_count():
    """Points over many slabs along x (and in random order) land where their stencils say, to rounding,
    and the slab order makes the grid bit-for-bit the same on one thread and on all."""
    rng = np.random.default_rng(0)
    half, h, s = 3, 0.1, 0.15
    shape = (64, 20, 20)
    origin = np.zeros(3)
    lo = (half + 1) * h
    pts = np.column_stack([rng.uniform(lo, (shape[i] - half - 2) * h, 700) for i in range(3)])
    w = rng.normal(size=len(pts))
    ref = spread_reference(pts, w, origin, h, s, half, shape)
    got = np.zeros(shape)
    _spread(pts, w, origin, h, s, half, got)
    assert np.abs(got - ref).max() < 1e-12 * np.abs(ref).max()
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = np.zeros(shape)
        _spread(pts, w, origin, h, s, half, one)
    finally:
        numba.set_num_threads(threads)
    assert np.array_equal(one, got)


def gather_reference(pts, origin, h, s, half, u):
    """Each point's Gaussian stencil over ``u``, and its gradient, node by node (NumPy)."""
    c = 1.0 / ((2 * np.pi) ** 1.5 * s**3)
    vals, grads = [], []
    for p in pts:
        f = (p - origin) / h
        i0 = np.floor(f + 0.5).astype(int) - half
        idx = [np.arange(i0[a], i0[a] + 2 * half + 1) for a in range(3)]
        d = [(f[a] - idx[a]) * h for a in range(3)]
        g = [np.exp(-d[a] ** 2 / (2 * s * s)) for a in range(3)]
        dg = [-d[a] / (s * s) * g[a] for a in range(3)]
        block = u[np.ix_(*idx)]
        vals.append(c * np.einsum("i,j,k,ijk", g[0], g[1], g[2], block))
        grads.append(c * np.array([np.einsum("i,j,k,ijk", dg[0], g[1], g[2], block),
                                   np.einsum("i,j,k,ijk", g[0], dg[1], g[2], block),
                                   np.einsum("i,j,k,ijk", g[0], g[1], dg[2], block)]))
    return np.array(vals), np.array(grads)


def test_gather_is_the_stencil_sum_with_its_gradient():
    """Values and gradients at points anywhere in a grid that is not a cube (rows addressed flat),
    the same with and without the gradient; and the gradient is the values' finite difference."""
    rng = np.random.default_rng(4)
    half, h, s = 3, 0.1, 0.15
    shape = (17, 23, 29)
    origin = np.array([0.3, -0.2, 0.1])
    lo = (half + 1) * h
    pts = origin + np.column_stack([rng.uniform(lo, (shape[i] - half - 2) * h, 300) for i in range(3)])
    u = rng.normal(size=shape)
    ref_v, ref_g = gather_reference(pts, origin, h, s, half, u)
    v, g = np.empty(len(pts)), np.empty((len(pts), 3))
    _gather(pts, origin, h, s, half, u, v, g, True)
    v_only = np.empty(len(pts))
    _gather(pts, origin, h, s, half, u, v_only, np.empty((1, 3)), False)
    scale = np.abs(ref_v).max()
    assert np.abs(v - ref_v).max() < 1e-12 * scale and np.abs(v_only - ref_v).max() < 1e-12 * scale
    assert np.abs(g - ref_g).max() < 1e-12 * np.abs(ref_g).max()
    # The gradient is that of the gathered field (central differences, away from stencil shifts).
    step = 1e-6
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = step
        plus, minus = np.empty(len(pts)), np.empty(len(pts))
        _gather(pts + e, origin, h, s, half, u, plus, np.empty((1, 3)), False)
        _gather(pts - e, origin, h, s, half, u, minus, np.empty((1, 3)), False)
        fd = (plus - minus) / (2 * step)
        same_stencil = np.all(np.floor((pts + e - origin) / h + 0.5) == np.floor((pts - e - origin) / h + 0.5), axis=1)
        assert same_stencil.sum() > 250
        assert np.abs(fd - g[:, axis])[same_stencil].max() < 1e-4 * np.abs(g).max()


def test_csr_matvec_is_scipys_product_and_adds_in_place():
    a = sp.random(300, 200, density=0.05, format="csr", random_state=1)
    x = np.random.default_rng(2).normal(size=200)
    assert np.allclose(csr_matvec(a, x), a @ x, rtol=1e-14, atol=1e-14)
    out = np.ones(300)
    assert csr_matvec(a, x, out) is out
    assert np.allclose(out, 1.0 + a @ x, rtol=1e-14, atol=1e-14)
    single = a.astype(np.float32)  # the local step's matrix: float32 entries, summed in double precision
    want = single.astype(np.float64) @ x
    assert np.abs(csr_matvec(single, x) - want).max() < 1e-13 * np.abs(want).max()


def test_far_centres_block_and_direct_sums_agree_with_dense():
    """The stored block between the grid's centres and the far ones (the exterior sphere) and the
    direct sums that replace it when it is too big give the same products, and the dense one."""
    kernel = MultiOrder(10.0, 0.01)
    rng = np.random.default_rng(3)
    core = rng.uniform(-0.5, 0.5, (2000, 3))
    far = 3.0 * rng.normal(size=(12, 3))
    far = 4.0 * far / np.linalg.norm(far, axis=1, keepdims=True)
    c = np.vstack([core[:1000], far[:6], core[1000:], far[6:]])  # far centres among the others
    a = kernel_matrix(kernel, c)
    block = fast.GridSum(kernel, c, eps=1e-7)
    direct = fast.GridSum(kernel, c, eps=1e-7)
    direct.OUTSIDE_BLOCK_BYTES = 0
    assert len(block.outside) == 12 and block._outside_block() is not None and direct._outside_block() is None
    w = rng.normal(size=len(c))
    ref = a @ w
    for e in (None, 1e-3):
        got, want = block.matvec(w, eps=e), direct.matvec(w, eps=e)
        assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-12
        assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < (e or 1e-7)
    subset = np.r_[rng.choice(1000, 200, replace=False), 1000, 1003, 2006 + np.arange(6)]
    z = rng.normal(size=len(subset))
    ref = a[:, subset] @ z
    got, want = block.from_subset(subset)(z), direct.from_subset(subset)(z)
    assert np.linalg.norm(got - want) / np.linalg.norm(want) < 1e-12
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 1e-7


def test_restricted_near_field_is_the_smaller_radius_cell_list_matrix():
    """A companion's near field cut from the product's (larger radius) has exactly the entries, and
    values, of a fresh cell-list build at the smaller radius."""
    from o3drbf.solvers.fast.neighbours import CellList, restrict_near

    pts = np.random.default_rng(4).uniform(-1, 1, (3000, 3))
    tab = np.cos(np.linspace(0, 3, 4001))
    dr = 0.5 / 4000
    big = CellList(pts, 0.3).matrix(pts, tab, dr)
    small = CellList(pts, 0.17).matrix(pts, tab, dr)
    cut = restrict_near(big, pts, 0.17, tab, dr)
    assert cut.nnz == small.nnz < big.nnz
    assert (cut != small).nnz == 0


def test_companions_take_their_near_field_from_the_product():
    """The looser companions' stored near fields come from the product's pattern (no second cell
    search) and give the products a fresh build gives."""
    kernel = MultiOrder(10.0, 0.01)
    c = np.random.default_rng(5).uniform(-0.5, 0.5, (4000, 3))
    g = fast.GridSum(kernel, c, eps=1e-7, store=True)
    w = np.random.default_rng(6).normal(size=len(c))
    g.matvec(w)  # the product's near field first
    tier = g._tier(1e-3)
    assert tier._near_parent is g and tier.rc <= g.rc
    fresh = fast.GridSum(kernel, c, eps=1e-3, radius=g.tier_radius(1e-3), store=True)
    assert tier.near.nnz == fresh.near.nnz
    assert np.allclose(g.matvec(w, eps=1e-3), fresh.matvec(w), rtol=1e-12, atol=1e-12 * np.abs(fresh.matvec(w)).max())


def test_local_step_radius_is_the_sampled_median_of_the_neighbours_distances():
    """The tapered near field's radius is the median distance to the k-th neighbour (self not counted)
    over neighbour_radius's sample of the centres: within a percent of every centre's median (SciPy),
    the same on every call, and the median over all the centres where they are fewer than the sample."""
    from scipy.spatial import cKDTree

    from o3drbf.solvers.fast import precondition
    from o3drbf.solvers.fast.neighbours import RADIUS_SAMPLE
    from o3drbf.synthetic.shapes import Torus

    pts, _ = Torus().sample(20000, seed=4)
    tree = cKDTree(pts)
    kernel = MultiOrder(10.0, 0.01)
    full = float(np.median(tree.query(pts, k=[33])[0][:, 0]))
    _, r1, _ = precondition.tapered_near(kernel, pts, tree, 32, lambda phir: 1.0)
    _, r2, _ = precondition.tapered_near(kernel, pts, tree, 32, lambda phir: 1.0)
    assert r1 == r2 and r1 != full and abs(r1 / full - 1) < 0.01
    few = pts[:RADIUS_SAMPLE]
    few_tree = cKDTree(few)
    _, r_few, _ = precondition.tapered_near(kernel, few, few_tree, 32, lambda phir: 1.0)
    assert r_few == float(np.median(few_tree.query(few, k=[33])[0][:, 0]))


@pytest.mark.parametrize("span", [(7, 9, 5), (33, 20, 17)])
def test_kernel_transform_by_mirrored_views_is_the_full_transform(span):
    """The potential multiplies each block of columns by K's transform read from its kept octant through
    mirrored views; the same numbers as the full transform (built by indexing) in every kind of block:
    first half, mirrored half, across the middle, one column."""
    rng = np.random.default_rng(0)
    c = rng.uniform(0, 1, (500, 3)) * np.array(span) / 30
    m = fast.GridSum(MultiOrder(10, 0.01), c, eps=1e-6).mesh
    fx, fy, fz = m.fshape
    mirror = lambda f: np.minimum(np.arange(f), f - np.arange(f))  # noqa: E731
    full = m.khat[np.ix_(mirror(fx), mirror(fy))]
    for j0, j1 in [(0, fy), (0, 1), (fy // 2 - 1, fy // 2 + 2), (fy // 2 + 1, fy), (fy - 1, fy), (fy // 2, fy // 2 + 1)]:
        blk = rng.normal(size=(fx, j1 - j0, m.khat.shape[2])) + 0j
        want = blk * full[:, j0:j1]
        m._times_khat(blk, j0, j1)
        assert np.array_equal(blk, want), (j0, j1)


def potential_reference(mesh, pts, w, ktable):
    """The grid potential by its definition: the spread weights convolved (aperiodic, node by node) with the
    grid kernel ``ktable(squared node distance) h^3``, times h^3."""
    grid = np.zeros(mesh.shape)
    _spread(pts, w, mesh.origin, mesh.h, mesh.s, mesh.half, grid)
    idx = np.indices(mesh.shape).reshape(3, -1).T
    d2 = ((idx[:, None, :] - idx[None, :, :]) ** 2).sum(axis=2)
    return (ktable(d2) * mesh.h**3 @ grid.reshape(-1)).reshape(mesh.shape) * mesh.h**3


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_potential_is_the_direct_convolution_in_and_out_of_reused_work(dtype):
    """The potential equals the node-by-node convolution, with new work arrays and with a solve's reused ones;
    inside :func:`reused_work` the work arrays are one buffer (shared from call to call, a new result not
    overwritten by the next call, a scratch result in the buffer), freed when the block ends."""
    import gc
    import weakref

    from o3drbf.solvers.fast.fftgrid import Mesh, reused_work, work_arrays

    def ktable(n2):
        return np.exp(-np.asarray(n2, float) / 9.0)

    rng = np.random.default_rng(1)
    h, s, half = 0.1, 0.12, 2
    mesh = Mesh(np.zeros(3), np.array([0.5, 0.4, 0.3]), h, s, half, ktable, dtype)
    lo, hi = mesh.origin + (half + 1) * h, mesh.origin + (np.array(mesh.shape) - half - 2) * h
    pts = rng.uniform(lo, hi, (40, 3))
    w1, w2 = rng.normal(size=40), rng.normal(size=40)
    ref1, ref2 = potential_reference(mesh, pts, w1, ktable), potential_reference(mesh, pts, w2, ktable)
    tol = (1e-12 if dtype == np.float64 else 2e-6) * np.abs(ref1).max()
    assert np.abs(mesh.potential(pts, w1) - ref1).max() < tol
    with reused_work():
        a, b = work_arrays((3, 4), np.float64, (5,), np.complex128)
        c, d = work_arrays((3, 4), np.float64, (5,), np.complex128)
        assert a.base is c.base and not np.shares_memory(a, b)
        del a, b, c, d
        u1 = mesh.potential(pts, w1)
        u2 = mesh.potential(pts, w2, scratch=True)  # (the buffer grown to the mesh's work arrays)
        mz = mesh.shape[2]
        # a scratch result: the work array, in the grid's precision and padded along z; gathers read it as it is
        assert u2.dtype == dtype and u2.shape[:2] == mesh.shape[:2] and u2.shape[2] >= mz
        assert np.abs(u1 - ref1).max() < tol and np.abs(u2[:, :, :mz] - ref2).max() < tol
        assert u1.dtype == np.float64 and u1.shape == mesh.shape
        g = mesh.gather(u2, pts, False)
        np.testing.assert_allclose(g, mesh.gather(np.ascontiguousarray(ref2), pts, False), rtol=0, atol=tol * 30)
        e, z = work_arrays((3, 4), np.float64, (5,), np.complex128)
        assert np.shares_memory(e.base, u2)  # the scratch result: in the work buffer
        buffer = weakref.ref(e.base)
        del e, z
        with reused_work():  # nested (a robust refit inside a fit): the same buffer
            f, _ = work_arrays((3, 4), np.float64, (5,), np.complex128)
            assert f.base is buffer()
            del f, _
        assert buffer() is not None
    del u2
    gc.collect()
    assert buffer() is None
    x, y = work_arrays((3, 4), np.float64, (5,), np.complex128)
    assert x.base is None and y.base is None  # outside: new arrays


def test_potential_by_scipy_fft_public_functions_is_the_same(monkeypatch):
    """Where scipy.fft's pocketfft module is not found, its public functions give the same potential."""
    from o3drbf.solvers.fast import fftgrid

    def ktable(n2):
        return np.exp(-np.asarray(n2, float) / 9.0)

    rng = np.random.default_rng(2)
    mesh = fftgrid.Mesh(np.zeros(3), np.array([0.5, 0.4, 0.3]), 0.1, 0.12, 2, ktable, np.float64)
    lo, hi = mesh.origin + 3 * 0.1, mesh.origin + (np.array(mesh.shape) - 4) * 0.1
    pts, w = rng.uniform(lo, hi, (40, 3)), rng.normal(size=40)
    fast_path = mesh.potential(pts, w)
    monkeypatch.setattr(fftgrid, "_pfft", fftgrid.PublicTransforms)
    public = mesh.potential(pts, w)
    assert np.abs(public - fast_path).max() < 1e-12 * np.abs(fast_path).max()
    assert np.abs(public - potential_reference(mesh, pts, w, ktable)).max() < 1e-12 * np.abs(fast_path).max()


@pytest.mark.parametrize("kernel", [MultiOrder(8, 0.006), MultiOrder(3.456, 0.025)], ids=repr)
def test_long_part_of_real_rates_is_the_gaussian_smoothed_kernel(monkeypatch, kernel):
    """The grid's long part of a kernel whose decay rates are real, summed in real arithmetic: each
    component e^{-kappa r} / (4 pi r) convolved with the Gaussian of width sigma (a radial quadrature),
    times e^{-kappa^2 (sigma^2 + extra^2) / 2}, within 1e-10 of the largest value."""
    import math

    from scipy.integrate import quad

    from o3drbf.solvers.fast import grid

    def smoothed(r, kappa, sigma):
        def f(rho):
            return math.exp(-kappa * rho) / (4 * math.pi) * (math.exp(-(r - rho) ** 2 / (2 * sigma**2))
                                                              - math.exp(-(r + rho) ** 2 / (2 * sigma**2)))
        return quad(f, 0.0, r + 12 * sigma, points=[r], limit=200, epsabs=0.0, epsrel=1e-13)[0] / (r * math.sqrt(2 * math.pi) * sigma)

    kinds = []
    psi = grid._psi_long
    monkeypatch.setattr(grid, "_psi_long", lambda r, kappa, sigma: kinds.append(type(kappa)) or psi(r, kappa, sigma))
    sigma, extra = 0.068, 0.03
    r = np.array([0.005, 0.02, 0.07, 0.2, 0.45])
    got = grid.long_part(kernel, r, sigma, extra=extra)
    assert kinds and all(k is float for k in kinds)
    want = np.zeros(len(r))
    for kappa, coef in grid._components(kernel):
        kappa, coef = complex(kappa).real, complex(coef).real
        want += coef * math.exp(-kappa**2 * (sigma**2 + extra**2) / 2) * np.array([smoothed(x, kappa, sigma) for x in r])
    assert np.abs(got - want).max() <= 1e-10 * np.abs(want).max()
