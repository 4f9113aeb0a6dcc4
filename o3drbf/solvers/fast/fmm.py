"""Fast sums by fmm3dpy: :class:`FastSum` (Laplace + Yukawa FMMs, a sparse short-range term) and its helper process."""

from __future__ import annotations

import math
import os

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.rbf.kernels import Gaussian, Kernel, MultiOrder
from o3drbf.rbf.sums import kernel_sum
from o3drbf.solvers.fast.neighbours import mean_neighbours, pairs_chunks, sparse_matrix
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS, clip_eps

__all__ = ["FastSum", "default_workers", "SPARSE_BUDGET"]

#: Neighbour-list entries above which a short-range term goes to the FMM instead.
SPARSE_BUDGET = 100_000_000
# Pairs closer than this (relative to the box) count as coincident: the FMM
# skips them, so phi(0) is added explicitly.
_COINCIDENT = 1e-12


def _fmm3d():
    try:
        import fmm3dpy
    except ImportError:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the fast solver needs fmm3dpy (pip install 'o3drbf[fast]' or pip install fmm3dpy)"
        ) from None
    return fmm3dpy


def _fmm_call(kind, eps, zk, src, charges, targets, gradient):
    """One fmm3dpy sum: ``(pot, grad)`` at the sources (targets None) or at the targets."""
    fmm = _fmm3d()
    kw = dict(pg=2 if gradient else 1) if targets is None else dict(targets=targets, pgt=2 if gradient else 1)
    if kind == "l":
        out = fmm.lfmm3d(eps=eps, sources=src, charges=charges, **kw)
    else:
        out = fmm.hfmm3d(eps=eps, zk=zk, sources=src, charges=charges, **kw)
    pot = out.pot if targets is None else out.pottarg
    grad = (out.grad if targets is None else out.gradtarg) if gradient else None
    return pot, grad


_POOL = None


def _pool():
    """A persistent one-process pool that runs an FMM beside the main process.

    fmm3dpy's wheel is single-threaded and holds the GIL, so the Laplace and
    Yukawa sums run concurrently only in separate processes."""
    global _POOL
    if _POOL is None:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # fork (not spawn/forkserver): no re-import of the user's __main__.
        _POOL = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("fork"))
        import atexit

        atexit.register(_close_pool)
    return _POOL


def _close_pool() -> None:
    """Shut the helper process down at exit, while the modules it needs still exist
    (otherwise the executor's clean-up runs during interpreter teardown and prints a traceback)."""
    global _POOL
    pool, _POOL = _POOL, None
    if pool is not None:
        pool.shutdown(wait=True, cancel_futures=True)


def default_workers() -> int:
    """Processes for the FMM terms: ``O3DRBF_FMM_WORKERS`` (1 or 2; default 1).

    2 runs the last Yukawa sum in a forked helper process, concurrently with
    the Laplace one: worth it only on idle cores."""
    raw = os.environ.get("O3DRBF_FMM_WORKERS") or "1"
    try:
        return 2 if int(raw) >= 2 else 1
    except ValueError:
        return 1


class FastSum:
    """Fast ``sum_j w_j phi(|x - c_j|)`` for one set of centres.

    Parameters
    ----------
    kernel : MultiOrder, Gaussian or ThinPlate
    centres : (N, 3) array
    eps : float
        Relative tolerance of the sums (FMM precision; truncation of the
        sparse terms).  Products may be asked for at a looser tolerance,
        never a tighter one than the sparse terms were built for.
    sparse_budget : int
        Largest neighbour list (entries) for a sparse short-range term.

    Raises
    ------
    ValueError
        Multi-order kernel at or near the confluent point 4 tau^2 delta^2 = 1,
        or a Gaussian too wide for a sparse matrix of ``sparse_budget`` entries.
    """

    def __init__(self, kernel: Kernel, centres, eps: float = DEFAULT_EPS, sparse_budget: int = SPARSE_BUDGET,
                 workers: int | None = None):
        self.kernel = kernel
        self.workers = default_workers() if workers is None else int(workers)
        self.centres = np.ascontiguousarray(centres, dtype=float)
        self.n = len(self.centres)
        self.eps = clip_eps(eps)
        self.sparse_budget = int(sparse_budget)
        self._src = np.ascontiguousarray(self.centres.T)
        self.tree = cKDTree(self.centres)
        self.phi0 = float(kernel.value_at_zero)
        span = float(np.ptp(self.centres, axis=0).max()) if self.n > 1 else 1.0
        self._tiny = _COINCIDENT * max(span, 1e-300)
        self.info: dict = {}
        if isinstance(kernel, MultiOrder):
            self._setup_multiorder()
        elif isinstance(kernel, Gaussian):
            self._setup_gaussian()
        else:
            self.mode = "direct"
            self.info["mode"] = "direct (no fast path for this kernel)"

    # -- multi-order ------------------------------------------------------------------
    def _setup_multiorder(self):
        k = self.kernel
        self.mode = "fmm"
        if k.coefficients is None:
            raise ValueError(
                f"{k!r} is at the confluent point 4 tau^2 delta^2 = 1, where the fast multipole "
                "split into Yukawa terms breaks down; change tau by ~1% or use method='dense'"
            )
        a, b = k.decay_rates
        A, B = k.coefficients
        if max(abs(A), abs(B)) > 1e3:
            raise ValueError(
                f"{k!r} is too close to the confluent point 4 tau^2 delta^2 = 1 (split weights "
                f"|A| = {abs(A):.1e} cancel); change tau by ~1% or use method='dense'"
            )
        self._scale = 1.0 / k.delta**2  # fmm3dpy includes 1/(4 pi)
        self._c = 4.0 * math.pi * k.delta**2
        # terms: (zk, coefficient, take 2 Re?)
        self._short_sparse = False
        self._short_m = None
        if abs(a.imag) > 0:
            self._terms = [(1j * a, A, True)]
            self.info["split"] = "laplace + 1 complex Yukawa pair"
            return
        a, b, A, B = a.real, b.real, A.real, B.real
        if a < b:
            a, b, A, B = b, a, B, A
        self._terms = [(1j * b, B, False)]
        # Short-range term a: truncation radius for this eps.
        tol = self.eps * self.phi0
        radius = 10.0 / a
        for _ in range(30):
            radius = max(math.log(max(abs(A) / (self._c * radius * tol), 1.0 + 1e-12)) / a, 1e-12)
        self._short_radius = radius
        self._short_coef = (a, A)
        per = mean_neighbours(self.tree, self.centres, radius)
        est = per * self.n
        self.info["short_radius"] = radius
        self.info["short_neighbours"] = per
        if est <= self.sparse_budget:
            self._short_sparse = True  # the centre-centre matrix is built on first use
            self.info["split"] = "laplace + medium Yukawa by FMM, short Yukawa sparse"
        else:
            self._terms.append((1j * a, A, False))
            self.info["split"] = "laplace + 2 Yukawa by FMM (short-range list over budget)"

    @property
    def _short(self):
        """Sparse centre-centre matrix of the short-range Yukawa term (None if by FMM)."""
        if self.mode != "fmm" or not self._short_sparse:
            return None
        if self._short_m is None:
            per = self.info["short_neighbours"]
            self._short_m = sparse_matrix(
                self.tree, self.centres, self._short_radius, self._short_value, per, self.n, drop_self=True
            )
            self.info["short_nnz"] = int(self._short_m.nnz)
        return self._short_m

    def _short_value(self, r, i=None, j=None):
        a, A = self._short_coef
        out = np.empty_like(r)
        far = r > self._tiny
        out[far] = A * np.exp(-a * r[far]) / (self._c * r[far])
        out[~far] = self.phi0  # coincident pair: the FMM skipped it entirely
        return out

    def _short_grad_coef(self, r):
        """d/dr [A e^{-ar}/(C r)] / r."""
        a, A = self._short_coef
        out = np.zeros_like(r)
        far = r > self._tiny
        rf = r[far]
        out[far] = -A * (1.0 + a * rf) * np.exp(-a * rf) / (self._c * rf**3)
        return out

    def _fmm(self, w, eps, targets=None, gradient=False, sources=None):
        """Laplace + Yukawa terms (scaled, without self / coincident pairs)."""
        src = self._src if sources is None else sources
        eps = clip_eps(eps)
        jobs = [("l", eps, None, np.ascontiguousarray(w, dtype=float), 1.0)]
        for zk, coef, pair in self._terms:
            e = min(clip_eps(eps / max((2.0 if pair else 1.0) * abs(coef), 1e-300)), 1e-2)
            jobs.append(("h", e, zk, np.ascontiguousarray(coef * w, dtype=complex), 2.0 if pair else 1.0))
        futures = []
        if self.workers >= 2 and len(jobs) >= 2:
            # The last (Yukawa) sum in a helper process, the rest here.
            kind, e, zk, ch, f = jobs[-1]
            try:
                futures = [(_pool().submit(_fmm_call, kind, e, zk, src, ch, targets, gradient), f, jobs[-1])]
                jobs = jobs[:-1]
            except Exception:  # no processes available: stay serial
                self.workers = 1
        pot = np.zeros(src.shape[1] if targets is None else targets.shape[1])
        grad = np.zeros((3, len(pot))) if gradient else None
        results = [(_fmm_call(kind, e, zk, src, ch, targets, gradient), f) for kind, e, zk, ch, f in jobs]
        for fut, f, job in futures:
            try:
                results.append((fut.result(), f))
            except Exception:  # broken helper process: redo it here, stay serial from now on
                global _POOL
                _POOL = None
                self.workers = 1
                kind, e, zk, ch, _ = job
                results.append((_fmm_call(kind, e, zk, src, ch, targets, gradient), f))
        for (p, g), f in results:
            pot += f * p.real
            if gradient:
                grad += f * g.real
        pot *= self._scale
        if gradient:
            grad *= self._scale
            return pot, grad
        return pot

    # -- Gaussian ---------------------------------------------------------------------
    def _setup_gaussian(self):
        self.mode = "sparse"
        sigma = self.kernel.sigma
        radius = sigma * math.sqrt(math.log(10.0 / self.eps))
        per = mean_neighbours(self.tree, self.centres, radius)
        if per * self.n > self.sparse_budget:
            raise ValueError(
                f"Gaussian sigma={sigma:g} reaches ~{per:.0f} neighbours per centre "
                f"({per * self.n:.1e} matrix entries > budget {self.sparse_budget:.0e}); "
                "use a smaller sigma, fewer constraints, or method='dense'"
            )
        self._radius = radius
        self._gauss_per = per
        self._matrix_m = None
        self.info.update(mode="sparse Gaussian", radius=radius)

    @property
    def _matrix(self):
        """Sparse centre-centre Gaussian matrix, built on first use."""
        if self._matrix_m is None:
            kern = self.kernel
            self._matrix_m = sparse_matrix(
                self.tree, self.centres, self._radius, lambda r, i, j: kern(r), self._gauss_per, self.n
            )
            self.info["nnz"] = int(self._matrix_m.nnz)
        return self._matrix_m

    # -- public -----------------------------------------------------------------------
    def matvec(self, w, eps: float | None = None) -> np.ndarray:
        """(Phi w)_i = sum_j w_j phi(|c_i - c_j|), self term included."""
        w = np.asarray(w, dtype=float)
        if self.mode == "sparse":
            return self._matrix @ w
        if self.mode == "direct":
            return kernel_sum(self.kernel, self.centres, w, self.centres)
        eps = self.eps if eps is None else max(float(eps), self.eps)
        out = self._fmm(w, eps)
        out += self.phi0 * w
        if self._short is not None:
            out += self._short @ w
        return out

    def evaluate(self, w, targets, gradient: bool = False, eps: float | None = None, subset=None):
        """sum_j w_j phi(|x - c_j|) (and its gradient) at arbitrary targets.

        ``subset`` (indices into the centres) restricts the sum to those centres
        (``w`` then has one entry per subset index).
        """
        targets = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        w = np.asarray(w, dtype=float)
        cen = self.centres if subset is None else self.centres[subset]
        m = len(targets)
        if m == 0:
            return (np.zeros(0), np.zeros((0, 3))) if gradient else np.zeros(0)
        if self.mode == "direct":
            return kernel_sum(self.kernel, cen, w, targets, gradient=gradient)
        tree = self.tree if subset is None else cKDTree(cen)
        if self.mode == "sparse":
            return self._sparse_eval(tree, cen, w, targets, self._radius, gradient, gauss=True)
        eps = self.eps if eps is None else max(float(eps), self.eps)
        src = np.ascontiguousarray(cen.T)
        out = self._fmm(w, eps, targets=np.ascontiguousarray(targets.T), gradient=gradient, sources=src)
        vals, grads = out if gradient else (out, None)
        if gradient:
            grads = np.ascontiguousarray(grads.T)
        if self._short_sparse:
            v2 = self._sparse_eval(tree, cen, w, targets, self._short_radius, gradient, gauss=False)
        else:
            v2 = self._coincident(tree, w, targets, gradient)
        if gradient:
            return vals + v2[0], grads + v2[1]
        return vals + v2

    def from_subset(self, subset):
        """A callable ``(w_sub, eps) -> sum_{j in subset} w_j phi(|c_i - c_j|)`` at every centre."""
        subset = np.asarray(subset)
        if self.mode == "sparse":
            cols = self._matrix[:, subset].tocsr()
            return lambda w, eps=None: cols @ w
        if self.mode == "direct":
            return lambda w, eps=None: kernel_sum(self.kernel, self.centres[subset], w, self.centres)
        src = np.ascontiguousarray(self._src[:, subset])
        cols = self._short[:, subset].tocsr() if self._short is not None else None

        def apply(w, eps=None):
            e = self.eps if eps is None else max(float(eps), self.eps)
            out = self._fmm(w, e, targets=self._src, sources=src)
            out[subset] += self.phi0 * w  # coincident with their own centre: skipped by the FMM
            if cols is not None:
                out += cols @ w
            return out

        return apply

    def _coincident(self, tree, w, targets, gradient):
        """phi(0) w_j for targets that coincide with a centre (skipped by the FMM)."""
        d, j = tree.query(targets, k=1, distance_upper_bound=self._tiny)
        hit = np.isfinite(d)
        vals = np.zeros(len(targets))
        vals[hit] = self.phi0 * w[j[hit]]
        return (vals, np.zeros((len(targets), 3))) if gradient else vals

    def _sparse_eval(self, tree, cen, w, targets, radius, gradient, gauss):
        m = len(targets)
        vals = np.zeros(m)
        grads = np.zeros((m, 3)) if gradient else None
        per = mean_neighbours(tree, targets, radius, sample=500)
        for start, mm, i, j, r in pairs_chunks(tree, targets, radius, per):
            if gauss:
                v = self.kernel(r)
            else:
                v = self._short_value(r)
            vals[start : start + mm] += np.bincount(i, weights=v * w[j], minlength=mm)
            if gradient:
                g = self.kernel.derivative_over_r(r) if gauss else self._short_grad_coef(r)
                gw = g * w[j]
                diff = targets[start + i] - cen[j]
                for ax in range(3):
                    grads[start : start + mm, ax] += np.bincount(i, weights=gw * diff[:, ax], minlength=mm)
        return (vals, grads) if gradient else vals
