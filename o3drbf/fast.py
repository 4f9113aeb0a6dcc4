"""Fast kernel sums and a preconditioned Krylov solve for large N.

Three pieces, each usable on its own:

- :class:`FastSum` -- ``sum_j w_j phi(|x - c_j|)`` at the centres (the
  matrix-vector product of the fit) or at arbitrary targets, with gradients,
  in O(N log N) time and O(N) memory;
- :func:`solve` -- the saddle-point system of :mod:`o3drbf.solve` by
  flexible GMRES with a two-level preconditioner (called by
  ``o3drbf.solve.solve(method="fast")``);
- :func:`make_evaluator` -- a callable for ``ImplicitSurface.evaluator``.

Notes
-----
**Multi-order kernel.**  With ``a, b = kernel.decay_rates`` and
``A, B = kernel.coefficients``,

    phi(r) = (1 + A e^{-a r} + B e^{-b r}) / (4 pi delta^2 r),

a Laplace potential plus two screened-Coulomb (Yukawa) terms.  fmm3dpy's
``lfmm3d`` sums ``c_j / (4 pi r)`` and ``hfmm3d`` with ``zk = 1j a`` sums
``c_j e^{-a r} / (4 pi r)``; both include the ``1/(4 pi)`` and skip the
self-interaction (and any pair closer than ~1e-15), so

    (Phi w)_i = [lfmm(w) + A hfmm_a(w) + B hfmm_b(w)]_i / delta^2 + phi(0) w_i.

- The short-range term (rate a ~ 1/tau, weight |A| ~ (delta tau)^2) is a
  sparse matrix in disguise: it is truncated where ``|A| e^{-a r}/(4 pi
  delta^2 r) < eps phi(0)`` and summed from a KD-tree neighbour list
  (exactly, in float64), unless that list would exceed ``sparse_budget``
  entries, in which case it is one more FMM at tolerance ``eps / |A|``.
- When ``4 tau^2 delta^2 > 1`` the rates and weights are complex
  conjugates: ``A e^{-ar} + B e^{-br} = 2 Re(A e^{-ar})`` is ONE complex-
  wavenumber Helmholtz FMM.
- At or near the confluent point ``4 tau^2 delta^2 = 1`` the weights A, B
  blow up and cancel (|A| ~ 1 / gap); when ``max(|A|, |B|) > 1e3`` (or
  exactly confluent) the fast path refuses with a message (change tau by
  ~1%, or solve densely).

**Gaussian.**  exp(-(r/sigma)^2) is truncated at ``r = sigma
sqrt(ln(10/eps))`` and applied as a sparse matrix.  **Thin-plate** r^3 has
no fast path here: products are direct (O(N^2) time, O(N) memory).

**Solve.**  FGMRES on the full saddle-point system ``[Phi + Lambda, Q; Q^T,
0]`` with a right *constraint* preconditioner: given an approximate inverse
M of ``Phi + Lambda``, ``p = (Q^T M Q)^{-1} (Q^T M r - t)``, ``w = M r - (M Q)
p``, so every search direction satisfies ``Q^T w = t`` and the iterates
satisfy the polynomial constraint ``Q^T w = 0`` to rounding (the constant
p0 is solved for, not projected away).  M is two-level multiplicative:

1. coarse: a uniform subset C of about N/8 centres (at most ``max_coarse``),
   the exact kernel system on C factored by Cholesky:
   ``z_C = (Phi_CC + Lambda_C)^{-1} r_C``;
2. residual update ``r' = r - (Phi + Lambda)[:, C] z_C`` (dense block when
   small, else a fast sum from the coarse centres);
3. local: ``z += S^{-1} r'`` with S the near-field matrix of the *tapered*
   kernel ``phi(r) - phi(R)`` on the k = 64 nearest neighbours (positive
   definite, unlike a plain cut-off), its diagonal damped by 1.5, solved by
   10 Jacobi-preconditioned CG steps.

Measured (delta 10, tau 0.01, torus + 10% exterior, FGMRES to 1e-6, dense
products so that only the preconditioner varies): near-field alone 16 / 28 /
37 iterations at N = 2k / 8k / 16k; with the coarse level (|C| = N/8) and an
undamped near field 9 / 20 / -; damped by 1.5: 7-8 / 8-9 / 10.  The count
depends on N / |C| (16k with |C| = 1000: 13), so beyond ``8 * max_coarse``
(48,000) it grows slowly (30k: 14 with FMM products; delta 3.16: 11 at 2k and
8k).  Exact (sparse LU) local solves gave the same counts as 10 CG steps but
took 77 s with 22x fill-in at 30k, hence CG.

Product accuracy is relaxed as the residual falls (inexact Krylov, Bouras &
Fraysse 2005): the FMM tolerance for an Arnoldi step is
``eps * ||r_0|| / ||r_j||`` (at most 1e-3), and each restart recomputes the
true residual at full accuracy, so the reported residual is real.
"""

from __future__ import annotations

import math
import os
import time
import warnings

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .kernels import Gaussian, Kernel, MultiOrder
from .solve import ConvergenceWarning, Solution, available_memory
from .sums import kernel_matrix, kernel_sum, polynomial_basis

__all__ = ["FastSum", "TwoLevel", "solve", "make_evaluator", "fast_memory", "default_workers", "DEFAULT_EPS"]

#: Default relative tolerance of fast sums (evaluation).
DEFAULT_EPS = 1e-6
#: Neighbour-list entries above which a short-range term goes to the FMM instead.
SPARSE_BUDGET = 100_000_000
#: Loosest product tolerance the relaxation may reach.
RELAX_CAP = 1e-3
#: Pairs handled per chunk when building neighbour lists / summing sparse terms.
_PAIR_CHUNK = 8_000_000
#: Bytes of FMM working memory per point (measured ~7.4 kB at 1e-6, fmm3dpy 2.1).
_FMM_BYTES_PER_POINT = 8_000
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
    return _POOL


def default_workers() -> int:
    """Processes for the FMM terms: ``O3DRBF_FMM_WORKERS`` (1 or 2; default 1).

    2 runs the last Yukawa sum in a forked helper process, concurrently with
    the Laplace one: worth it only on idle cores (on the shared 2-core
    machine, under load, a 30k product took 11.3 s with 2 vs 9.8 s with 1)."""
    raw = os.environ.get("O3DRBF_FMM_WORKERS") or "1"
    try:
        return 2 if int(raw) >= 2 else 1
    except ValueError:
        return 1


def _clip_eps(eps: float) -> float:
    return float(min(max(eps, 1e-13), 1e-2))


# --------------------------------------------------------------------------------------
# neighbour lists
# --------------------------------------------------------------------------------------
def _pairs_chunks(tree_s: cKDTree, targets: np.ndarray, radius: float, per_target: float):
    """Yield (offset, i, j, r) for target chunks: all sources within ``radius`` of each target."""
    m = len(targets)
    step = max(1, int(_PAIR_CHUNK / max(per_target, 1.0)))
    for start in range(0, m, step):
        t = targets[start : start + step]
        tt = cKDTree(t)
        arr = tt.sparse_distance_matrix(tree_s, radius, output_type="ndarray")
        yield start, len(t), arr["i"].astype(np.int64), arr["j"].astype(np.int64), arr["v"]


def _mean_neighbours(tree_s: cKDTree, targets: np.ndarray, radius: float, sample: int = 2000) -> float:
    """Average number of sources within ``radius`` of a target (from a sample)."""
    if len(targets) == 0:
        return 0.0
    rng = np.random.default_rng(0)
    idx = rng.choice(len(targets), min(sample, len(targets)), replace=False)
    counts = tree_s.query_ball_point(targets[idx], radius, return_length=True)
    return float(np.mean(counts))


def _sparse_matrix(tree_s, targets, radius, value, per_target, n_sources, drop_self=False):
    """CSR matrix of ``value(r, i, j)`` over all (target i, source j) pairs with r <= radius."""
    blocks = []
    for start, m, i, j, r in _pairs_chunks(tree_s, targets, radius, per_target):
        if drop_self:
            keep = (i + start) != j
            i, j, r = i[keep], j[keep], r[keep]
        v = value(r, i + start, j)
        blocks.append(sp.csr_matrix((v, (i, j)), shape=(m, n_sources)))
    if not blocks:
        return sp.csr_matrix((0, n_sources))
    return sp.vstack(blocks, format="csr")


# --------------------------------------------------------------------------------------
# fast sums
# --------------------------------------------------------------------------------------
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
        self.eps = _clip_eps(eps)
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
        per = _mean_neighbours(self.tree, self.centres, radius)
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
            self._short_m = _sparse_matrix(
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
        eps = _clip_eps(eps)
        jobs = [("l", eps, None, np.ascontiguousarray(w, dtype=float), 1.0)]
        for zk, coef, pair in self._terms:
            e = min(_clip_eps(eps / max((2.0 if pair else 1.0) * abs(coef), 1e-300)), 1e-2)
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
        per = _mean_neighbours(self.tree, self.centres, radius)
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
            self._matrix_m = _sparse_matrix(
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
        per = _mean_neighbours(tree, targets, radius, sample=500)
        for start, mm, i, j, r in _pairs_chunks(tree, targets, radius, per):
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


# --------------------------------------------------------------------------------------
# preconditioner
# --------------------------------------------------------------------------------------
def _uniform_subset(points: np.ndarray, count: int) -> np.ndarray:
    """About ``count`` indices spread uniformly over the points (one per voxel)."""
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
        key = np.floor((points - lo) / h).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        if best is None or abs(len(first) - count) < abs(len(best) - count):
            best = first
        if len(first) > count:
            lo_h = h
        else:
            hi_h = h
        if abs(len(first) - count) <= 0.05 * count:
            break
    return np.sort(best)


class TwoLevel:
    """Two-level multiplicative preconditioner for ``Phi + diag(lam)``.

    Parameters
    ----------
    fast : FastSum
        The operator (its centres and kernel).
    lam : (N,) array
    neighbours : int
        k of the tapered near-field matrix.
    coarse_ratio, max_coarse : int
        Coarse level size ``min(N / coarse_ratio, max_coarse)``.
    inner : int
        CG steps on the near-field matrix.
    damping : float
        The near-field diagonal phi(0) - phi(R) is multiplied by this (a
        damped local step after the coarse correction; 1.5 measured best:
        at N = 8,000 1.0 needs 20 iterations, 1.5 needs 9, 2 needs 10, 3 needs 11).
    exact_below : int
        Up to this N the "coarse" level is all centres: an exact Cholesky
        preconditioner (one iteration).
    select : {"uniform", "random"}
        How the coarse centres are picked (one per voxel, or at random).
    eps : float
        Tolerance of the coarse-to-fine residual update (when not dense):
        1e-2 gave the same counts as 1e-4 (8k: 6 to 1e-5) in 35% less time.
    dense_budget : int
        Bytes allowed for storing the (N, |C|) coarse-to-fine block.
    """

    def __init__(self, fast: FastSum, lam, neighbours=64, coarse_ratio=8, max_coarse=6000, inner=10,
                 eps=1e-2, dense_budget=256 * 2**20, select="uniform", exact_below=3000, damping=1.5):
        kernel, x = fast.kernel, fast.centres
        n = len(x)
        self.fast, self.lam, self.inner, self.eps = fast, np.asarray(lam, float), int(inner), eps
        t0 = time.perf_counter()
        # Near field: tapered kernel phi(r) - phi(R) on ~k neighbours.
        k = min(neighbours, n - 1)
        if k >= 1:
            d, _ = fast.tree.query(x, k=k + 1)
            radius = float(np.median(d[:, -1]))
            phir = float(kernel(np.array([radius]))[0])
            s = _sparse_matrix(
                fast.tree, x, radius, lambda r, i, j: kernel(r) - phir, k + 1, n, drop_self=True
            )
            diag = damping * (fast.phi0 - phir) + self.lam
        else:
            radius, s, diag = 0.0, sp.csr_matrix((n, n)), fast.phi0 + self.lam
        self.near = (s + sp.diags(diag)).tocsr()
        self.near_diag = np.asarray(diag, dtype=float)
        self.radius = radius
        # Coarse level.
        mc = n if n <= exact_below else min(max(n // coarse_ratio, 1), max_coarse, n)
        if select == "random" and mc < n:
            self.coarse = np.sort(np.random.default_rng(0).choice(n, mc, replace=False))
        else:
            self.coarse = _uniform_subset(x, mc)
        xc = x[self.coarse]
        acc = kernel_matrix(kernel, xc)
        acc[np.diag_indices(len(xc))] += self.lam[self.coarse]
        self.factor = sla.cho_factor(acc, lower=True, overwrite_a=True, check_finite=False)
        del acc
        self.exact = len(self.coarse) == n
        self.block = None
        self.update = None
        if not self.exact and n * len(self.coarse) * 8 <= dense_budget:
            self.block = kernel_matrix(kernel, x, xc, order="C")
        elif not self.exact:
            self.update = fast.from_subset(self.coarse)
        self.setup_seconds = time.perf_counter() - t0
        self.info = {
            "near_neighbours": k,
            "near_radius": radius,
            "near_nnz": int(self.near.nnz),
            "coarse": len(self.coarse),
            "coarse_update": "exact" if self.exact else ("dense block" if self.block is not None else "fast sum"),
            "setup_seconds": self.setup_seconds,
        }

    def _coarse_to_fine(self, zc):
        """(Phi + Lambda)[:, C] z_C."""
        if self.block is not None:
            out = self.block @ zc
        else:
            out = self.update(zc, self.eps)
        out[self.coarse] += self.lam[self.coarse] * zc
        return out

    def __call__(self, r):
        zc = sla.cho_solve(self.factor, r[self.coarse], check_finite=False)
        z = np.zeros_like(r)
        if self.exact:
            z[self.coarse] = zc
            return z
        z[self.coarse] = zc
        r2 = r - self._coarse_to_fine(zc)
        z += _cg(self.near, self.near_diag, r2, self.inner)
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
        ap = a @ p
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


# --------------------------------------------------------------------------------------
# FGMRES
# --------------------------------------------------------------------------------------
def _fgmres(matvec, b, prec, rtol, max_iterations, restart, true_matvec, bar=None):
    """Flexible GMRES (right preconditioned), restarted from the true residual.

    ``matvec(x, rel)`` may be inexact with relative accuracy ``rel`` (relaxed
    as the residual falls); ``true_matvec`` is the accurate product used at
    every restart.  Returns x, iterations, true relative residual, history.
    """
    n = len(b)
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return np.zeros(n), 0, 0.0, []
    x = np.zeros(n)
    r = b.copy()
    beta = bn
    its = 0
    history = []
    while True:
        if beta <= rtol * bn or its >= max_iterations:
            return x, its, beta / bn, history
        m = min(restart, max_iterations - its)
        V = np.empty((m + 1, n))
        Z = np.empty((m, n))
        H = np.zeros((m + 1, m))
        V[0] = r / beta
        g = np.zeros(m + 1)
        g[0] = beta
        cs, sn = np.zeros(m), np.zeros(m)
        est = beta
        j_used = 0
        for j in range(m):
            Z[j] = prec(V[j])
            # Relaxed accuracy: eps * ||r_0|| / ||r_j|| (inexact Krylov).
            w = matvec(Z[j], bn / max(est, 1e-300))
            its += 1
            for i in range(j + 1):  # modified Gram-Schmidt, twice for safety
                H[i, j] = w @ V[i]
                w -= H[i, j] * V[i]
            for i in range(j + 1):
                c = w @ V[i]
                H[i, j] += c
                w -= c * V[i]
            hnext = float(np.linalg.norm(w))
            H[j + 1, j] = hnext
            if hnext > 0:
                V[j + 1] = w / hnext
            for i in range(j):  # apply previous Givens rotations
                t = cs[i] * H[i, j] + sn[i] * H[i + 1, j]
                H[i + 1, j] = -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
                H[i, j] = t
            den = math.hypot(H[j, j], H[j + 1, j])
            cs[j], sn[j] = (1.0, 0.0) if den == 0 else (H[j, j] / den, H[j + 1, j] / den)
            H[j, j] = den
            H[j + 1, j] = 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            est = abs(g[j + 1])
            history.append(est / bn)
            j_used = j + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(residual=f"{est / bn:.1e}")
            if est <= rtol * bn or hnext == 0:
                break
        y = sla.solve_triangular(H[:j_used, :j_used], g[:j_used], check_finite=False)
        x = x + Z[:j_used].T @ y
        del V, Z
        r = b - true_matvec(x)
        beta = float(np.linalg.norm(r))
        if est <= rtol * bn and beta > rtol * bn and history and history[-1] < 1e-3 * beta / bn:
            # The recurrence converged but the true residual did not move:
            # the products are not accurate enough to go further.
            return x, its, beta / bn, history


# --------------------------------------------------------------------------------------
# memory
# --------------------------------------------------------------------------------------
def fast_memory(n: int, restart: int = 50, eps: float = 1e-6) -> int:
    """Rough peak bytes of a fast solve with ``n`` constraints."""
    fmm = _FMM_BYTES_PER_POINT * n * (1.0 if eps <= 1e-6 else 0.6)
    krylov = 2 * (restart + 2) * n * 8
    sparse = 12 * n * (64 + 300)  # near field + typical short-range list
    coarse = 8 * 6000**2 + 256 * 2**20
    return int(fmm + krylov + sparse + coarse)


# --------------------------------------------------------------------------------------
# solve
# --------------------------------------------------------------------------------------
def solve(
    kernel: Kernel,
    centres,
    y,
    lam,
    rtol: float = 1e-6,
    max_iterations: int = 200,
    progress: bool = False,
    eps: float | None = None,
    restart: int = 50,
    memory_limit: int | None = None,
    preconditioner: dict | None = None,
    relax: bool = True,
    operator: FastSum | None = None,
) -> Solution:
    """Solve ``[Phi + diag(lam), Q; Q^T, 0] [w; p] = [y; 0]`` with fast products.

    Parameters
    ----------
    kernel : MultiOrder or Gaussian (ThinPlate is refused: use method='dense')
    centres : (N, 3) array
    y, lam : (N,) arrays
    rtol : float
        Relative residual ``||K x - b|| / ||b||`` to reach.
    max_iterations : int
        FGMRES iterations (fast products) at most.
    progress : bool
        tqdm bar with iterations and residual.
    eps : float, optional
        Tolerance of the fast products at full accuracy; default ``rtol / 10``
        (fmm3dpy delivers ~eps / 30 relative error).
    restart : int
        FGMRES restart length.
    memory_limit : int, optional
        Bytes; default 80% of available memory.  Checked before starting.
    preconditioner : dict, optional
        Keyword arguments of :class:`TwoLevel`.
    relax : bool
        Loosen the product tolerance as the residual falls (inexact Krylov).
    operator : FastSum, optional
        A prebuilt product for these centres (or any object with its
        interface, e.g. a dense stand-in for testing the preconditioner).

    Returns
    -------
    Solution
        ``info`` holds the split, the preconditioner's sizes, setup and solve
        seconds, the residual history and ``constraint`` = ``|Q^T w|``.

    Warns
    -----
    ConvergenceWarning
        When ``rtol`` is not reached; the message gives the residual reached.
    """
    t0 = time.perf_counter()
    if not isinstance(kernel, (MultiOrder, Gaussian)):
        raise ValueError(
            f"the fast solver supports the multiorder and gaussian bases, not {kernel.name}; "
            "use method='dense' or 'iterative'"
        )
    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    y = np.asarray(y, dtype=float)
    lam = np.broadcast_to(np.asarray(lam, dtype=float), (n,)).copy()
    rtol = float(rtol)
    eps = _clip_eps(rtol / 10.0 if eps is None else eps)
    limit = int(0.8 * available_memory()) if memory_limit is None else int(memory_limit)
    need = fast_memory(n, restart, eps)
    if need > limit:
        raise MemoryError(
            f"a fast solve of {n} constraints needs about {need / 2**30:.1f} GB but the limit is "
            f"{limit / 2**30:.1f} GB; subsample the constraints (surface_count) or raise memory_limit"
        )
    q = polynomial_basis(centres, kernel.polynomial_degree)
    m = q.shape[1]
    t_setup = time.perf_counter()
    fast = FastSum(kernel, centres, eps=eps) if operator is None else operator
    prec_a = TwoLevel(fast, lam, **(preconditioner or {}))
    # Constraint preconditioner: exact elimination of p with M ~ (Phi + Lambda)^{-1}.
    mq = np.column_stack([prec_a(q[:, k]) for k in range(m)]) if m else np.zeros((n, 0))
    s = q.T @ mq
    setup_seconds = time.perf_counter() - t_setup

    def prec(v):
        r, t = v[:n], v[n:]
        mr = prec_a(r)
        if not m:
            return mr
        p = np.linalg.solve(s, q.T @ mr - t)
        return np.concatenate([mr - mq @ p, p])

    def product(v, rel):
        w, p = v[:n], v[n:]
        e = max(eps, min(RELAX_CAP, eps * rel)) if relax else eps
        top = fast.matvec(w, eps=e) + lam * w + q @ p
        return np.concatenate([top, q.T @ w])

    b = np.concatenate([y, np.zeros(m)])
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=max_iterations, desc="fast FGMRES", unit="it", leave=False,
                   disable=os.environ.get("O3DRBF_NO_PROGRESS") == "1")
    t_solve = time.perf_counter()
    try:
        x, its, res, history = _fgmres(product, b, prec, rtol, max_iterations, restart,
                                       lambda v: product(v, 1.0), bar)
    finally:
        if bar is not None:
            bar.close()
    w, p = x[:n], x[n:]
    info = {
        "split": fast.info,
        "preconditioner": prec_a.info,
        "eps": eps,
        "setup_seconds": setup_seconds,
        "solve_seconds": time.perf_counter() - t_solve,
        "history": history,
        "constraint": float(np.abs(q.T @ w).max()) if m else 0.0,
        "converged": res <= rtol,
    }
    if res > rtol:
        warnings.warn(
            f"fast solve reached relative residual {res:.2e} > rtol {rtol:.1e} after {its} iterations; "
            "raise max_iterations, loosen rtol, or use method='dense' where it fits",
            ConvergenceWarning,
            stacklevel=3,
        )
    return Solution(w, p, "fast", float(res), time.perf_counter() - t0, its, info)


# --------------------------------------------------------------------------------------
# evaluator
# --------------------------------------------------------------------------------------
def make_evaluator(kernel: Kernel, centres, weights, eps: float = DEFAULT_EPS, chunk: int = 1_000_000):
    """A callable ``(points (M, 3), gradient) -> values (M,) [, grads (M, 3)]`` for
    ``ImplicitSurface.evaluator``: ``sum_i w_i phi(|x - c_i|)`` without the
    polynomial, by FMM with targets (multi-order), sparse sums (Gaussian) or
    direct sums (thin-plate).  Targets are processed ``chunk`` at a time."""
    fast = FastSum(kernel, centres, eps=eps)
    weights = np.ascontiguousarray(weights, dtype=float)
    if weights.shape != (fast.n,):
        raise ValueError(f"weights must have shape ({fast.n},), got {weights.shape}")

    def evaluator(points, gradient=False):
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(pts) <= chunk:
            return fast.evaluate(weights, pts, gradient=gradient)
        parts = [fast.evaluate(weights, pts[s : s + chunk], gradient=gradient) for s in range(0, len(pts), chunk)]
        if gradient:
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return np.concatenate(parts)

    evaluator.fast_sum = fast
    return evaluator
