"""Fast kernel sums and a preconditioned Krylov solve for large N.

Four pieces, each usable on its own:

- :class:`GridSum` -- the default product for the multi-order kernel: an
  Ewald-type Gaussian split, far part by FFT on a grid (particle-mesh), near
  part as a sparse matrix; 5-10x faster than fmm3dpy's single-threaded wheel
  (100,000 centres: ~1-3 s a product vs ~30 s), with looser companions for
  relaxed products (see the class notes);
- :class:`FastSum` -- ``sum_j w_j phi(|x - c_j|)`` at the centres (the
  matrix-vector product of the fit) or at arbitrary targets, with gradients,
  in O(N log N) time and O(N) memory, by fmm3dpy (``backend="fmm"``, and the
  automatic choice for eps < 1e-8, the Gaussian and any kernel the grid
  cannot take);
- :func:`solve` -- the saddle-point system of :mod:`o3drbf.solvers` by
  flexible GMRES with a two-level preconditioner (called by
  ``o3drbf.solvers.solve(method="fast")``);
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

**Far centres.**  The grid covers the box of the centres that have a
neighbour within the near-field radius; the few isolated centres beyond it
(the pipeline's sphere of exterior constraints around the bounding box) are
summed directly, both as sources and as targets (:func:`outside_centres`:
at most ``DIRECT_PAIRS`` kernel evaluations a product, or 0.1 % of the
centres).  Otherwise the sphere set the grid's box: at 100,000 constraints
(delta 40, tau 0.005, eps 1e-7) 8.1 GB of FFT arrays, over the then fixed
2 GB budget, and the solve fell
back to fmm3dpy (375-615 s); with the split, 0.41 GB and the grid.  The grid
spacing follows the near-field radius (a neighbour count), not tau.

**Gaussian.**  exp(-(r/sigma)^2) is truncated at ``r = sigma
sqrt(ln(10/eps))`` and applied as a sparse matrix.  **Thin-plate** r^3 has
no fast path here: products are direct (O(N^2) time, O(N) memory).

**Solve.**  FGMRES on the full saddle-point system ``[Phi + Lambda, Q; Q^T,
0]`` with a right *constraint* preconditioner: given an approximate inverse
M of ``Phi + Lambda``, ``p = (Q^T M Q)^{-1} (Q^T M r - t)``, ``w = M r - (M Q)
p``, so every search direction satisfies ``Q^T w = t`` and the iterates
satisfy the polynomial constraint ``Q^T w = 0`` to rounding (the constant
p0 is solved for, not projected away).  M is two-level multiplicative:

1. coarse: a uniform subset C of about N/8 centres, the exact kernel system
   on C factored by Cholesky, ``z_C = (Phi_CC + Lambda_C)^{-1} r_C``, while
   |C| <= ``max_coarse`` (6,000).  Above it, up to N = 144,000 the coarse
   level is capped at 6,000 centres; beyond, the coarse system on N/8
   centres is solved by 8 nested FGMRES steps with products on C (grid /
   FMM at 1e-3) preconditioned by the same scheme on C (recursively: its
   own coarse level is min(N/64, 6,000) centres by Cholesky up to
   N = 1,152,000, nested again beyond);
2. residual update ``r' = r - (Phi + Lambda)[:, C] z_C`` (dense block when
   small, else a fast sum from the coarse centres);
3. local: ``z += S^{-1} r'`` with S the near-field matrix of the *tapered*
   kernel ``phi(r) - phi(R)`` on the k = 64 nearest neighbours (positive
   definite, unlike a plain cut-off), its diagonal damped by 2, solved by
   10 Jacobi-preconditioned CG steps.

Measured (delta 10, tau 0.01, torus + 10% exterior, FGMRES to 1e-6, dense
products so that only the preconditioner varies): near-field alone 16 / 28 /
37 iterations at N = 2k / 8k / 16k; with the coarse level (|C| = N/8) and an
undamped near field 9 / 20 / -; damped by 1.5: 7-8 / 8-9 / 10.  The count
depends on N / |C| (16k with |C| = 1000: 13), so beyond ``8 * max_coarse``
(48,000) it grows slowly (30k: 14 with FMM products; delta 3.16: 11 at 2k and
8k).  Exact (sparse LU) local solves gave the same counts as 10 CG steps but
took 77 s with 22x fill-in at 30k, hence CG.

Scaling (grid products, 2 cores, benchmarks/scale.py; the counts above were
with damping 1.5 and the coarse level capped at 6,000 centres): capped, the
count was 14 / 38 / 16 / 36 at 30k / 50k / 100k / 300k -- the 50k plateau
(residual stuck near 1e-4) was the damping (2.0: 10 iterations; 2.5 and 3.0
no better at 100k), the 300k growth the cap (ratio N / |C| = 50).  The
nested coarse level needs about 8 inner steps: at 100k 3 steps gave 34
iterations, a 1e-2 inner tolerance 30, 8 steps 12 (but the fit took 35.5 s
vs 30.4 s capped, back to back, hence nesting only above 144,000); at 300k
nesting gave 15 iterations and a 146 s fit (5.8 GB peak), vs 36 and 215 s.
A 12,000-centre dense Cholesky took 36 s (16,000: 76 s, 2.1 GB) on the 2
shared cores, hence nesting rather than a larger cap.

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

from o3drbf.progress import progress_bar
from o3drbf.rbf.kernels import Gaussian, Kernel, MultiOrder
from o3drbf.solvers.base import ConvergenceWarning, MemoryRefusal, Solution, memory_limit_or_default
from o3drbf.rbf.sums import kernel_matrix, kernel_sum, polynomial_basis

__all__ = ["FastSum", "TwoLevel", "solve", "make_evaluator", "fast_memory", "default_workers", "DEFAULT_EPS",
           "GridSum", "fast_operator", "grid_bytes", "outside_centres", "GRID_BUDGET", "product_tolerance", "check_memory",
           "grid_budget", "memory_plan", "grid_plan", "split_design", "fitting_fraction", "product_neighbours"]

#: Default relative tolerance of fast sums (evaluation).
DEFAULT_EPS = 1e-6
#: Neighbour-list entries above which a short-range term goes to the FMM instead.
SPARSE_BUDGET = 100_000_000
#: Bytes per stored sparse entry (float64 value, int32 column index).
_NNZ_BYTES = 12
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
    the Laplace one: worth it only on idle cores (on the shared 2-core
    machine, under load, a 30k product took 11.3 s with 2 vs 9.8 s with 1)."""
    raw = os.environ.get("O3DRBF_FMM_WORKERS") or "1"
    try:
        return 2 if int(raw) >= 2 else 1
    except ValueError:
        return 1


def _clip_eps(eps: float) -> float:
    return float(min(max(eps, 1e-13), 1e-2))


def product_tolerance(rtol: float) -> float:
    """The fast products' tolerance :func:`solve` uses for a relative residual ``rtol``."""
    return _clip_eps(float(rtol) / 10.0)


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
# grid (particle-mesh) sums: Gaussian split, FFT far part, sparse near part
# --------------------------------------------------------------------------------------
try:  # numba is a dependency; without it the grid backend is unavailable
    import numba as _numba

    _njit, _prange, HAVE_GRID = _numba.njit, _numba.prange, True
except ImportError:  # pragma: no cover
    _numba, HAVE_GRID = None, False

    def _njit(*a, **k):
        return lambda f: f

    _prange = range

import scipy.fft as _sfft

def _components(kernel):
    """[(kappa, coef)] with phi(r) = sum coef e^{-kappa r} / (4 pi r) (complex allowed)."""
    a, b = kernel.decay_rates
    A, B = kernel.coefficients
    d2 = kernel.delta ** 2
    return [(0.0, 1.0 / d2), (complex(a), complex(A) / d2), (complex(b), complex(B) / d2)]


def _psi_long(r, kappa, sigma):
    """G_sigma * e^{-kappa r}/(4 pi r), times e^{-kappa^2 sigma^2 / 2} (far field = the kernel's)."""
    from scipy.special import erfc, erfcx
    r = np.maximum(np.asarray(r, float), 1e-7 * sigma)
    q = math.sqrt(2.0) * sigma
    x1 = (kappa * sigma**2 - r) / q
    x2 = (kappa * sigma**2 + r) / q
    t1 = np.exp(-kappa * r) * erfc(x1)
    t2 = erfcx(x2) * np.exp(-(kappa * sigma) ** 2 / 2 - r * r / (2 * sigma**2))
    return (t1 - t2) / (8 * math.pi * r)


def long_part(kernel, r, sigma, extra=0.0):
    """sum_c coef_c e^{-kappa_c^2 extra^2 / 2} psi_long(r; kappa_c, sigma)."""
    out = np.zeros(np.shape(r), dtype=complex)
    for kappa, coef in _components(kernel):
        damp = np.exp(-(kappa * extra) ** 2 / 2)
        out += coef * damp * _psi_long(r, kappa + 0j, sigma)
    return out.real


@_njit(cache=True)
def _spread(pts, w, origin, h, s, half, grid):
    W = 2 * half + 1
    c = 1.0 / ((2 * math.pi) ** 1.5 * s ** 3)
    inv = 1.0 / (2 * s * s)
    wx = np.empty(W); wy = np.empty(W); wz = np.empty(W)
    for p in range(pts.shape[0]):
        fx = (pts[p, 0] - origin[0]) / h; fy = (pts[p, 1] - origin[1]) / h; fz = (pts[p, 2] - origin[2]) / h
        ix = int(math.floor(fx + 0.5)) - half; iy = int(math.floor(fy + 0.5)) - half; iz = int(math.floor(fz + 0.5)) - half
        for a in range(W):
            d = (ix + a - fx) * h; wx[a] = math.exp(-d * d * inv)
            d = (iy + a - fy) * h; wy[a] = math.exp(-d * d * inv)
            d = (iz + a - fz) * h; wz[a] = math.exp(-d * d * inv)
        wp = w[p] * c
        for a in range(W):
            va = wp * wx[a]
            for b in range(W):
                vb = va * wy[b]
                for q in range(W):
                    grid[ix + a, iy + b, iz + q] += vb * wz[q]


@_njit(cache=True, parallel=True)
def _gather(pts, origin, h, s, half, u, out, grad, want):
    W = 2 * half + 1
    c = 1.0 / ((2 * math.pi) ** 1.5 * s ** 3)
    inv = 1.0 / (2 * s * s)
    for p in _prange(pts.shape[0]):
        wx = np.empty(W); wy = np.empty(W); wz = np.empty(W)
        dx = np.empty(W); dy = np.empty(W); dz = np.empty(W)
        fx = (pts[p, 0] - origin[0]) / h; fy = (pts[p, 1] - origin[1]) / h; fz = (pts[p, 2] - origin[2]) / h
        ix = int(math.floor(fx + 0.5)) - half; iy = int(math.floor(fy + 0.5)) - half; iz = int(math.floor(fz + 0.5)) - half
        for a in range(W):
            d = (fx - ix - a) * h; wx[a] = math.exp(-d * d * inv); dx[a] = -d / (s * s) * wx[a]
            d = (fy - iy - a) * h; wy[a] = math.exp(-d * d * inv); dy[a] = -d / (s * s) * wy[a]
            d = (fz - iz - a) * h; wz[a] = math.exp(-d * d * inv); dz[a] = -d / (s * s) * wz[a]
        acc = 0.0; g0 = 0.0; g1 = 0.0; g2 = 0.0
        for a in range(W):
            for b in range(W):
                row = 0.0; rowd = 0.0
                for q in range(W):
                    v = u[ix + a, iy + b, iz + q]
                    row += v * wz[q]
                    if want:
                        rowd += v * dz[q]
                acc += wx[a] * wy[b] * row
                if want:
                    g0 += dx[a] * wy[b] * row
                    g1 += wx[a] * dy[b] * row
                    g2 += wx[a] * wy[b] * rowd
        out[p] = c * acc
        if want:
            grad[p, 0] = c * g0; grad[p, 1] = c * g1; grad[p, 2] = c * g2


@_njit(cache=True)
def _cells(pts, lo, cell, dims):
    n = pts.shape[0]
    key = np.empty(n, np.int64)
    for p in range(n):
        i = min(max(int((pts[p, 0] - lo[0]) / cell), 0), dims[0] - 1)
        j = min(max(int((pts[p, 1] - lo[1]) / cell), 0), dims[1] - 1)
        k = min(max(int((pts[p, 2] - lo[2]) / cell), 0), dims[2] - 1)
        key[p] = (i * dims[1] + j) * dims[2] + k
    return key


@_njit(cache=True, parallel=True)
def _near_count(tp, sp_, start, lo, cell, dims, rc):
    m = tp.shape[0]
    cnt = np.zeros(m, np.int64)
    rc2 = rc * rc
    for p in _prange(m):
        i0 = int((tp[p, 0] - lo[0]) / cell); j0 = int((tp[p, 1] - lo[1]) / cell); k0 = int((tp[p, 2] - lo[2]) / cell)
        c = 0
        for i in range(max(i0 - 1, 0), min(i0 + 2, dims[0])):
            for j in range(max(j0 - 1, 0), min(j0 + 2, dims[1])):
                for k in range(max(k0 - 1, 0), min(k0 + 2, dims[2])):
                    key = (i * dims[1] + j) * dims[2] + k
                    for q in range(start[key], start[key + 1]):
                        d0 = tp[p, 0] - sp_[q, 0]; d1 = tp[p, 1] - sp_[q, 1]; d2 = tp[p, 2] - sp_[q, 2]
                        if d0 * d0 + d1 * d1 + d2 * d2 <= rc2:
                            c += 1
        cnt[p] = c
    return cnt


@_njit(cache=True, parallel=True)
def _near_fill(tp, sp_, order, start, lo, cell, dims, rc, indptr, indices, data, tab, dr):
    m = tp.shape[0]
    rc2 = rc * rc
    nt = tab.shape[0]
    for p in _prange(m):
        i0 = int((tp[p, 0] - lo[0]) / cell); j0 = int((tp[p, 1] - lo[1]) / cell); k0 = int((tp[p, 2] - lo[2]) / cell)
        c = indptr[p]
        for i in range(max(i0 - 1, 0), min(i0 + 2, dims[0])):
            for j in range(max(j0 - 1, 0), min(j0 + 2, dims[1])):
                for k in range(max(k0 - 1, 0), min(k0 + 2, dims[2])):
                    key = (i * dims[1] + j) * dims[2] + k
                    for q in range(start[key], start[key + 1]):
                        d0 = tp[p, 0] - sp_[q, 0]; d1 = tp[p, 1] - sp_[q, 1]; d2 = tp[p, 2] - sp_[q, 2]
                        r2 = d0 * d0 + d1 * d1 + d2 * d2
                        if r2 <= rc2:
                            x = math.sqrt(r2) / dr
                            ii = min(int(x), nt - 2)
                            f = x - ii
                            indices[c] = order[q]
                            data[c] = tab[ii] * (1 - f) + tab[ii + 1] * f
                            c += 1


@_njit(cache=True, parallel=True)
def _near_sum(tp, sp_, wsorted, start, lo, cell, dims, rc, tab, dtab, dr, out, grad, want):
    m = tp.shape[0]
    rc2 = rc * rc
    nt = tab.shape[0]
    for p in _prange(m):
        i0 = int((tp[p, 0] - lo[0]) / cell); j0 = int((tp[p, 1] - lo[1]) / cell); k0 = int((tp[p, 2] - lo[2]) / cell)
        acc = 0.0; g0 = 0.0; g1 = 0.0; g2 = 0.0
        for i in range(max(i0 - 1, 0), min(i0 + 2, dims[0])):
            for j in range(max(j0 - 1, 0), min(j0 + 2, dims[1])):
                for k in range(max(k0 - 1, 0), min(k0 + 2, dims[2])):
                    key = (i * dims[1] + j) * dims[2] + k
                    for q in range(start[key], start[key + 1]):
                        d0 = tp[p, 0] - sp_[q, 0]; d1 = tp[p, 1] - sp_[q, 1]; d2 = tp[p, 2] - sp_[q, 2]
                        r2 = d0 * d0 + d1 * d1 + d2 * d2
                        if r2 <= rc2:
                            x = math.sqrt(r2) / dr
                            ii = min(int(x), nt - 2)
                            f = x - ii
                            acc += wsorted[q] * (tab[ii] * (1 - f) + tab[ii + 1] * f)
                            if want:
                                g = wsorted[q] * (dtab[ii] * (1 - f) + dtab[ii + 1] * f)
                                g0 += g * d0; g1 += g * d1; g2 += g * d2
        out[p] += acc
        if want:
            grad[p, 0] += g0; grad[p, 1] += g1; grad[p, 2] += g2


def _fft_workers() -> int:
    try:
        return max(1, min(int(os.environ.get("OMP_NUM_THREADS") or os.cpu_count() or 1), os.cpu_count() or 1))
    except ValueError:
        return 1


#: Bytes of FFT arrays a grid may take when memory is not the question (reference size of the
#: tests and benchmarks); a grid's actual budget is :func:`grid_budget`, from the memory available.
GRID_BUDGET = 2 * 2**30


def grid_budget(budget: int | None = None) -> int:
    """Bytes a new grid's FFT arrays may take: ``budget``, or :func:`memory_limit_or_default`
    (80 % of the memory available now), so that a grid follows the memory the machine has."""
    return memory_limit_or_default() if budget is None else int(budget)


def split_design(rc: float, eps: float) -> tuple[float, float, float, int]:
    """``(sigma, s, h, half)`` of a grid split whose near part ends at ``rc`` for the design tolerance ``eps``.

    sigma is the Ewald split width (``erfc(rc / (sqrt(2) sigma)) = eps``), ``s = sigma / sqrt(3)``
    the spreading Gaussian's standard deviation, ``h`` the grid spacing (aliasing
    ~``exp(-2 pi^2 s^2 / h^2)`` below eps) and ``half`` the stencil's half-width in cells.
    """
    from scipy.special import erfcinv

    sigma = rc / (math.sqrt(2.0) * float(erfcinv(eps)))
    s = sigma / math.sqrt(3.0)
    ratio = max(0.7, math.sqrt(math.log(10.0 / eps) / (2 * math.pi**2)))
    h = s / ratio
    half = int(math.ceil(math.sqrt(2 * math.log(10.0 / eps)) * ratio))
    return sigma, s, h, half


def near_table(kernel, rc: float, sigma: float, eps: float):
    """The near part phi_S = phi - phi_L tabulated: ``(cut radius, table, dr, d table / r)``; the cut is
    where ``|phi_S| < eps phi(0)``."""
    nt = 1 << 15
    rr = np.linspace(0.0, 1.3 * rc + 8 * sigma, nt)
    phis = kernel(rr) - long_part(kernel, rr, sigma)
    big = np.nonzero(np.abs(phis) > eps * float(kernel.value_at_zero))[0]
    cut = float(rr[min(big[-1] + 1, nt - 1)]) if len(big) else float(rr[1])
    dr = float(rr[1] - rr[0])
    dphis = np.gradient(phis, dr)
    dtab = np.empty(nt)
    dtab[1:] = dphis[1:] / rr[1:]
    dtab[0] = dtab[1]
    return cut, phis, dr, dtab


def default_neighbours(n: int) -> int:
    """Near-field size of a grid on ``n`` centres when none is given: N / 100 within [100, 1000]."""
    return min(max(n // 100, 100), 1000)


#: Most near-field neighbours of the products at the centres (:func:`product_neighbours`): more make
#: a product a little cheaper in CPU but its sparse near part (and the peak memory) much larger.
PRODUCT_NEIGHBOURS_MAX = 1000


def product_neighbours(n: int, limit: int | None = None) -> int:
    """Near-field size of the grid products of a fit on ``n`` centres.

    More neighbours make the grid coarser (FFT nodes fall as k^-1.5 on a
    surface) and the sparse near part larger (~0.6 k entries a row); the
    FFTs cost far more per node than a sparse entry, so the products use up
    to ``PRODUCT_NEIGHBOURS_MAX`` neighbours, as many as keep the near parts
    (the product's and its two companions', ~1.7 k entries a row) within 30 %
    of ``limit`` bytes (default :func:`memory_limit_or_default`), and never
    fewer than :func:`default_neighbours`."""
    limit = memory_limit_or_default(limit)
    fit = int(0.3 * limit / (max(n, 1) * _NNZ_BYTES * 1.1))
    return int(min(max(fit, default_neighbours(n)), PRODUCT_NEIGHBOURS_MAX, max(n // 16, default_neighbours(n))))


def neighbour_radius(centres, tree: cKDTree, k: int) -> float:
    """Median distance from a seeded sample of 2,000 centres to their ``k``-th nearest centre (self included)."""
    n = len(centres)
    rng = np.random.default_rng(0)
    sample = centres[rng.choice(n, min(n, 2000), replace=False)]
    k = int(min(max(k, 8), max(n // 4, 2)))
    d, _ = tree.query(sample, k=k)
    return max(float(np.median(d[:, -1])), 1e-6 * max(float(np.ptp(centres, axis=0).max()), 1e-300))
#: Kernel evaluations per product allowed for the far centres a grid leaves out (summed directly).
DIRECT_PAIRS = 50_000_000


def grid_bytes(lo, hi, h: float, half: int) -> int:
    """Bytes the grid backend's FFT arrays take over the box ``[lo, hi]`` ((3,) each) at spacing ``h``
    with a spreading half-width of ``half`` cells (what a grid's budget, :func:`grid_budget`, is compared with)."""
    return _Mesh.nbytes(lo, hi, h, half)


class _Mesh:
    """A grid of spacing h over a box, with the FFT of the grid kernel K (zero-padded: aperiodic)."""

    def __init__(self, lo, hi, h, s, half, ktable, dtype=np.float64):
        self.h, self.s, self.half, self.dtype = h, s, half, dtype
        pad = (half + 2) * h
        self.origin = np.asarray(lo, float) - pad
        self.shape = tuple(int(math.ceil((hi[i] - lo[i] + 2 * pad) / h)) + 1 for i in range(3))
        self.fshape = tuple(_sfft.next_fast_len(2 * m - 1, real=True) for m in self.shape)
        idx = [np.minimum(np.arange(p), p - np.arange(p)).astype(np.int32) for p in self.fshape]
        n2 = (idx[0][:, None, None] ** 2 + idx[1][None, :, None] ** 2) + idx[2][None, None, :] ** 2
        kgrid = ktable(n2)  # K at h * sqrt(n2)
        del n2
        kgrid *= h**3
        # K is even along every axis (K[i] = K[p - i]), so its transform is real: keep the real part only
        # (half the memory of the complex spectrum).
        spectrum = _sfft.rfftn(kgrid.astype(dtype, copy=False), workers=_fft_workers(), overwrite_x=True)
        del kgrid
        self.khat = np.ascontiguousarray(spectrum.real)
        del spectrum

    @staticmethod
    def nbytes(lo, hi, h, half, single: bool = False, part: str = "all") -> int:
        """Bytes of a grid's kernel transform plus the work arrays of one potential (``single``: float32 FFTs).

        ``part``: "all", "kept" (the real kernel transform, kept while the grid lives: 4 bytes a
        padded node, 2 in single precision) or "work" (the padded grid, its transform and the
        inverse of one potential, freed after it)."""
        pad = (half + 2) * h
        shape = [math.ceil((hi[i] - lo[i] + 2 * pad) / h) + 1 for i in range(3)]
        kept, work = (2, 10) if single else (4, 20)
        per = {"all": kept + work, "kept": kept, "work": work}[part]
        return int(per * np.prod([2.0 * m for m in shape]))

    def potential(self, pts, w):
        # Spread straight into the zero-padded array the FFT takes (no padded copy), transform in place.
        grid = np.zeros(self.fshape, dtype=self.dtype)
        _spread(pts, w, self.origin, self.h, self.s, self.half, grid)
        g = _sfft.rfftn(grid, workers=_fft_workers(), overwrite_x=True)
        del grid
        g *= self.khat
        u = _sfft.irfftn(g, s=self.fshape, workers=_fft_workers(), overwrite_x=True)
        del g
        out = np.ascontiguousarray(u[: self.shape[0], : self.shape[1], : self.shape[2]], dtype=float)
        del u
        out *= self.h**3
        return out

    def gather(self, u, pts, gradient):
        out = np.empty(len(pts))
        grad = np.empty((len(pts), 3)) if gradient else np.empty((1, 3))
        _gather(pts, self.origin, self.h, self.s, self.half, u, out, grad, gradient)
        return (out, grad) if gradient else out

    def covers(self, pts):
        lo = self.origin + (self.half + 1) * self.h
        hi = self.origin + (np.array(self.shape) - self.half - 2) * self.h
        return bool((pts.min(axis=0) >= lo).all() and (pts.max(axis=0) <= hi).all())

    def inside(self, pts):
        """(M,) bool: the points whose stencil lies on this grid."""
        lo = self.origin + (self.half + 1) * self.h
        hi = self.origin + (np.array(self.shape) - self.half - 2) * self.h
        return ((pts >= lo) & (pts <= hi)).all(axis=1)


class GridSum:
    """Fast ``sum_j w_j phi(|x - c_j|)`` for the multi-order kernel by a grid (particle-mesh) split.

    The kernel is split as in Ewald summation, term by term (Laplace and
    Yukawa): ``phi = phi_L + phi_S`` with

        phi_L = sum_c coef_c e^{-kappa_c^2 sigma^2 / 2} (G_sigma * e^{-kappa_c r} / (4 pi r)),

    smooth (bandwidth ~ 1 / sigma) and equal to phi beyond a few sigma, and
    ``phi_S = phi - phi_L`` short-ranged (cut where ``|phi_S| < eps phi(0)``).
    The far part is three Gaussian convolutions: spread the weights with a
    Gaussian of std s = sigma / sqrt(3) onto a grid of spacing
    ``h = s / ratio``, convolve with the grid kernel K (its zero-padded FFT,
    closed-form erfc expressions), gather with the same Gaussian.  The near
    part is a sparse matrix (centres) or a compiled cell-list sum (targets),
    with phi_S from a 32,768-entry table.  Coincident points need no special
    case: the grid includes phi_L(0), the near part phi_S(0).

    Parameters
    ----------
    kernel : MultiOrder
    centres : (N, 3) array
    eps : float
        Relative tolerance, 1e-9..1e-2 (sets the split, the stencil and h).
    neighbours : int, optional
        Near-field size: sigma is chosen so that the cut-off radius holds about
        this many centres (more: smaller grid, larger sparse part).  Default
        N / 100 within [100, 1000] (at N = 10,000, 1,000 neighbours made the
        near part of an evaluation 24 of 51 s: a tenth of all centres).
        Measured at N = 100,000, eps 1e-5 (loaded machine): 400 -> 8.4 s a
        product (grid 360x360x135), 1,000 -> 2.8 s (240x240x96), 2,000 -> 2.7 s.
    budget : int, optional
        Bytes allowed for the FFT arrays; default :func:`grid_budget` (from the
        memory available when the grid is built, and again when :meth:`cover`
        enlarges it).
    tree : cKDTree, optional
        Of ``centres`` (reused when given).
    outside : (K,) int array, optional
        Centres the grid leaves out and sums directly (both as sources and
        as targets); default :func:`outside_centres` (isolated centres beyond
        the others' box, such as the exterior sphere), so that the grid's
        box, and its memory, is set by the data rather than by the sphere.
    radius : float, optional
        The near-field radius itself (instead of ``neighbours``): the looser
        companions take one that keeps their grid no finer than this one's.

    Raises
    ------
    ValueError
        Not a multi-order kernel, confluent, or numba missing.
    MemoryError
        The grid would exceed the budget.
    """

    def __init__(self, kernel: Kernel, centres, eps: float = DEFAULT_EPS, neighbours: int | None = None,
                 budget: int | None = None, tree: cKDTree | None = None, outside=None, radius: float | None = None):
        if not HAVE_GRID:
            raise ValueError("the grid backend needs numba, which is not installed")
        if not isinstance(kernel, MultiOrder) or kernel.coefficients is None:
            raise ValueError(f"the grid backend supports the non-confluent multi-order kernel, not {kernel!r}")
        t0 = time.perf_counter()
        self.kernel = kernel
        self.centres = np.ascontiguousarray(centres, dtype=float)
        self.n = n = len(self.centres)
        self.eps = _clip_eps(eps)
        eps = self.eps / 10  # measured errors ~1-2x the design tolerance: keep the result below eps
        self.tree = cKDTree(self.centres) if tree is None else tree
        self.phi0 = float(kernel.value_at_zero)
        self.mode = "grid"
        if radius is None:
            rc = neighbour_radius(self.centres, self.tree, default_neighbours(n) if neighbours is None else neighbours)
        else:
            rc = float(radius)
        self.design_radius = rc
        sigma, s, h, half = split_design(rc, eps)
        self.s, self.h, self.half, self.sigma = s, h, half, sigma
        single = self.eps >= 1e-4  # single-precision FFTs (half the time and memory): ~1e-6 round-off << eps
        full = _Mesh.nbytes(self.centres.min(axis=0), self.centres.max(axis=0), h, half, single)
        if outside is None:
            outside = outside_centres(self.centres, self.tree, rc)
        self._set_core(outside)
        lo, hi = self._cc.min(axis=0), self._cc.max(axis=0)
        need = _Mesh.nbytes(lo, hi, h, half, single)
        self._fixed_budget = None if budget is None else int(budget)
        self.budget = grid_budget(budget)
        self._eval_mesh = None
        if need > self.budget:
            raise MemoryError(f"the grid of fast sums over {n:,} centres needs ~{need / 2**30:.1f} GB of FFT arrays "
                              f"(budget {self.budget / 2**30:.1f} GB)")
        # Near part: phi_S = phi - phi_L on a table, cut where |phi_S| < eps phi(0).
        self.rc, self.tab, self.dr, self.dtab = near_table(kernel, rc, sigma, eps)
        self._meshes = []
        self.mesh = self._mesh(lo, hi)
        self._cell_setup()
        self._near_m = None
        key = np.floor((self._cc - self.mesh.origin) / (4 * h)).astype(np.int64)
        self._perm = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))  # grid order: cache-friendly spreading
        self._sorted = np.ascontiguousarray(self._cc[self._perm])
        self.info = {"mode": "grid (Gaussian split: FFT far part + sparse near part)", "split": "grid",
                     "near_radius": self.rc, "sigma": sigma, "h": h, "grid": self.mesh.shape,
                     "fft": self.mesh.fshape, "stencil": 2 * half + 1, "grid_bytes": need,
                     "grid_bytes_all_centres": full, "outside": len(self._out),
                     "setup_seconds": time.perf_counter() - t0}

    def _ktable(self, n2):
        top = int(n2.max())
        vals = long_part(self.kernel, self.h * np.sqrt(np.arange(top + 1.0)), self.s, extra=math.sqrt(2.0) * self.s)
        return vals[n2]

    def _mesh(self, lo, hi):
        for m in self._meshes:
            if m.covers(np.array([lo, hi])):
                return m
        # Single-precision FFTs (half the time and memory) where ~1e-6 round-off is far below eps.
        m = _Mesh(lo, hi, self.h, self.s, self.half, self._ktable, np.float32 if self.eps >= 1e-4 else np.float64)
        self._meshes = [m] + self._meshes[:1]
        return m

    def _mesh_bytes(self, lo, hi) -> int:
        return _Mesh.nbytes(lo, hi, self.h, self.half, self.eps >= 1e-4)

    def _set_core(self, outside):
        """Split the centres into the grid's (core) and the few far ones summed directly."""
        out = np.unique(np.asarray(outside, dtype=np.int64).reshape(-1))
        if len(out) and (out[0] < 0 or out[-1] >= self.n or len(out) >= self.n):
            raise ValueError("outside must index fewer than all of the centres; pass None to choose them")
        self._out = out
        if len(out) == 0:
            self._core = None
            self._cc = self.centres
            return
        mask = np.ones(self.n, bool)
        mask[out] = False
        self._core = np.nonzero(mask)[0]
        self._cc = np.ascontiguousarray(self.centres[self._core])
        self._core_pos = np.full(self.n, -1, np.int64)
        self._core_pos[self._core] = np.arange(len(self._core))

    def _cell_setup(self):
        lo = self._cc.min(axis=0)
        cell = self.rc
        dims = np.maximum(np.ceil((self._cc.max(axis=0) - lo) / cell).astype(np.int64), 1)
        key = _cells(self._cc, lo, cell, dims)
        order = np.argsort(key, kind="stable")
        start = np.searchsorted(key[order], np.arange(int(np.prod(dims)) + 1)).astype(np.int64)
        self._cl = (lo, cell, dims, order, np.ascontiguousarray(self._cc[order]), start)

    @property
    def near(self):
        """Sparse matrix of phi_S between the grid's (core) centres (built on first use)."""
        if self._near_m is None:
            lo, cell, dims, order, spts, start = self._cl
            nc = len(self._cc)
            cnt = _near_count(self._cc, spts, start, lo, cell, dims, self.rc)
            indptr = np.zeros(nc + 1, np.int64)
            np.cumsum(cnt, out=indptr[1:])
            indices = np.empty(indptr[-1], np.int32)
            data = np.empty(indptr[-1])
            _near_fill(self._cc, spts, order.astype(np.int32), start, lo, cell, dims, self.rc, indptr,
                       indices, data, self.tab, self.dr)
            self._near_m = sp.csr_matrix((data, indices, indptr), shape=(nc, nc))
            self.info["near_nnz"] = int(indptr[-1])
        return self._near_m

    def _tier(self, eps):
        """The loosest operator at least as accurate as ``eps``: this one, or a cached
        looser companion (tolerance 1e-4 or 1e-3, :meth:`tier_radius`: a grid no finer,
        single-precision FFTs, a 9-11 point stencil instead of 13-15, a smaller near part)."""
        if eps is None:
            return self
        for tol in (1e-3, 1e-4):
            if tol <= eps and tol >= 10 * self.eps:
                tiers = self.__dict__.setdefault("_tiers", {})
                if tol not in tiers:
                    tiers[tol] = GridSum(self.kernel, self.centres, eps=tol, radius=self.tier_radius(tol),
                                         tree=self.tree, outside=self._out, budget=self._fixed_budget)
                return tiers[tol]
        return self

    def tier_radius(self, tol: float) -> float:
        """Near-field radius of the companion at tolerance ``tol``: that of ~300 neighbours, or more where
        that would make its grid finer than this one's (a looser companion never takes more FFT memory)."""
        rc = neighbour_radius(self.centres, self.tree, min(300, max(self.n // 300, 64)))
        return max(rc, self.h / split_design(1.0, _clip_eps(tol) / 10)[2])

    def matvec(self, w, eps: float | None = None) -> np.ndarray:
        """(Phi w)_i, self term included, to relative accuracy ``eps`` (default: the operator's)."""
        w = np.asarray(w, dtype=float)
        op = self._tier(eps)
        if op is not self:
            return op.matvec(w)
        p = self._perm
        wc = w if self._core is None else w[self._core]
        u = self.mesh.potential(self._sorted, np.ascontiguousarray(wc[p]))
        outc = np.empty(len(self._cc))
        outc[p] = self.mesh.gather(u, self._sorted, False)
        outc += self.near @ wc
        if self._core is None:
            return outc
        # The far centres: summed directly (few of them), both ways.
        out = np.empty(self.n)
        o = self._out
        out[self._core] = outc + kernel_sum(self.kernel, self.centres[o], w[o], self._cc)
        out[o] = kernel_sum(self.kernel, self.centres, w, self.centres[o])
        return out

    def evaluate(self, w, targets, gradient: bool = False, eps: float | None = None):
        """sum_j w_j phi(|x - c_j|) (and its gradient) at arbitrary targets.

        Targets beyond the grid are summed directly when they are few (at most
        ``DIRECT_PAIRS / N``), else the grid is enlarged to cover them."""
        t = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        w = w if isinstance(w, np.ndarray) and w.dtype == float else np.asarray(w, dtype=float)
        if len(t) == 0:
            return (np.zeros(0), np.zeros((0, 3))) if gradient else np.zeros(0)
        base = self.mesh if self._eval_mesh is None else self._eval_mesh
        inside = base.inside(t)
        if inside.all():
            mesh, far = base, None
        elif (~inside).sum() * self.n <= DIRECT_PAIRS:
            mesh, far = base, np.nonzero(~inside)[0]
        else:
            mesh, far = self._mesh(np.minimum(self._cc.min(0), t.min(0)), np.maximum(self._cc.max(0), t.max(0))), None
        if far is not None:
            near_t = np.nonzero(inside)[0]
            v_out = np.empty(len(t))
            g_out = np.empty((len(t), 3)) if gradient else None
            exact = kernel_sum(self.kernel, self.centres, w, t[far], gradient=gradient)
            if len(near_t):
                part = self._evaluate_on(mesh, w, t[near_t], gradient)
                if gradient:
                    v_out[near_t], g_out[near_t] = part
                else:
                    v_out[near_t] = part
            if gradient:
                v_out[far], g_out[far] = exact
                return v_out, g_out
            v_out[far] = exact
            return v_out
        return self._evaluate_on(mesh, w, t, gradient)

    def cover(self, lo, hi) -> bool:
        """Build (once) the grid :meth:`evaluate` uses so that it covers the box ``[lo, hi]``.

        Without it, targets beyond the centres' grid enlarge it call by call
        (a new kernel transform and potential each time); with it, one grid
        and one potential serve a whole extraction.  Returns False (and
        changes nothing) when that grid would exceed the budget.

        Parameters
        ----------
        lo, hi : (3,) array_like
            Corners of the box, in the centres' coordinates.
        """
        lo = np.minimum(self._cc.min(axis=0), np.asarray(lo, dtype=float))
        hi = np.maximum(self._cc.max(axis=0), np.asarray(hi, dtype=float))
        if self.mesh.covers(np.array([lo, hi])):
            self._eval_mesh = None
            return True
        need = self._mesh_bytes(lo, hi)
        limit = grid_budget(self._fixed_budget)
        if self._fixed_budget is None:  # what is available now, plus the grid the new one replaces
            limit += self._mesh_bytes(*self._box())
        if need > limit:
            return False
        # The larger grid replaces the centres' one (it serves the products too): one grid in memory, not two.
        self._meshes = []
        self._ucache = None
        self.mesh = self._eval_mesh = self._mesh(lo, hi)
        return True

    def _box(self):
        return self._cc.min(axis=0), self._cc.max(axis=0)

    def _evaluate_on(self, mesh, w, t, gradient):
        """The grid + near sum from the core centres at targets inside ``mesh``, plus the far centres directly."""
        cached = getattr(self, "_ucache", None)
        wc = w if self._core is None else w[self._core]
        if cached is not None and cached[0] is mesh and cached[1] is w:
            u = cached[2]  # same weights object (an evaluator): reuse the grid potential
        else:
            u = mesh.potential(self._sorted, np.ascontiguousarray(wc[self._perm]))
            self._ucache = (mesh, w, u)
        # Targets in grid order: the stencil reads (and the cell-list scans) stay in cache.
        key = np.floor((t - mesh.origin) / (4 * mesh.h)).astype(np.int64)
        tp = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
        ts = np.ascontiguousarray(t[tp])
        out = mesh.gather(u, ts, gradient)
        vals, grad = out if gradient else (out, np.empty((1, 3)))
        lo, cell, dims, order, spts, start = self._cl
        _near_sum(ts, spts, np.ascontiguousarray(wc[order]), start, lo, cell, dims, self.rc, self.tab, self.dtab,
                  self.dr, vals, grad, gradient)
        if self._core is not None:
            o = self._out
            extra = kernel_sum(self.kernel, self.centres[o], w[o], ts, gradient=gradient)
            if gradient:
                vals += extra[0]
                grad += extra[1]
            else:
                vals += extra
        v_out = np.empty(len(t))
        v_out[tp] = vals
        if gradient:
            g_out = np.empty((len(t), 3))
            g_out[tp] = grad
            return v_out, g_out
        return v_out

    def from_subset(self, subset):
        """A callable ``(w_sub, eps) -> sum_{j in subset} w_j phi(|c_i - c_j|)`` at every centre."""
        subset = np.asarray(subset)
        if self._core is None:
            csub, cmask, osub = subset, None, subset[:0]
        else:
            cmask = self._core_pos[subset] >= 0
            csub, osub = self._core_pos[subset[cmask]], subset[~cmask]
        cache = {}

        def apply(w, eps=None):
            op = self._tier(eps)
            w = np.asarray(w, dtype=float)
            if op not in cache:
                key = np.floor((op._cc[csub] - op.mesh.origin) / (4 * op.h)).astype(np.int64)
                pos = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
                cache[op] = (np.ascontiguousarray(op._cc[csub[pos]]), pos, op.near[:, csub].tocsr())
            pts, pos, cols = cache[op]
            wc = w if cmask is None else w[cmask]
            outc = np.empty(len(op._cc))
            if len(csub):
                u = op.mesh.potential(pts, np.ascontiguousarray(wc[pos]))
                outc[op._perm] = op.mesh.gather(u, op._sorted, False)
                outc += cols @ wc
            else:
                outc[:] = 0.0
            if self._core is None:
                return outc
            out = np.zeros(self.n)
            out[self._core] = outc
            if len(osub):
                out += kernel_sum(self.kernel, self.centres[osub], w[~cmask], self.centres)
            o = self._out
            out[o] = kernel_sum(self.kernel, self.centres[subset], w, self.centres[o])
            return out

        return apply


def outside_centres(centres, tree: cKDTree, radius: float, max_pairs: int | None = None) -> np.ndarray:
    """Indices of the few far centres a grid need not cover (summed directly instead).

    A centre is isolated when no other centre lies within ``radius`` (the
    near-field radius, ~1,000 neighbours for the others): e.g. the sparse
    sphere of exterior constraints around the bounding box, which would
    otherwise set the grid's box (at 100,000 constraints, 8.1 GB of FFT
    arrays instead of 0.35 GB).  The grid then covers the box of the
    non-isolated centres; the centres outside that box are returned, or none
    if they are both more than ``max_pairs / N`` (default ``DIRECT_PAIRS``)
    and more than 0.1 % of the centres.

    Parameters
    ----------
    centres : (N, 3) array
    tree : cKDTree
        Of ``centres``.
    radius : float
    max_pairs : int, optional

    Returns
    -------
    (K,) int array
    """
    centres = np.asarray(centres, dtype=float)
    n = len(centres)
    cap = DIRECT_PAIRS if max_pairs is None else int(max_pairs)
    if n < 3:
        return np.zeros(0, np.int64)
    d, _ = tree.query(centres, k=2)
    busy = d[:, 1] <= radius
    if busy.sum() < 2:
        return np.zeros(0, np.int64)
    lo, hi = centres[busy].min(axis=0), centres[busy].max(axis=0)
    out = np.nonzero(((centres < lo) | (centres > hi)).any(axis=1))[0]
    if len(out) * n > cap and len(out) > 1e-3 * n:  # a few (the sphere) are summed directly even at large N
        return np.zeros(0, np.int64)
    return out.astype(np.int64)


def fast_operator(kernel: Kernel, centres, eps: float = DEFAULT_EPS, backend: str = "auto", memory_limit: int | None = None,
                  neighbours: int | None = None):
    """The product for a fast solve: :class:`GridSum` or :class:`FastSum`.

    ``backend="auto"`` takes the grid for the multi-order kernel when numba is
    there, ``eps >= 1e-8`` and the grid fits :func:`grid_budget` (it is 5-10x
    faster than fmm3dpy's single-threaded wheel: 100,000 centres, 2.8 s vs
    ~30 s a product), else the FMM (``"fmm"``).  The grid's near field has
    ``neighbours``, default :func:`product_neighbours` (``memory_limit``): right for
    products at the centres; evaluation at many targets wants fewer (:func:`default_neighbours`)."""
    if neighbours is None:
        neighbours = product_neighbours(len(centres), memory_limit)
    if backend not in ("auto", "grid", "fmm"):
        raise ValueError(f"backend must be 'auto', 'grid' or 'fmm', got {backend!r}")
    if backend == "grid":
        return GridSum(kernel, centres, eps=eps, neighbours=neighbours)
    if backend == "auto" and HAVE_GRID and isinstance(kernel, MultiOrder) and kernel.coefficients is not None \
            and eps >= 1e-8 and len(centres) >= 64:
        try:
            return GridSum(kernel, centres, eps=eps, neighbours=neighbours)
        except MemoryError as exc:
            import logging

            logging.getLogger("o3drbf").warning(
                "fast products: %s; falling back to fmm3dpy (single-threaded wheel: ~%.0f s a product)",
                exc, 30.0 * len(centres) / 1e5,
            )
    return FastSum(kernel, centres, eps=eps)


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


def _subset_operator(fast, subset, eps):
    """The same kind of product on ``fast.centres[subset]`` (for a nested coarse level)."""
    cen = fast.centres[subset]
    if isinstance(fast, GridSum):  # the grid when it fits its budget, else fmm3dpy
        return fast_operator(fast.kernel, cen, eps=max(eps, fast.eps), backend="auto")
    if isinstance(fast, FastSum):
        return FastSum(fast.kernel, cen, eps=max(eps, fast.eps), workers=fast.workers)
    return type(fast)(fast.kernel, cen)


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
        Coarse level size ``N / coarse_ratio``, solved by Cholesky up to
        ``max_coarse`` centres; above it, capped at ``max_coarse`` when
        ``nested`` is 0, else solved by nested steps.
    inner : int
        CG steps on the near-field matrix.
    damping : float
        The near-field diagonal phi(0) - phi(R) is multiplied by this (a
        damped local step after the coarse correction).  At N = 8,000 1.0
        needs 20 iterations, 1.5 needs 9, 2 needs 10, 3 needs 11; at 50,000
        (grid products) 1.5 needs 38 (a plateau near 1e-4), 2 needs 10.
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
    nested : int
        FGMRES steps for a coarse level above ``max_coarse`` (0: cap it at
        ``max_coarse`` instead).  The steps are preconditioned by a
        TwoLevel on the coarse centres (same parameters, so recursive).
    nested_eps : float
        Tolerance of the products on the coarse centres (nested level).
    nested_rtol : float
        Relative residual that stops the nested steps early (0: always
        ``nested`` steps; 1e-2 gave 30 outer iterations at 100k, vs 12).
    nested_ratio : float
        Nest only when ``N > nested_ratio * max_coarse`` (144,000 by
        default); below it the coarse level is capped.  At 100k nesting
        cut the count from 16 to 12 but the fit took 35.5 s instead of
        30.4 s; at 300k it took 146 s (15 iterations) instead of 215 s (36).
    """

    def __init__(self, fast: FastSum, lam, neighbours=64, coarse_ratio=8, max_coarse=6000, inner=10,
                 eps=1e-2, dense_budget=256 * 2**20, select="uniform", exact_below=3000, damping=2.0,
                 nested=8, nested_eps=1e-3, nested_rtol=0.0, nested_ratio=24):
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
        want = max(n // coarse_ratio, 1)
        self.nested = int(nested) if n > exact_below and want > max_coarse and n > nested_ratio * max_coarse else 0
        mc = n if n <= exact_below else min(want, n if self.nested else max_coarse, n)
        if select == "random" and mc < n:
            self.coarse = np.sort(np.random.default_rng(0).choice(n, mc, replace=False))
        else:
            self.coarse = _uniform_subset(x, mc)
        xc = x[self.coarse]
        self.factor = self.inner_level = None
        if self.nested:
            # The coarse system is too big for Cholesky: solve it loosely by a
            # few FGMRES steps preconditioned by the same scheme (recursively).
            sub = _subset_operator(fast, self.coarse, nested_eps)
            self.inner_level = TwoLevel(sub, self.lam[self.coarse], neighbours=neighbours,
                                        coarse_ratio=coarse_ratio, max_coarse=max_coarse, inner=inner, eps=eps,
                                        dense_budget=dense_budget, select=select, exact_below=exact_below,
                                        damping=damping, nested=nested, nested_eps=nested_eps,
                                        nested_rtol=nested_rtol, nested_ratio=nested_ratio)
            self._sub, self._sub_lam, self._sub_eps = sub, self.lam[self.coarse], nested_eps
            self._sub_rtol = float(nested_rtol)
        else:
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
            "coarse_solve": (f"{self.nested} nested FGMRES steps" if self.nested else "Cholesky"),
            "setup_seconds": self.setup_seconds,
        }
        if self.inner_level is not None:
            self.info["inner"] = self.inner_level.info

    def _coarse_to_fine(self, zc):
        """(Phi + Lambda)[:, C] z_C."""
        if self.block is not None:
            out = self.block @ zc
        else:
            out = self.update(zc, self.eps)
        out[self.coarse] += self.lam[self.coarse] * zc
        return out

    def _coarse_solve(self, rc):
        """z_C ~ (Phi_CC + Lambda_C)^{-1} r_C: Cholesky, or a few nested FGMRES steps."""
        if self.factor is not None:
            return sla.cho_solve(self.factor, rc, check_finite=False)
        sub, lam, e = self._sub, self._sub_lam, self._sub_eps

        def product(v, rel=1.0):
            return sub.matvec(v, eps=e) + lam * v

        z, *_ = _fgmres(product, rc, self.inner_level, self._sub_rtol, self.nested, self.nested, product, final=False)
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
def _fgmres(matvec, b, prec, rtol, max_iterations, restart, true_matvec, bar=None, final=True, x0=None):
    """Flexible GMRES (right preconditioned), restarted from the true residual.

    ``matvec(x, rel)`` may be inexact with relative accuracy ``rel`` (relaxed
    as the residual falls); ``true_matvec`` is the accurate product used at
    every restart; ``x0`` a starting guess (default 0).  Returns x,
    iterations, true relative residual, history.
    """
    n = len(b)
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return np.zeros(n), 0, 0.0, []
    if x0 is None:
        x = np.zeros(n)
        r = b.copy()
    else:
        x = np.array(x0, dtype=float)
        r = b - true_matvec(x)
    beta = float(np.linalg.norm(r))
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
        if not final:  # one cycle, no true residual (a nested solve)
            return x, its, est / bn, history
        r = b - true_matvec(x)
        beta = float(np.linalg.norm(r))
        if est <= rtol * bn and beta > rtol * bn and history and history[-1] < 1e-3 * beta / bn:
            # The recurrence converged but the true residual did not move:
            # the products are not accurate enough to go further.
            return x, its, beta / bn, history


# --------------------------------------------------------------------------------------
# memory
# --------------------------------------------------------------------------------------
#: Bytes per centre of the kd-tree, the sorted copies and the index arrays every product keeps.
_PER_CENTRE_BYTES = 200


def fast_memory(n: int, restart: int = 50, eps: float = 1e-6) -> int:
    """Rough peak bytes of a fast solve with ``n`` constraints, from ``n`` alone.

    The FMM route (fmm3dpy's working memory) or the grid route's near parts
    (about 1,000 + 2 x 400 entries a row) with a grid of 10 kB a centre; the
    estimate that knows the centres is :func:`memory_plan`."""
    fmm = _FMM_BYTES_PER_POINT * n * (1.0 if eps <= 1e-6 else 0.6) + 12 * n * 300
    grid = _NNZ_BYTES * n * 1800 + 1e4 * n
    krylov = 2 * (restart + 2) * n * 8
    precond = 12 * n * 64 + 8 * 6000**2 + 256 * 2**20 + (12 * (n // 8) * 1000 if n > 144_000 else 0)
    return int(max(fmm, grid) + krylov + precond)


def _core_box(centres, tree, rc, outside=None):
    """(outside indices, core lo, core hi, core count) of a grid with near radius ``rc``."""
    if outside is None:
        outside = outside_centres(centres, tree, rc)
    if len(outside):
        mask = np.ones(len(centres), bool)
        mask[outside] = False
        core = centres[mask]
    else:
        core = centres
    return outside, core.min(axis=0), core.max(axis=0), len(core)


def grid_plan(kernel, centres, tree, eps: float, neighbours: int | None = None, radius: float | None = None,
              outside=None, box=None, near: bool = True, memo: dict | None = None) -> dict:
    """What a :class:`GridSum` with these arguments would take, without building it.

    Parameters
    ----------
    kernel : MultiOrder
    centres : (N, 3) array
    tree : cKDTree
        Of ``centres``.
    eps, neighbours, radius, outside
        As for :class:`GridSum`.
    box : (2, 3) array_like, optional
        A box the grid must cover too (:meth:`GridSum.cover`).
    near : bool
        Count the stored near-field matrix (products at the centres build it;
        evaluation at targets does not).
    memo : dict, optional
        Neighbour radii already measured on this tree, by neighbour count (filled in).

    Returns
    -------
    dict
        ``grid`` (the kernel transform, kept), ``work`` (the transforms of
        one product, freed after it), ``near`` (sparse matrix), ``potential``
        (one grid potential), bytes; ``h``, ``radius`` (design), ``outside``.
    """
    n = len(centres)
    e = _clip_eps(eps)
    if radius is None:
        k = default_neighbours(n) if neighbours is None else neighbours
        memo = {} if memo is None else memo
        if k not in memo:
            memo[k] = neighbour_radius(centres, tree, k)
        radius = memo[k]
    rc = float(radius)
    sigma, _, h, half = split_design(rc, e / 10)
    outside, lo, hi, n_core = _core_box(centres, tree, rc, outside)
    if box is not None:
        lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
    grid = _Mesh.nbytes(lo, hi, h, half, e >= 1e-4, "kept")
    work = _Mesh.nbytes(lo, hi, h, half, e >= 1e-4, "work")
    pad = (half + 2) * h
    cells = float(np.prod([math.ceil((hi[i] - lo[i] + 2 * pad) / h) + 1 for i in range(3)]))
    nnz = 0.0
    if near:
        cut = near_table(kernel, rc, sigma, e / 10)[0]
        sample = centres[np.random.default_rng(1).choice(n, min(n, 1000), replace=False)]
        nnz = float(np.mean(tree.query_ball_point(sample, cut, return_length=True))) * n_core
    return {"grid": int(grid), "work": int(work), "near": int(_NNZ_BYTES * nnz + 8 * n_core), "potential": int(8 * cells),
            "h": h, "radius": rc, "outside": outside}


def _twolevel_plan(kernel, centres, tree, lam_count, coarse_update_nnz, options=None) -> int:
    """Bytes of a :class:`TwoLevel` on these centres with its default options (``options`` overrides)."""
    o = {"neighbours": 64, "coarse_ratio": 8, "max_coarse": 6000, "exact_below": 3000, "dense_budget": 256 * 2**20,
         "nested": 8, "nested_ratio": 24, "nested_eps": 1e-3}
    o.update(options or {})
    n = len(centres)
    total = 2 * _NNZ_BYTES * n * (o["neighbours"] + 1)  # the tapered near matrix (and its copy while built)
    want = max(n // o["coarse_ratio"], 1)
    nested = o["nested"] and n > o["exact_below"] and want > o["max_coarse"] and n > o["nested_ratio"] * o["max_coarse"]
    mc = n if n <= o["exact_below"] else min(want, n if nested else o["max_coarse"], n)
    if mc < n:
        total += min(8 * n * mc, o["dense_budget"]) if 8 * n * mc <= o["dense_budget"] else int(coarse_update_nnz * mc / n) * _NNZ_BYTES
    if not nested:
        return int(total + 1.5 * 8 * mc * mc)
    sub_idx = np.sort(np.random.default_rng(2).choice(n, mc, replace=False))
    sub = centres[sub_idx]
    sub_tree = cKDTree(sub)
    g = grid_plan(kernel, sub, sub_tree, max(o["nested_eps"], 1e-8), neighbours=product_neighbours(mc))
    inner = _twolevel_plan(kernel, sub, sub_tree, mc, g["near"] / _NNZ_BYTES, o)
    krylov = 2 * (o["nested"] + 2) * mc * 8
    return int(total + g["grid"] + g["near"] + inner + krylov + _PER_CENTRE_BYTES * mc)  # (its work: below the outer's)


def memory_plan(kernel, centres, rtol: float = 1e-6, eps: float | None = None, restart: int = 50, tree: cKDTree | None = None,
                preconditioner: dict | None = None, evaluation: bool = True, evaluation_eps: float = DEFAULT_EPS,
                box=None, extraction_bytes: int = 0, limit: int | None = None) -> dict:
    """Peak bytes of a fast fit on these centres (and of evaluating and meshing it), without building anything.

    It follows the solve as it runs: during FGMRES the products at the
    solve's tolerance and their two looser companions (each a grid and a
    near-field matrix), the two-level preconditioner (tapered near field,
    coarse Cholesky or the nested level with its own grid), the Krylov
    basis; at the end the evaluator's grid joins the products; meshing
    holds the evaluator's grid enlarged to ``box`` and ``extraction_bytes``.
    Kernels or tolerances the grid does not take are estimated by
    :func:`fast_memory`.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array
    rtol : float
        Relative residual of the solve; the products' tolerance is
        :func:`product_tolerance` of it unless ``eps`` is given.
    eps : float, optional
    restart : int
    tree : cKDTree, optional
        Of ``centres``.
    preconditioner : dict, optional
        Options of :class:`TwoLevel`.
    evaluation : bool
        Count the evaluator (:func:`make_evaluator`) and meshing.
    evaluation_eps : float
    box : (2, 3) array_like, optional
        The meshing lattice's box (default: the centres' box padded by 5 % of its span).
    extraction_bytes : int
        Marching cubes' own arrays (:func:`o3drbf.options.extraction_memory`).
    limit : int, optional
        The memory limit the products' near-field size follows
        (:func:`product_neighbours`); default :func:`memory_limit_or_default`.

    Returns
    -------
    dict
        ``total`` (the peak, bytes), ``fit``, ``end_of_fit``, ``mesh``
        (the three phases), ``parts`` (bytes by piece) and ``route``
        ("grid" or "fmm").
    """
    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    e = product_tolerance(rtol) if eps is None else _clip_eps(eps)
    grid_ok = HAVE_GRID and isinstance(kernel, MultiOrder) and kernel.coefficients is not None and e >= 1e-8 and n >= 64
    if not grid_ok:
        need = fast_memory(n, restart, e)
        return {"total": need, "fit": need, "end_of_fit": need, "mesh": need, "parts": {}, "route": "fmm"}
    tree = cKDTree(centres) if tree is None else tree
    base = _PER_CENTRE_BYTES * n
    memo = {}
    main = grid_plan(kernel, centres, tree, e, neighbours=product_neighbours(n, limit), memo=memo)
    out = main["outside"]
    parts = {"grid": main["grid"], "near": main["near"]}
    work = [main["work"]]
    rc300 = neighbour_radius(centres, tree, min(300, max(n // 300, 64)))
    tier_nnz = 0
    for tol in (1e-3, 1e-4):
        if tol >= 10 * e:
            t = grid_plan(kernel, centres, tree, tol, radius=max(rc300, main["h"] / split_design(1.0, tol / 10)[2]), outside=out)
            parts[f"grid {tol:g}"], parts[f"near {tol:g}"] = t["grid"], t["near"]
            work.append(t["work"])
            tier_nnz = t["near"] / _NNZ_BYTES if tol == 1e-3 else tier_nnz
    parts["preconditioner"] = _twolevel_plan(kernel, centres, tree, n, tier_nnz or main["near"] / _NNZ_BYTES, preconditioner)
    parts["krylov"] = int(2 * (restart + 1) * (n + 4) * 8 + 3 * n * 4 * 8)
    products = sum(v for k, v in parts.items() if k.startswith(("grid", "near")))
    fit = base + products + parts["preconditioner"] + parts["krylov"] + max(work)
    end = mesh = 0
    if evaluation:
        if box is None:
            _, lo, hi, _ = _core_box(centres, tree, main["radius"], out)
            pad = 0.05 * float((hi - lo).max())
            box = np.stack([lo - pad, hi + pad])
        at_centres = grid_plan(kernel, centres, tree, evaluation_eps, near=False, outside=out, memo=memo)
        at_box = grid_plan(kernel, centres, tree, evaluation_eps, near=False, box=np.asarray(box, dtype=float), outside=out,
                           memo=memo)
        parts["evaluator"] = at_box["grid"] + at_box["potential"]
        end = base + products + at_centres["grid"] + at_centres["potential"] + max(work + [at_centres["work"]])
        mesh = base + parts["evaluator"] + at_box["work"] + int(extraction_bytes)
    return {"total": int(max(fit, end, mesh)), "fit": int(fit), "end_of_fit": int(end), "mesh": int(mesh), "parts": parts,
            "route": "grid"}


def check_memory(n: int, restart: int = 50, eps: float = 1e-6, memory_limit: int | None = None, kernel=None, centres=None,
                 **plan) -> dict | None:
    """Refuse, before anything is built, a fast solve that would not fit in ``memory_limit`` bytes.

    With ``kernel`` and ``centres`` the need is :func:`memory_plan`'s (``plan``
    holds its other arguments), else :func:`fast_memory`'s.  The limit
    defaults to 80 % of the memory available now.

    Returns
    -------
    dict or None
        The plan (None without centres).

    Raises
    ------
    MemoryRefusal
        Naming the need, the limit and the share of the constraints that would fit.
    """
    limit = memory_limit_or_default(memory_limit)
    result = None
    if centres is not None and kernel is not None:
        result = memory_plan(kernel, centres, eps=eps, restart=restart, limit=limit, **plan)
        need = result["total"]
    else:
        need = fast_memory(n, restart, eps)
    if need > limit:
        fraction = None
        if centres is not None and kernel is not None:
            fraction = fitting_fraction(kernel, centres, limit, eps=eps, restart=restart, limit=limit, **plan)
        raise MemoryRefusal(f"a fast solve of {n} constraints", need, limit, fraction=fraction,
                            cli_hint="use fewer constraints (--surface-count) or --tiles auto")
    return result


def fitting_fraction(kernel, centres, fit_in: int, **plan) -> float:
    """About the largest share of ``centres`` (a seeded random subset, like a sparser subsample) whose
    :func:`memory_plan` (with ``plan``) fits in ``fit_in`` bytes (0 if not even 1 % does)."""
    n = len(centres)
    rng = np.random.default_rng(3)
    order = rng.permutation(n)
    frac = 1.0
    need = memory_plan(kernel, centres, **plan)["total"]
    for _ in range(8):
        frac *= min(0.9, max(0.2, (fit_in / need) ** 1.25))
        m = int(frac * n)
        if m < max(100, n // 100):
            return 0.0
        need = memory_plan(kernel, centres[np.sort(order[:m])], **plan)["total"]
        if need <= fit_in:
            return frac
    return 0.0


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
    backend: str = "auto",
    x0=None,
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
    backend : {"auto", "grid", "fmm"}
        The product when ``operator`` is None (:func:`fast_operator`).
    x0 : (N + M,) array, optional
        Starting guess ``[w; p]`` (e.g. the solution of a nearby system: a
        robust refit starts from the fit before it).

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
    eps = product_tolerance(rtol) if eps is None else _clip_eps(eps)
    if operator is None:  # (a prebuilt operator was checked by whoever built it)
        check_memory(n, restart, eps, memory_limit, kernel=kernel, centres=centres, preconditioner=preconditioner, evaluation=False)
    q = polynomial_basis(centres, kernel.polynomial_degree)
    m = q.shape[1]
    t_setup = time.perf_counter()
    fast = fast_operator(kernel, centres, eps=eps, backend=backend, memory_limit=memory_limit) if operator is None else operator
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
    bar = progress_bar(progress, total=max_iterations, desc="fast FGMRES", unit="it")
    t_solve = time.perf_counter()
    try:
        x, its, res, history = _fgmres(product, b, prec, rtol, max_iterations, restart,
                                       lambda v: product(v, 1.0), bar, x0=x0)
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
def make_evaluator(kernel: Kernel, centres, weights, eps: float = DEFAULT_EPS, chunk: int = 1_000_000,
                   backend: str = "auto"):
    """A callable ``(points (M, 3), gradient) -> values (M,) [, grads (M, 3)]`` for
    ``ImplicitSurface.evaluator``: ``sum_i w_i phi(|x - c_i|)`` without the
    polynomial, by FMM with targets (multi-order), sparse sums (Gaussian) or
    direct sums (thin-plate); ``backend`` as in :func:`fast_operator` (the
    grid for the multi-order kernel by default).  Targets are processed
    ``chunk`` at a time.  ``evaluator.cover(lo, hi)`` prepares the grid for
    targets in that box (:meth:`GridSum.cover`; a no-op for other backends)."""
    # Few neighbours: the near part of an evaluation is summed afresh at every target.
    fast = fast_operator(kernel, centres, eps=eps, backend=backend, neighbours=default_neighbours(len(centres)))
    if isinstance(fast, GridSum):
        # The grid's gradients are ~10x less accurate than its values: gradients
        # (vertex normals, few points) come from a second grid at eps / 10.
        fine = {}

        def pick(gradient):
            if not gradient:
                return fast
            if "op" not in fine:
                try:
                    fine["op"] = GridSum(kernel, fast.centres, eps=eps / 10, tree=fast.tree, outside=fast._out,
                                         neighbours=default_neighbours(fast.n))
                    if "box" in fine:
                        fine["op"].cover(*fine["box"])
                except MemoryError as exc:  # gradients from the values' grid (~10 eps) rather than a failure this late
                    import logging

                    logging.getLogger("o3drbf").info("gradients from the evaluation grid: %s", exc)
                    fine["op"] = fast
            return fine["op"]

        def cover(lo, hi):
            fine["box"] = (lo, hi)
            return fast.cover(lo, hi)
    else:

        def pick(gradient):
            return fast

        def cover(lo, hi):
            return False
    weights = np.ascontiguousarray(weights, dtype=float)
    if weights.shape != (fast.n,):
        raise ValueError(f"weights must have shape ({fast.n},), got {weights.shape}")

    def evaluator(points, gradient=False):
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        op = pick(gradient)
        if len(pts) <= chunk:
            return op.evaluate(weights, pts, gradient=gradient)
        parts = [op.evaluate(weights, pts[s : s + chunk], gradient=gradient) for s in range(0, len(pts), chunk)]
        if gradient:
            return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        return np.concatenate(parts)

    evaluator.fast_sum = fast
    evaluator.cover = cover
    return evaluator
