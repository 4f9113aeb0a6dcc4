"""Grid (particle-mesh) sums for the multi-order kernel: the Ewald-type split, its near part, and
:class:`GridSum` (the FFT grid itself: :mod:`o3drbf.solvers.fast.fftgrid`)."""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.rbf import compiled
from o3drbf.rbf.kernels import Kernel, MultiOrder
from o3drbf.rbf.sums import kernel_matrix, kernel_sum
from o3drbf.solvers.base import memory_limit_or_default
from o3drbf.solvers.fast.fftgrid import Mesh
from o3drbf.solvers.fast.neighbours import HAVE_GRID, CellList, csr_matvec, default_neighbours, nearest_distance, neighbour_radius, \
    restrict_near, store_near
from o3drbf.solvers.fast.tolerance import DEFAULT_EPS, clip_eps

__all__ = ["GridSum", "grid_bytes", "grid_budget", "outside_centres", "split_design",
           "near_table", "near_entries", "long_part", "GRID_BUDGET", "DIRECT_PAIRS", "OUTSIDE_BLOCK_SHARE", "OUTSIDE_BLOCK_MIN",
           "outside_block_bytes", "COMPANION_TOLERANCES", "served_tolerance", "TABLE_EPS"]


#: From this tolerance on, an evaluation at targets sums the far centres (:func:`outside_centres`) from the
#: kernel's tables (:class:`o3drbf.rbf.compiled.KernelTable`: 1e-8 of a value, 1e-5 of a gradient), faster
#: than the exact kernel and far inside the tolerance.
TABLE_EPS = 1e-4


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
    """sum_c coef_c e^{-kappa_c^2 extra^2 / 2} psi_long(r; kappa_c, sigma).

    Real decay rates and coefficients (most kernels) are summed in real arithmetic, where SciPy's
    ``erfc`` and ``erfcx`` are several times faster than on complex arguments, to the same accuracy."""
    parts = [(complex(kappa), complex(coef)) for kappa, coef in _components(kernel)]
    if all(kappa.imag == 0 and coef.imag == 0 for kappa, coef in parts):
        out = np.zeros(np.shape(r))
        for kappa, coef in parts:
            out += coef.real * math.exp(-(kappa.real * extra) ** 2 / 2) * _psi_long(r, kappa.real, sigma)
        return out
    out = np.zeros(np.shape(r), dtype=complex)
    for kappa, coef in parts:
        damp = np.exp(-(kappa * extra) ** 2 / 2)
        out += coef * damp * _psi_long(r, kappa, sigma)
    return out.real


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


def near_entries(centres, tree: cKDTree, cut: float, n_core: int) -> float:
    """Entries of the near-field matrix of cut-off ``cut`` over ``n_core`` centres, from a seeded
    sample of 1,000 of ``centres`` (``tree`` is theirs)."""
    n = len(centres)
    sample = centres[np.random.default_rng(1).choice(n, min(n, 1000), replace=False)]
    return float(np.mean(tree.query_ball_point(sample, cut, return_length=True))) * n_core


#: Kernel evaluations per product allowed for the far centres a grid leaves out (summed directly).
DIRECT_PAIRS = 50_000_000
#: :meth:`GridSum.from_subset` gives a subset of at most this share of the centres (a preconditioner's coarse
#: level) a grid sum of its own, with ``SUBSET_NEIGHBOURS`` in its near field: a far coarser grid than that of
#: all the centres, whose FFTs would cost as much for the few sources as for all of them.
SUBSET_SHARE = 0.25
SUBSET_NEIGHBOURS = 32
#: A stored block of the far centres' kernel (:meth:`GridSum._outside_block`, :meth:`GridSum.at`) may take this
#: share of the memory limit, and at least ``OUTSIDE_BLOCK_MIN`` bytes: a fixed cap summed the exterior
#: sphere's few dozen centres directly at every product (several times a product) from about half a million centres.
OUTSIDE_BLOCK_SHARE = 0.05
OUTSIDE_BLOCK_MIN = 256 * 2**20
#: Tolerances of a grid sum's looser companions (:meth:`GridSum._tier`), loosest first: 1e-3 and 1e-4 serve a
#: solve's relaxed products (never looser than ``RELAX_CAP``), 1e-2 the coarse rows of the preconditioner's
#: second correction (``TwoLevelSettings.post_eps``).
COMPANION_TOLERANCES = (1e-2, 1e-3, 1e-4)


def served_tolerance(eps: float | None, own: float) -> float:
    """The tolerance a request at ``eps`` to a grid sum at ``own`` is served at: the loosest of
    ``COMPANION_TOLERANCES`` at least ten times ``own`` and no looser than ``eps``, else ``own``."""
    for tol in COMPANION_TOLERANCES:
        if eps is not None and tol <= eps and tol >= 10 * own:
            return tol
    return own


def outside_block_bytes(limit: int | None = None) -> int:
    """Bytes a stored block of the far centres' kernel may take under the memory limit ``limit``
    (default :func:`memory_limit_or_default`): ``OUTSIDE_BLOCK_SHARE`` of it, at least ``OUTSIDE_BLOCK_MIN``."""
    return int(max(OUTSIDE_BLOCK_MIN, OUTSIDE_BLOCK_SHARE * memory_limit_or_default(limit)))


def grid_bytes(lo, hi, h: float, half: int) -> int:
    """Bytes the grid backend's FFT arrays take over the box ``[lo, hi]`` ((3,) each) at spacing ``h``
    with a spreading half-width of ``half`` cells (what a grid's budget, :func:`grid_budget`, is compared with)."""
    return Mesh.nbytes(lo, hi, h, half)


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
        :func:`default_neighbours`.
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
    store : bool, optional
        Keep the near field of the products as a sparse matrix (fast
        products) or sum it afresh at every product by the cell list (no
        memory); default :func:`~o3drbf.solvers.fast.neighbours.store_near`
        of its estimated size.  The looser companions follow this choice.
    box : (2, 3) array_like, optional
        Corners of a box of targets the grid covers from the start (as
        :meth:`cover` would enlarge it, when within the budget; else the
        centres' box alone, as without it).

    Raises
    ------
    ValueError
        Not a multi-order kernel, confluent, or numba missing.
    MemoryError
        The grid would exceed the budget.
    """

    def __init__(self, kernel: Kernel, centres, eps: float = DEFAULT_EPS, neighbours: int | None = None,
                 budget: int | None = None, tree: cKDTree | None = None, outside=None, radius: float | None = None,
                 store: bool | None = None, box=None):
        if not HAVE_GRID:
            raise ValueError("the grid backend needs numba, which is not installed")
        if not isinstance(kernel, MultiOrder) or kernel.coefficients is None:
            raise ValueError(f"the grid backend supports the non-confluent multi-order kernel, not {kernel!r}")
        t0 = time.perf_counter()
        self.kernel = kernel
        self.centres = np.ascontiguousarray(centres, dtype=float)
        self.n = n = len(self.centres)
        self.eps = clip_eps(eps)
        eps = self.eps / 10  # the split is designed at a tenth of the tolerance, so that the result stays below it
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
        full = Mesh.nbytes(self.centres.min(axis=0), self.centres.max(axis=0), h, half, single)
        if outside is None:
            outside = outside_centres(self.centres, self.tree, rc)
        self._set_core(outside)
        lo, hi = self._cc.min(axis=0), self._cc.max(axis=0)
        need = Mesh.nbytes(lo, hi, h, half, single)
        self._fixed_budget = None if budget is None else int(budget)
        self.budget = grid_budget(budget)
        self._eval_mesh = None
        if box is not None:  # the targets' box too, at once (no grid over the centres alone first)
            b = np.asarray(box, dtype=float)
            wide = np.minimum(lo, b[0]), np.maximum(hi, b[1])
            if Mesh.nbytes(*wide, h, half, single) <= self.budget:
                lo, hi = wide
                need = Mesh.nbytes(lo, hi, h, half, single)
        if need > self.budget:
            raise MemoryError(f"the grid of fast sums over {n:,} centres needs ~{need / 2**30:.1f} GB of FFT arrays "
                              f"(budget {self.budget / 2**30:.1f} GB)")
        # Near part: phi_S = phi - phi_L on a table, cut where |phi_S| < eps phi(0).
        self.rc, self.tab, self.dr, self.dtab = near_table(kernel, rc, sigma, eps)
        self.store = store_near(near_entries(self.centres, self.tree, self.rc, len(self._cc)), self.budget) if store is None \
            else bool(store)
        self._meshes = []
        self.mesh = self._mesh(lo, hi)
        self.cells = CellList(self._cc, self.rc)
        self._near_m = None
        key = np.floor((self._cc - self.mesh.origin) / (4 * h)).astype(np.int64)
        self._perm = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))  # grid order: cache-friendly spreading
        self._sorted = np.ascontiguousarray(self._cc[self._perm])
        self.info = {"mode": "grid (Gaussian split: FFT far part + sparse near part)", "split": "grid",
                     "near_radius": self.rc, "sigma": sigma, "h": h, "grid": self.mesh.shape,
                     "fft": self.mesh.fshape, "stencil": 2 * half + 1, "grid_bytes": need,
                     "grid_bytes_all_centres": full, "outside": len(self.outside),
                     "near_field": "stored" if self.store else "summed on the fly",
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
        m = Mesh(lo, hi, self.h, self.s, self.half, self._ktable, np.float32 if self.eps >= 1e-4 else np.float64)
        self._meshes = [m] + self._meshes[:1]
        return m

    def _mesh_bytes(self, lo, hi) -> int:
        return Mesh.nbytes(lo, hi, self.h, self.half, self.eps >= 1e-4)

    def _set_core(self, outside):
        """Split the centres into the grid's (core) and the few far ones summed directly."""
        out = np.unique(np.asarray(outside, dtype=np.int64).reshape(-1))
        if len(out) and (out[0] < 0 or out[-1] >= self.n or len(out) >= self.n):
            raise ValueError("outside must index fewer than all of the centres; pass None to choose them")
        self.outside = out
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

    @property
    def near(self):
        """Sparse matrix of phi_S between the grid's (core) centres (built on first use)."""
        if self._near_m is None:
            parent = self.__dict__.get("_near_parent")
            if parent is not None and parent._near_m is not None and parent.rc >= self.rc:
                self._near_m = restrict_near(parent._near_m, self._cc, self.rc, self.tab, self.dr)  # no cell search
            else:
                self._near_m = self.cells.matrix(self._cc, self.tab, self.dr, dtype=np.float32)
            self.info["near_nnz"] = int(self._near_m.nnz)
        return self._near_m

    def _add_near(self, wc, outc, cells=None):
        """``outc += near @ wc`` (core centres): the stored matrix, or the cell-list sum from ``cells``
        (default all core centres; ``wc`` in their order) at every core centre."""
        if cells is None and self.store:
            csr_matvec(self.near, wc, outc)
            return
        if cells is None:  # sources = targets
            outc += self.cells.self_sum(wc, self.tab, self.dr)
            return
        part = np.zeros(len(self._cc))
        cells.add_sum(self.cells.sorted, wc, self.tab, self.dtab, self.dr, part)  # targets in cell order: cache-friendly
        outc[self.cells.order] += part

    def _tier(self, eps):
        """The loosest operator at least as accurate as ``eps``: this one, or a cached
        looser companion (a tolerance of ``COMPANION_TOLERANCES``, :meth:`tier_radius`: a grid no finer,
        single-precision FFTs, a 9-11 point stencil instead of 13-15, a smaller near part)."""
        tol = self._tolerance_for(eps)
        if tol == self.eps:
            return self
        tiers = self.__dict__.setdefault("_tiers", {})
        if tol not in tiers:
            tiers[tol] = GridSum(self.kernel, self.centres, eps=tol, radius=self.tier_radius(tol),
                                 tree=self.tree, outside=self.outside, budget=self._fixed_budget, store=self.store)
            tiers[tol]._outside_held = self.__dict__.setdefault("_outside_held", [])  # the same far block
            tiers[tol]._near_parent = self  # its near field: a part of this one's
        return tiers[tol]

    def tier_radius(self, tol: float) -> float:
        """Near-field radius of the companion at tolerance ``tol``: that of ~300 neighbours, or more where
        that would make its grid finer than this one's (a looser companion never takes more FFT memory)."""
        rc = self.__dict__.get("_tier_rc")
        if rc is None:  # the same for every companion: found once
            rc = self._tier_rc = neighbour_radius(self.centres, self.tree, min(300, max(self.n // 300, 64)))
        return max(rc, self.h / split_design(1.0, clip_eps(tol) / 10)[2])

    def weights_over(self, centres, index, weights) -> np.ndarray | None:
        """``weights`` of ``centres`` as weights over this grid sum's centres (zero at the others), when its
        centres at ``index`` are exactly ``centres`` (e.g. a robust refit's: the same constraints, some left
        out), so that it sums them; else None."""
        index = np.asarray(index)
        centres = np.asarray(centres, dtype=float)
        if not (index.shape == (len(centres),) and (index.size == 0 or (index.min() >= 0 and index.max() < self.n))
                and np.array_equal(self.centres[index], centres)):
            return None
        full = np.zeros(self.n)
        full[index] = np.asarray(weights, dtype=float)
        return full

    def matvec(self, w, eps: float | None = None) -> np.ndarray:
        """(Phi w)_i, self term included, to relative accuracy ``eps`` (default: the operator's)."""
        w = np.asarray(w, dtype=float)
        op = self._tier(eps)
        if op is not self:
            return op.matvec(w)
        p = self._perm
        wc = w if self._core is None else w[self._core]
        u = self.mesh.potential(self._sorted, np.ascontiguousarray(wc[p]), scratch=True)
        outc = np.empty(len(self._cc))
        outc[p] = self.mesh.gather(u, self._sorted, False)
        self._add_near(wc, outc)
        if self._core is None:
            return outc
        # The far centres: summed directly (few of them), both ways.
        out = np.empty(self.n)
        o = self.outside
        block = self._outside_block()
        if block is None:
            out[self._core] = outc + kernel_sum(self.kernel, self.centres[o], w[o], self._cc)
            out[o] = kernel_sum(self.kernel, self.centres, w, self.centres[o])
            return out
        to_core, among = block
        out[self._core] = outc + to_core @ w[o]
        out[o] = wc @ to_core + among @ w[o]
        return out

    #: A fixed cap on the bytes of the stored kernel block between the grid's centres and the far ones it
    #: leaves out (:meth:`_outside_block`), and of the one between :meth:`at`'s targets and the far centres,
    #: or None: :func:`outside_block_bytes` of the grid's budget.  Above it, the far centres are summed
    #: directly at every product.
    OUTSIDE_BLOCK_BYTES = None

    @property
    def outside_cap(self) -> int:
        """Bytes a stored block of the far centres' kernel may take (:attr:`OUTSIDE_BLOCK_BYTES`)."""
        return outside_block_bytes(self.budget) if self.OUTSIDE_BLOCK_BYTES is None else int(self.OUTSIDE_BLOCK_BYTES)

    def _outside_block(self):
        """``(phi(core centres, far centres), phi(far, far))``, built on first use and shared with the looser
        companions (same centres), or None when it would exceed :attr:`outside_cap`."""
        held = self.__dict__.setdefault("_outside_held", [])
        if not held:
            o = self.outside
            if len(self._cc) * len(o) * 8 > self.outside_cap:
                held.append(None)
            else:
                far = self.centres[o]
                held.append((kernel_matrix(self.kernel, self._cc, far, order="C"), kernel_matrix(self.kernel, far, order="C")))
        return held[0]

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

    def at(self, targets):
        """``w -> sum_j w_j phi(|x - c_j|)`` at fixed ``targets`` ((M, 3)): :meth:`evaluate` with the
        targets' grid order, and the few beyond the grid (summed directly), found once."""
        t = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        mesh = self.mesh if self._eval_mesh is None else self._eval_mesh
        inside = mesh.inside(t)
        far = np.nonzero(~inside)[0]
        if len(far) * self.n > DIRECT_PAIRS:
            if not self.cover(t.min(axis=0), t.max(axis=0)):
                raise MemoryError(f"a grid over {len(t):,} targets exceeds the budget of {self.budget / 2**30:.1f} GB")
            mesh, far = self.mesh, far[:0]
        rows = np.nonzero(inside)[0] if len(far) else np.arange(len(t))
        key = np.floor((t[rows] - mesh.origin) / (4 * mesh.h)).astype(np.int64)
        rows = rows[np.lexsort((key[:, 2], key[:, 1], key[:, 0]))]  # grid order: stencil reads stay in cache
        ts = np.ascontiguousarray(t[rows])
        o = self.outside
        # The far centres' kernel at the targets: stored once when small (a product's cost otherwise).
        block = kernel_matrix(self.kernel, ts, self.centres[o], order="C") \
            if self._core is not None and len(ts) * len(o) * 8 <= self.outside_cap else None

        def apply(w):
            w = np.asarray(w, dtype=float)
            wc = w if self._core is None else w[self._core]
            u = mesh.potential(self._sorted, np.ascontiguousarray(wc[self._perm]), scratch=True)
            vals = mesh.gather(u, ts, False)
            del u
            self.cells.add_sum(ts, wc, self.tab, self.dtab, self.dr, vals, None)
            if block is not None:
                vals += block @ w[o]
            elif self._core is not None:
                vals += kernel_sum(self.kernel, self.centres[o], w[o], ts)
            out = np.empty(len(t))
            out[rows] = vals
            if len(far):
                out[far] = kernel_sum(self.kernel, self.centres, w, t[far])
            return out

        apply.operator = self
        return apply

    def rows(self, subset, eps: float | None = None):
        """``w -> (Phi w)[subset]``: a product's rows at some of the centres, to relative accuracy ``eps``
        (default: the operator's; a looser one is served by a looser companion, as in :meth:`matvec`).

        Only those rows are summed: the grid potential of all the weights, gathered, with the near field,
        at the subset alone (:meth:`at`); the far centres among them as in :meth:`matvec`.  For a few
        rows this skips the gather and the near field at every centre.

        Parameters
        ----------
        subset : (M,) int array
            Indices of the centres.
        eps : float, optional
        """
        op = self._tier(eps)
        subset = np.asarray(subset, dtype=np.int64).reshape(-1)
        if op._core is None:
            return op.at(op.centres[subset])
        grid_rows = np.nonzero(op._core_pos[subset] >= 0)[0]
        far_rows = np.nonzero(op._core_pos[subset] < 0)[0]
        on_grid = op.at(op.centres[subset[grid_rows]])  # inside the grid: never enlarges it
        far_pos = np.searchsorted(op.outside, subset[far_rows])

        def apply(w):
            w = np.asarray(w, dtype=float)
            out = np.empty(len(subset))
            out[grid_rows] = on_grid(w)
            if len(far_rows):
                block = op._outside_block()
                if block is None:
                    out[far_rows] = kernel_sum(op.kernel, op.centres, w, op.centres[subset[far_rows]])
                else:
                    to_core, among = block
                    out[far_rows] = (w[op._core] @ to_core + among @ w[op.outside])[far_pos]
            return out

        return apply

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
        self.cells.add_sum(ts, wc, self.tab, self.dtab, self.dr, vals, grad if gradient else None)
        if self._core is not None:
            o = self.outside
            extra = kernel_sum(self.kernel, self.centres[o], w[o], ts, gradient=gradient, table=self._far_table())
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

    def _far_table(self):
        """The kernel's tables for the far centres' sums at targets (:meth:`evaluate`), from ``TABLE_EPS`` on; else None."""
        return None if self.eps < TABLE_EPS else compiled.kernel_table(self.kernel)

    def _tolerance_for(self, eps) -> float:
        """The tolerance a request at ``eps`` is served at (:func:`served_tolerance`)."""
        return served_tolerance(eps, self.eps)

    def from_subset(self, subset):
        """A callable ``(w_sub, eps) -> sum_{j in subset} w_j phi(|c_i - c_j|)`` at every centre.

        A subset of at most ``SUBSET_SHARE`` of the centres (a preconditioner's
        coarse level) is summed by a grid sum of its own, built once for each
        tolerance asked (:meth:`at` every centre); a larger one on this grid."""
        subset = np.asarray(subset)
        if 64 <= len(subset) <= SUBSET_SHARE * self.n:
            own = {}

            def apply_own(w, eps=None):
                tol = self._tolerance_for(eps)
                if tol not in own:  # (a full-accuracy request: a tenth of it, since the targets are not the sources)
                    sub = GridSum(self.kernel, self.centres[subset], eps=tol if tol > self.eps else clip_eps(tol / 10),
                                  neighbours=SUBSET_NEIGHBOURS, budget=self._fixed_budget, store=False)
                    sub.OUTSIDE_BLOCK_BYTES = self.OUTSIDE_BLOCK_BYTES
                    own[tol] = sub.at(self.centres)
                return own[tol](w)

            apply_own.sums = own  # tolerance -> the subset's sum at every centre (its ``operator``: the grid sum)
            return apply_own
        if self._core is None:
            csub, cmask, osub = subset, None, subset[:0]
        else:
            cmask = self._core_pos[subset] >= 0
            csub, osub = self._core_pos[subset[cmask]], subset[~cmask]
            far_pos = np.searchsorted(self.outside, osub)  # osub's places among the far centres
        cache = {}

        def apply(w, eps=None):
            op = self._tier(eps)
            w = np.asarray(w, dtype=float)
            if op not in cache:
                key = np.floor((op._cc[csub] - op.mesh.origin) / (4 * op.h)).astype(np.int64)
                pos = np.lexsort((key[:, 2], key[:, 1], key[:, 0]))
                cols = op.near[:, csub].tocsr() if op.store else CellList(op._cc[csub], op.rc)
                cache[op] = (np.ascontiguousarray(op._cc[csub[pos]]), pos, cols)
            pts, pos, cols = cache[op]
            wc = w if cmask is None else w[cmask]
            outc = np.empty(len(op._cc))
            if len(csub):
                u = op.mesh.potential(pts, np.ascontiguousarray(wc[pos]), scratch=True)
                outc[op._perm] = op.mesh.gather(u, op._sorted, False)
                if op.store:
                    csr_matvec(cols, wc, outc)
                else:
                    op._add_near(wc, outc, cells=cols)
            else:
                outc[:] = 0.0
            if self._core is None:
                return outc
            out = np.zeros(self.n)
            out[self._core] = outc
            o = self.outside
            block = self._outside_block()
            if block is None:
                if len(osub):
                    out += kernel_sum(self.kernel, self.centres[osub], w[~cmask], self.centres)
                out[o] = kernel_sum(self.kernel, self.centres[subset], w, self.centres[o])
                return out
            to_core, among = block
            wo = np.zeros(len(o))
            if len(osub):
                wo[far_pos] = w[~cmask]
                out[self._core] += to_core @ wo
            out[o] = wc @ to_core[csub] + among @ wo
            return out

        return apply


def outside_centres(centres, tree: cKDTree, radius: float, max_pairs: int | None = None) -> np.ndarray:
    """Indices of the few far centres a grid need not cover (summed directly instead).

    A centre is isolated when no other centre lies within ``radius`` (the
    near-field radius, ~1,000 neighbours for the others): e.g. the sparse
    sphere of exterior constraints around the bounding box, which would
    otherwise set the grid's box (and its memory).  The grid then covers the box of the
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
    busy = nearest_distance(centres, tree) <= radius
    if busy.sum() < 2:
        return np.zeros(0, np.int64)
    lo, hi = centres[busy].min(axis=0), centres[busy].max(axis=0)
    out = np.nonzero(((centres < lo) | (centres > hi)).any(axis=1))[0]
    if len(out) * n > cap and len(out) > 1e-3 * n:  # a few (the sphere) are summed directly even at large N
        return np.zeros(0, np.int64)
    return out.astype(np.int64)
