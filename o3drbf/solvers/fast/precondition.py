"""The two-level preconditioner of the fast solve: a coarse level (Cholesky or nested FGMRES) and a
tapered near-field local step."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
import time

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from o3drbf.rbf import compiled
from o3drbf.rbf.sums import kernel_matrix
from o3drbf.solvers.dense import DENSE_MAX
from o3drbf.solvers.fast.fgmres import fgmres
from o3drbf.solvers.fast.fmm import FastSum
from o3drbf.solvers.fast.grid import GridSum
from o3drbf.solvers.fast.operator import fast_operator
from o3drbf.solvers.fast.neighbours import CellList, csr_matvec, neighbour_radius, njit

__all__ = ["TwoLevel", "TwoLevelSettings", "coarse_size", "second_correction", "coarse_factor", "coarse_matrix_factor", "coarse_solve", "COARSE_SINGLE",
           "COARSE_MAX"]


def _uniform_subset(points: np.ndarray, count: int) -> np.ndarray:
    """About ``count`` indices spread uniformly over the points: in each occupied voxel of a grid
    sized for that count, the point nearest the voxel's centre (ties to the lower index), so
    that the choice does not depend on the points' order."""
    n = len(points)
    if count >= n:
        return np.arange(n)
    lo = points.min(axis=0)
    span = max(float(np.ptp(points, axis=0).max()), 1e-12)
    best = None
    # Bisection on the voxel size so that the occupied-voxel count ~ count.
    hi_h, lo_h = span, span * 1e-4
    for _ in range(30):
        h = math.sqrt(hi_h * lo_h)
        occupied = len(np.unique(_voxels(points, lo, h)[0]))
        if best is None or abs(occupied - count) < abs(best[1] - count):
            best = (h, occupied)
        if occupied > count:
            lo_h = h
        else:
            hi_h = h
        if abs(occupied - count) <= 0.05 * count:
            break
    flat, key = _voxels(points, lo, best[0])
    d2 = (((points - lo) / best[0] - (key + 0.5)) ** 2).sum(axis=1)
    order = np.lexsort((d2, flat))  # by voxel, then nearest its centre (a stable sort: then index)
    f = flat[order]
    return np.sort(order[np.r_[True, f[1:] != f[:-1]]])


def _voxels(points, lo, h):
    """(one integer a voxel of side ``h`` from ``lo``, in the rows' order; the voxels' integer coordinates)."""
    key = np.floor((points - lo) / h).astype(np.int64)
    dims = key.max(axis=0) + 1
    return (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2], key


#: The coarse level's Cholesky factorization and factor are in single precision (double where the single
#: factorization breaks down): the factorization takes a fraction of the time, its two triangular solves
#: a preconditioner step, bound by reading the factor, read half as much, and the factor, which lives
#: through the solve, takes half the memory.  The smoothing keeps the coarse matrix well conditioned; a
#: preconditioner needs no more than single precision (benchmarks/recorded/fast_solver.md, session 27).
COARSE_SINGLE = True

#: The largest coarse level (``TwoLevelSettings.max_coarse``): its single-precision factorization ran
#: to 19,370 centres on two threads (a double one of 16,000 crashes the installed OpenBLAS, whence
#: ``DENSE_MAX``; above it the double fallback of :func:`coarse_factor` takes one thread).
COARSE_MAX = 20_000


def _lower(a: np.ndarray, dtype) -> np.ndarray:
    """A Fortran-ordered copy of the lower triangle of ``a`` in ``dtype``; its upper triangle is not set
    (nor its pages touched)."""
    n = len(a)
    out = np.empty((n, n), dtype=dtype, order="F")
    step = max(1, (1 << 22) // max(n, 1))
    for i in range(0, n, step):
        j = min(i + step, n)
        out[i:j, i:j] = np.tril(a[i:j, i:j])  # (what lies above the diagonal is not read: it may be anything)
        out[j:, i:j] = a[j:, i:j]
    return out


def coarse_factor(a: np.ndarray, try_single: bool = True) -> np.ndarray:
    """The lower Cholesky factor of the symmetric positive definite ``a`` (its lower triangle read; it may
    be overwritten), Fortran-ordered; its upper triangle is not set.  With :data:`COARSE_SINGLE`, factored
    and kept in single precision, or, where that breaks down (or ``try_single`` is False: it is known to),
    factored in double and kept in single.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``a`` is not positive definite.
    """
    if COARSE_SINGLE and try_single:
        c, info = sla.lapack.spotrf(_lower(a, np.float32), lower=1, overwrite_a=1, clean=0)
        if info == 0:
            return c
    if len(a) > DENSE_MAX:  # the installed OpenBLAS crashes in larger two-thread double factorizations
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            c, _ = sla.cho_factor(a, lower=True, overwrite_a=True, check_finite=False)
    else:
        c, _ = sla.cho_factor(a, lower=True, overwrite_a=True, check_finite=False)
    return _lower(c, np.float32) if COARSE_SINGLE else np.asfortranarray(c)


def coarse_matrix_factor(kernel, x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """:func:`coarse_factor` of ``Phi(x, x) + diag(lam)``.  With :data:`COARSE_SINGLE` and a kernel with a
    compiled form, the lower triangle is evaluated straight into single precision
    (:func:`o3drbf.rbf.compiled.lower_matrix_single`: the same numbers as the double matrix's rounded
    copy) and factored in place, so no double matrix is made; it is made only where that factorization
    breaks down."""
    tried = False
    if COARSE_SINGLE and compiled.supports(kernel):
        c, info = sla.lapack.spotrf(compiled.lower_matrix_single(kernel, x, lam), lower=1, overwrite_a=1, clean=0)
        if info == 0:
            return c
        del c
        tried = True
    acc = kernel_matrix(kernel, x, lower=True)  # the lower triangle: all the factorization reads
    acc[np.diag_indices(len(x))] += lam
    return coarse_factor(acc, try_single=not tried)


def coarse_solve(factor: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``x`` with ``L L^T x = b`` for the lower factor ``L`` of :func:`coarse_factor`, in double.

    Two BLAS triangular solves (``trsv``): for one right-hand side they read the factor once each,
    where LAPACK's ``potrs`` goes through the matrix-matrix ``trsm`` at several times the cost.
    """
    trsv = sla.blas.strsv if factor.dtype == np.float32 else sla.blas.dtrsv
    y = trsv(factor, np.asarray(b, dtype=factor.dtype), lower=1)
    return np.asarray(trsv(factor, y, lower=1, trans=1, overwrite_x=1), dtype=float)


@njit(cache=True)
def _set_diagonal(indptr, indices, data, diag):
    """``data`` of the CSR matrix at (p, p) set to ``diag[p]`` (in place)."""
    for p in range(len(indptr) - 1):
        for c in range(indptr[p], indptr[p + 1]):
            if indices[c] == p:
                data[c] = diag[p]


def tapered_near(kernel, centres, tree, neighbours: int, diag):
    """The local step's matrix: ``phi(r) - phi(R)`` between the centres within R (the median distance
    to the ``neighbours``-th neighbour, self not counted: :func:`~o3drbf.solvers.fast.neighbours.neighbour_radius`,
    over its sample of the centres), its diagonal ``diag`` (CSR, built in place by the cell list, the
    tapered kernel tabulated at 32,768 radii), its entries in single precision: the local step
    only approximates, and its products, bound by reading the matrix, read a third less.
    Returns (matrix, R, phi(R))."""
    n = len(centres)
    radius = neighbour_radius(centres, tree, neighbours + 1)
    phir = float(kernel(np.array([radius]))[0])
    rr = np.linspace(0.0, 1.01 * radius, 1 << 15)
    tab = kernel(rr) - phir
    m = CellList(centres, radius).matrix(np.ascontiguousarray(centres, dtype=float), tab, float(rr[1] - rr[0]), np.float32)
    _set_diagonal(m.indptr, m.indices, m.data, np.broadcast_to(np.asarray(diag(phir), dtype=float), (n,)).copy())
    return m, radius, phir


def _subset_operator(fast, subset, eps):
    """The same kind of product on ``fast.centres[subset]`` (for a nested coarse level)."""
    cen = fast.centres[subset]
    if isinstance(fast, GridSum):  # the grid when it fits its budget, else fmm3dpy
        return fast_operator(fast.kernel, cen, eps=max(eps, fast.eps), backend="auto")
    if isinstance(fast, FastSum):
        return FastSum(fast.kernel, cen, eps=max(eps, fast.eps), workers=fast.workers)
    return type(fast)(fast.kernel, cen)


def coarse_size(n: int, settings: "TwoLevelSettings") -> tuple[int, int]:
    """(coarse centres, nested steps) of a :class:`TwoLevel` on ``n`` centres with these settings.

    All centres up to ``exact_below``; else ``n / coarse_ratio`` capped at
    ``max(cap_floor, n / cap_ratio)`` and at ``max_coarse``, factored by
    Cholesky (its set-up grows as the cube of the size, the iterations it
    saves as ``n``); with ``nested`` steps and ``n > nested_ratio *
    max_coarse``, ``n / coarse_ratio`` uncapped, solved by nested steps."""
    st = settings
    if n <= st.exact_below:
        return n, 0
    want = max(n // st.coarse_ratio, 1)
    cap = min(st.max_coarse, max(st.cap_floor, n // st.cap_ratio))
    if st.nested and want > cap and n > st.nested_ratio * st.max_coarse:
        return min(want, n), int(st.nested)
    return min(want, cap, n), 0


def second_correction(n: int, settings: "TwoLevelSettings") -> bool:
    """Whether a :class:`TwoLevel` on ``n`` centres with these settings takes the second coarse correction
    from a grid product's coarse rows: where the coarse level is capped below ``n / coarse_ratio`` (so never
    exact, and Cholesky-factored unless nested), there it saves more iterations than it costs.  (Where the
    coarse-to-fine block is stored, the correction takes its rows from the block instead.)"""
    mc, nested = coarse_size(n, settings)
    return bool(settings.post_coarse and not nested and mc < n // settings.coarse_ratio)


@dataclass(frozen=True)
class TwoLevelSettings:
    """The settings of :class:`TwoLevel` (each described there)."""

    neighbours: int = 64
    coarse_ratio: int = 8
    max_coarse: int = 16000
    cap_ratio: int = 20
    cap_floor: int = 6000
    inner: int = 10
    eps: float = 1e-3
    dense_budget: int = 256 * 2**20
    select: str = "uniform"
    exact_below: int = 3000
    damping: float = 2.0
    nested: int = 0
    nested_eps: float = 1e-3
    nested_rtol: float = 0.0
    nested_ratio: float = 24
    post_coarse: bool = True
    post_eps: float = 1e-2
    post_damping: float = 0.4


class TwoLevel:
    """Two-level multiplicative preconditioner for ``Phi + diag(lam)``.

    Parameters
    ----------
    fast : FastSum
        The operator (its centres and kernel).
    lam : (N,) array
    settings : TwoLevelSettings, optional
        The settings below (default :class:`TwoLevelSettings`); ``**overrides``
        are its fields by name, over it.
    neighbours : int
        k of the tapered near-field matrix.
    coarse_ratio, cap_ratio, cap_floor, max_coarse : int
        Coarse level size ``N / coarse_ratio``, capped at ``max(cap_floor,
        N / cap_ratio)`` and at ``max_coarse`` (:func:`coarse_size`), solved
        by Cholesky (:func:`coarse_factor`): 6,000 centres up to N = 120,000,
        16,000 from N = 320,000 (a larger coarse level saves iterations at
        large N, where they cost most; its factorization's set-up grows as
        the cube of its size).  ``max_coarse`` is at most :data:`COARSE_MAX`.
    inner : int
        CG steps on the near-field matrix.
    damping : float
        The near-field diagonal phi(0) - phi(R) is multiplied by this (a
        damped local step after the coarse correction); with the second
        coarse correction, by at least ``post_damping / (1 - phi(R) / phi(0))``.
    exact_below : int
        Up to this N the "coarse" level is all centres: an exact Cholesky
        preconditioner (one iteration).
    select : {"uniform", "random"}
        How the coarse centres are picked (one per voxel, or at random).
    eps : float
        Tolerance of the coarse-to-fine residual update (when not dense).
    dense_budget : int
        Bytes allowed for storing the (N, |C|) coarse-to-fine block.
    nested : int
        FGMRES steps for an uncapped coarse level (0, the default: capped
        instead).  The steps are preconditioned by a TwoLevel on the coarse
        centres (same parameters, so recursive); off by default, since
        the capped Cholesky level took about as many iterations, each
        cheaper (benchmarks/recorded/fast_solver.md, session 18).
    nested_eps : float
        Tolerance of the products on the coarse centres (nested level).
    nested_rtol : float
        Relative residual that stops the nested steps early (0: always
        ``nested`` steps).
    nested_ratio : float
        With ``nested`` steps, nest only when ``N > nested_ratio *
        max_coarse``; below it the coarse level is capped.
    post_coarse : bool
        After the local step, correct the coarse centres' weights once more
        from the residual left at them (the product's rows at the coarse
        centres, one more Cholesky solve): coarse, local, coarse.  Where the
        coarse-to-fine block is stored (``dense_budget``, up to about
        20,000 centres) those rows are the block's columns, cheap beside a
        product; where the coarse level is capped below ``N /
        coarse_ratio`` (from about 48,000 centres, :func:`second_correction`)
        they come from a grid product at ``post_eps``.  Between the two
        (a fast sum for the coarse-to-fine update and no cap), and with
        nested steps, no second correction.
    post_eps : float
        Tolerance of that product (its rows at the coarse centres only,
        :meth:`~o3drbf.solvers.fast.grid.GridSum.rows`).
    post_damping : float
        With the second coarse correction, the local step's damping is at
        least ``post_damping / (1 - phi(R) / phi(0))``.  The flatter the
        kernel over the near radius R, the less of it the near field holds,
        and an undamped local step between two coarse corrections
        over-corrects: at a million centres (phi(R) / phi(0) = 0.89) the
        solve stalled near a residual of 1e-4 with the damping of 2
        (benchmarks/recorded/fast_solver.md, session 23).
    """

    def __init__(self, fast: FastSum, lam, settings: TwoLevelSettings | None = None, **overrides):
        unknown = sorted(set(overrides) - {f.name for f in fields(TwoLevelSettings)})
        if unknown:
            raise ValueError(f"unknown preconditioner setting(s) {', '.join(unknown)}; valid: {', '.join(f.name for f in fields(TwoLevelSettings))}")
        st = replace(settings or TwoLevelSettings(), **overrides)
        if st.max_coarse > COARSE_MAX:
            raise ValueError(f"max_coarse {st.max_coarse} is above {COARSE_MAX}, the largest coarse level factored here; use nested "
                             "steps for a larger coarse level")
        neighbours, inner, eps, dense_budget, select = st.neighbours, st.inner, st.eps, st.dense_budget, st.select
        nested_eps, nested_rtol = st.nested_eps, st.nested_rtol
        kernel, x = fast.kernel, fast.centres
        n = len(x)
        self.fast, self.lam, self.inner, self.eps = fast, np.asarray(lam, float), int(inner), eps
        t0 = time.perf_counter()
        mc, self.nested = coarse_size(n, st)
        # The coarse centres first: whether the coarse-to-fine block is stored decides the second correction.
        if select == "random" and mc < n:
            self.coarse = np.sort(np.random.default_rng(0).choice(n, mc, replace=False))
        else:
            self.coarse = _uniform_subset(x, mc)
        self.exact = len(self.coarse) == n
        stores_block = not self.exact and n * len(self.coarse) * 4 <= dense_budget  # in single precision, like the coarse factor
        post = second_correction(n, st) or bool(st.post_coarse and not self.nested and stores_block)
        self.damping = float(st.damping)

        def near_diagonal(phir):  # the local step's diagonal, damped
            if post and fast.phi0 > phir:
                self.damping = max(self.damping, st.post_damping / (1.0 - phir / fast.phi0))
            self.diag_base = self.damping * (fast.phi0 - phir)
            return self.diag_base + self.lam

        # Near field: tapered kernel phi(r) - phi(R) on ~k neighbours.
        k = min(neighbours, n - 1)
        if k >= 1:
            self.near, radius, phir = tapered_near(kernel, x, fast.tree, k, near_diagonal)
        else:
            radius, self.diag_base = 0.0, fast.phi0
            self.near = sp.diags(self.diag_base + self.lam).tocsr()
        diag = self.diag_base + self.lam
        self.near_diag = np.asarray(diag, dtype=float)
        self.radius = radius
        # Coarse level.
        xc = x[self.coarse]
        self.factor = self.inner_level = None
        if self.nested:
            # The coarse system is too big for Cholesky: solve it loosely by a
            # few FGMRES steps preconditioned by the same scheme (recursively).
            sub = _subset_operator(fast, self.coarse, nested_eps)
            self.inner_level = TwoLevel(sub, self.lam[self.coarse], st)
            self._sub, self._sub_lam, self._sub_eps = sub, self.lam[self.coarse], nested_eps
            self._sub_rtol = float(nested_rtol)
        else:
            self.factor = coarse_matrix_factor(kernel, xc, self.lam[self.coarse])
        self.block = None
        self.update = None
        if stores_block:  # from the kernel's tables where it has them: a preconditioner's entries need not be exact
            self.block = kernel_matrix(kernel, x, xc, order="C", dtype=np.float32, table=compiled.kernel_table(kernel))
        elif not self.exact:
            self.update = fast.from_subset(self.coarse)
        self.post_rows = None
        if post and self.block is not None:  # the block's columns are the coarse rows: Phi[C, :] z = block^T z
            self.post_rows = lambda z, b=self.block: (z.astype(np.float32) @ b).astype(float)
        elif post:
            rows = getattr(fast, "rows", None)  # a grid sum: only the coarse rows of the product
            self.post_rows = rows(self.coarse, eps=st.post_eps) if rows is not None \
                else (lambda z, c=self.coarse, e=st.post_eps: fast.matvec(z, eps=e)[c])
        self.setup_seconds = time.perf_counter() - t0
        self.info = {
            "near_neighbours": k,
            "near_radius": radius,
            "near_nnz": int(self.near.nnz),
            "coarse": len(self.coarse),
            "coarse_update": "exact" if self.exact else ("dense block" if self.block is not None else "fast sum"),
            "coarse_solve": (f"{self.nested} nested FGMRES steps" if self.nested else "Cholesky"),
            "post_coarse": self.post_rows is not None,
            "damping": self.damping,
            "setup_seconds": self.setup_seconds,
        }
        if self.inner_level is not None:
            self.info["inner"] = self.inner_level.info

    def set_smoothing(self, lam) -> None:
        """Precondition ``Phi + diag(lam)`` for a new ``lam`` (in place), as a new :class:`TwoLevel` would.

        The coarse centres, the near field's pattern and the coarse-to-fine
        block are kept (the costly parts); the local step's diagonal follows
        ``lam``, and the coarse level is factored again (or, nested, set to it
        in turn) only when ``lam`` changed at a coarse centre.
        """
        lam = np.broadcast_to(np.asarray(lam, dtype=float), self.lam.shape).copy()
        coarse_changed = not np.array_equal(lam[self.coarse], self.lam[self.coarse])
        diag = self.diag_base + lam
        _set_diagonal(self.near.indptr, self.near.indices, self.near.data, np.ascontiguousarray(diag))
        self.near_diag, self.lam = diag, lam
        if not coarse_changed:
            return
        if self.inner_level is not None:
            self._sub_lam = lam[self.coarse]
            self.inner_level.set_smoothing(self._sub_lam)
        else:
            self.factor = None  # (its memory freed before the new one)
            self.factor = coarse_matrix_factor(self.fast.kernel, self.fast.centres[self.coarse], lam[self.coarse])

    def _coarse_to_fine(self, zc):
        """(Phi + Lambda)[:, C] z_C."""
        if self.block is not None:
            out = (self.block @ zc.astype(np.float32)).astype(float)
        else:
            out = self.update(zc, self.eps)
        out[self.coarse] += self.lam[self.coarse] * zc
        return out

    def _coarse_solve(self, rc):
        """z_C ~ (Phi_CC + Lambda_C)^{-1} r_C: Cholesky, or a few nested FGMRES steps."""
        if self.factor is not None:
            return coarse_solve(self.factor, rc)
        sub, lam, e = self._sub, self._sub_lam, self._sub_eps

        def product(v, rel=1.0):
            return sub.matvec(v, eps=e) + lam * v

        z, *_ = fgmres(product, rc, self.inner_level, self._sub_rtol, self.nested, self.nested, product, final=False)
        return z

    def __call__(self, r):
        zc = self._coarse_solve(r[self.coarse])
        z = np.zeros_like(r)
        if self.exact:
            z[self.coarse] = zc
            return z
        z[self.coarse] = zc
        r2 = r - self._coarse_to_fine(zc)
        z += _cg(self.near, self.near_diag, r2, self.inner)
        if self.post_rows is not None:
            c = self.coarse
            left = r[c] - self.post_rows(z) - self.lam[c] * z[c]
            z[c] += self._coarse_solve(left)
        return z


def _cg(a, diag, b, steps):
    """``steps`` Jacobi-preconditioned CG iterations for a x = b from x = 0."""
    x = np.zeros_like(b)
    r = b.copy()
    z = r / diag
    p = z.copy()
    rz = r @ z
    if rz == 0:
        return x
    for _ in range(steps):
        ap = csr_matvec(a, p) if sp.isspmatrix_csr(a) else a @ p
        alpha = rz / (p @ ap)
        x += alpha * p
        r -= alpha * ap
        z = r / diag
        rz_new = r @ z
        if rz_new <= 1e-30 * rz:
            break
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x
