"""Neighbour lists: KD-tree pair chunks and sparse matrices, the compiled cell list, near-field sizes."""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from o3drbf.prep.sampling import spatial_order  # (the solvers' order of the centres; defined with the points)
from o3drbf.solvers.base import memory_limit_or_default

__all__ = ["HAVE_GRID", "NNZ_BYTES", "PRODUCT_NEIGHBOURS_MAX", "NEAR_STORE_BYTES", "CELLS_PER_POINT", "store_near", "pairs_chunks", "mean_neighbours", "sparse_matrix",
           "CellList", "default_neighbours", "product_neighbours", "RADIUS_SAMPLE", "radius_sample", "neighbour_radius", "nearest_distance", "csr_matvec", "restrict_near", "spatial_order"]

#: Bytes per stored entry of a near-field matrix (float32 value, int32 column index).
NNZ_BYTES = 8
#: Pairs handled per chunk when building neighbour lists / summing sparse terms.
PAIR_CHUNK = 8_000_000

try:  # numba is a dependency; without it the grid backend is unavailable
    import numba

    njit, prange, HAVE_GRID = numba.njit, numba.prange, True
except ImportError:  # pragma: no cover
    HAVE_GRID = False

    def njit(*a, **k):
        return lambda f: f

    prange = range


#: The fast sums' compiled loops (near field, the grid's spreading and gathering) may reorder sums and
#: fuse multiply-adds, so that they vectorize: rounding-level changes only.  The cell-list pass and the
#: restriction of a larger near field share these flags, so they value a pair alike.
LOOP_MATH = {"reassoc", "contract"}
#: The CSR product's flags: fused multiply-adds, no reordering.  Reordering lets LLVM vectorize a row's sum
#: with gathers of ``x``, slower than scalar loads on some processors
#: (benchmarks/recorded/fast_solver.md, session 32); four running sums keep the scalar loop off the
#: add's latency instead.
CSR_MATH = {"contract"}


@njit(cache=True, parallel=True, fastmath=CSR_MATH)
def _csr_matvec(indptr, indices, data, x, out):
    # Unsigned column indices (no negative-index wrap per read); each row in four running sums, in a fixed order.
    for i in prange(out.shape[0]):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        k = indptr[i]
        end = indptr[i + 1]
        while k + 4 <= end:
            a0 += np.float64(data[k]) * x[np.uint64(indices[k])]
            a1 += np.float64(data[k + 1]) * x[np.uint64(indices[k + 1])]
            a2 += np.float64(data[k + 2]) * x[np.uint64(indices[k + 2])]
            a3 += np.float64(data[k + 3]) * x[np.uint64(indices[k + 3])]
            k += 4
        while k < end:
            a0 += np.float64(data[k]) * x[np.uint64(indices[k])]
            k += 1
        out[i] += (a0 + a1) + (a2 + a3)


def csr_matvec(a, x, out=None) -> np.ndarray:
    """``a @ x`` for a CSR matrix ``a`` (float64 or float32 entries) and a vector ``x``, on all threads
    (SciPy's product is serial); with ``out``, ``out += a @ x`` in place and ``out`` returned.  Each row
    is summed in double precision by the same code whichever thread takes it, so the result does not
    depend on the thread count.

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> a = sp.random(50, 40, density=0.2, format="csr", random_state=0)
    >>> x = np.arange(40.0)
    >>> bool(np.allclose(csr_matvec(a, x), a @ x))
    True
    """
    x = np.ascontiguousarray(x, dtype=float)
    if not HAVE_GRID or not sp.isspmatrix_csr(a) or a.dtype not in (np.float64, np.float32):  # pragma: no cover
        res = a @ x
        if out is None:
            return res
        out += res
        return out
    if out is None:
        out = np.zeros(a.shape[0])
    _csr_matvec(a.indptr, a.indices, a.data, x, out)
    return out


@njit(cache=True, parallel=True, fastmath=LOOP_MATH)
def _restrict_pass(fill, indptr, indices, pts, rc, tab, dr, counts, out_indptr, out_indices, out_data):
    rc2 = rc * rc
    nt = tab.shape[0]
    for i in prange(indptr.shape[0] - 1):
        c = out_indptr[i] if fill else 0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            d0 = pts[i, 0] - pts[j, 0]; d1 = pts[i, 1] - pts[j, 1]; d2 = pts[i, 2] - pts[j, 2]
            r2 = d0 * d0 + d1 * d1 + d2 * d2
            if r2 > rc2:
                continue
            if fill:
                x = math.sqrt(r2) / dr
                ii = min(int(x), nt - 2)
                f = x - ii
                out_indices[c] = j
                out_data[c] = tab[ii] * (1 - f) + tab[ii + 1] * f
            c += 1
        if not fill:
            counts[i] = c


def restrict_near(matrix, points, radius: float, tab, dr: float) -> sp.csr_matrix:
    """The near-field matrix of a smaller ``radius`` from a larger one's pattern: the pairs of ``matrix``
    (square, rows and columns both ``points``) within ``radius``, valued by ``tab`` as
    :meth:`CellList.matrix` values them (the same entries, each row in ``matrix``'s order), without
    the cell search.

    Parameters
    ----------
    matrix : (N, N) csr_matrix
        A near-field matrix whose radius is at least ``radius``.
    points : (N, 3) float array
    radius : float
    tab : (T,) array
        The function at ``r = 0, dr, 2 dr, ...``.
    dr : float
    """
    pts = np.ascontiguousarray(points, dtype=float)
    m = matrix.shape[0]
    counts = np.zeros(m, np.int64)
    # (the counting pass's unused outputs of the filling pass's types: one compiled variant for both)
    unused_i, unused_d = np.zeros(1, matrix.indices.dtype), np.zeros(1, matrix.dtype)
    indptr = np.zeros(m + 1, np.int64)
    _restrict_pass(False, matrix.indptr, matrix.indices, pts, float(radius), tab, float(dr), counts, indptr, unused_i, unused_d)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(indptr[-1], matrix.indices.dtype)
    data = np.empty(indptr[-1], matrix.dtype)
    _restrict_pass(True, matrix.indptr, matrix.indices, pts, float(radius), tab, float(dr), counts, indptr, indices, data)
    return sp.csr_matrix((data, indices, indptr), shape=matrix.shape)


def pairs_chunks(tree_s: cKDTree, targets: np.ndarray, radius: float, per_target: float):
    """Yield (offset, i, j, r) for target chunks: all sources within ``radius`` of each target."""
    m = len(targets)
    step = max(1, int(PAIR_CHUNK / max(per_target, 1.0)))
    for start in range(0, m, step):
        t = targets[start : start + step]
        tt = cKDTree(t)
        arr = tt.sparse_distance_matrix(tree_s, radius, output_type="ndarray")
        yield start, len(t), arr["i"].astype(np.int64), arr["j"].astype(np.int64), arr["v"]


def mean_neighbours(tree_s: cKDTree, targets: np.ndarray, radius: float, sample: int = 2000) -> float:
    """Average number of sources within ``radius`` of a target (from a sample)."""
    if len(targets) == 0:
        return 0.0
    rng = np.random.default_rng(0)
    idx = rng.choice(len(targets), min(sample, len(targets)), replace=False)
    counts = tree_s.query_ball_point(targets[idx], radius, return_length=True)
    return float(np.mean(counts))


def sparse_matrix(tree_s, targets, radius, value, per_target, n_sources, drop_self=False):
    """CSR matrix of ``value(r, i, j)`` over all (target i, source j) pairs with r <= radius."""
    blocks = []
    for start, m, i, j, r in pairs_chunks(tree_s, targets, radius, per_target):
        if drop_self:
            keep = (i + start) != j
            i, j, r = i[keep], j[keep], r[keep]
        v = value(r, i + start, j)
        blocks.append(sp.csr_matrix((v, (i, j)), shape=(m, n_sources)))
    if not blocks:
        return sp.csr_matrix((0, n_sources))
    return sp.vstack(blocks, format="csr")


@njit(cache=True)
def _cell_keys(pts, lo, cell, dims):
    n = pts.shape[0]
    key = np.empty(n, np.int64)
    for p in range(n):
        i = min(max(int((pts[p, 0] - lo[0]) / cell), 0), dims[0] - 1)
        j = min(max(int((pts[p, 1] - lo[1]) / cell), 0), dims[1] - 1)
        k = min(max(int((pts[p, 2] - lo[2]) / cell), 0), dims[2] - 1)
        key[p] = (i * dims[1] + j) * dims[2] + k
    return key


# What one pass of the near-field loop does with each pair within the radius.
_COUNT, _FILL, _SUM, _SUM_GRAD = 0, 1, 2, 3


@njit(cache=True, parallel=True, fastmath=LOOP_MATH)
def _near_pass(mode, tp, sp_, order, start, lo, cell, reach, dims, rc, tab, dtab, dr, wsorted, counts, indptr, indices, data,
               out, grad):
    """The one loop over (target, source) pairs within ``rc``, by the (2 reach + 1)^3 cells around each target
    (cells of side ``rc / reach``).

    ``mode`` _COUNT: ``counts[p]`` = pairs of target p; _FILL: the CSR row p (``indptr``, ``indices``
    = source index, ``data`` = table value); _SUM / _SUM_GRAD: ``out[p] += sum_q w_q tab(r_pq)`` (and
    ``grad[p] += sum_q w_q dtab(r_pq) (t_p - s_q)``).  The table is linearly interpolated at ``r / dr``.
    ``sp_`` is (3, N): the sorted points' coordinates, one row each.  The cells along z in a column
    are consecutive keys, so their points are one run; points and tables are read
    with unsigned offsets (no negative-index wrap) and the sums may be reordered, so the runs vectorize."""
    m = tp.shape[0]
    rc2 = rc * rc
    nt = tab.shape[0]
    sx = sp_[0]; sy = sp_[1]; sz = sp_[2]
    for p in prange(m):
        t0 = tp[p, 0]; t1 = tp[p, 1]; t2 = tp[p, 2]
        i0 = int((t0 - lo[0]) / cell); j0 = int((t1 - lo[1]) / cell); k0 = int((t2 - lo[2]) / cell)
        k_lo = max(k0 - reach, 0); k_hi = min(k0 + reach + 1, dims[2])
        c = indptr[p] if mode == _FILL else 0
        acc = 0.0; g0 = 0.0; g1 = 0.0; g2 = 0.0
        for i in range(max(i0 - reach, 0), min(i0 + reach + 1, dims[0])):
            for j in range(max(j0 - reach, 0), min(j0 + reach + 1, dims[1])):
                if k_lo >= k_hi:
                    continue
                row = (i * dims[1] + j) * dims[2]
                for q in range(start[row + k_lo], start[row + k_hi]):
                    uq = np.uint64(q)
                    d0 = t0 - sx[uq]; d1 = t1 - sy[uq]; d2 = t2 - sz[uq]
                    r2 = d0 * d0 + d1 * d1 + d2 * d2
                    if r2 > rc2:
                        continue
                    if mode == _COUNT:
                        c += 1
                        continue
                    x = math.sqrt(r2) / dr
                    ii = min(int(x), nt - 2)
                    f = x - ii
                    ui = np.uint64(ii)
                    v = tab[ui] * (1 - f) + tab[ui + np.uint64(1)] * f
                    if mode == _FILL:
                        indices[c] = order[uq]
                        data[c] = v
                        c += 1
                    else:
                        acc += wsorted[uq] * v
                        if mode == _SUM_GRAD:
                            g = wsorted[uq] * (dtab[ui] * (1 - f) + dtab[ui + np.uint64(1)] * f)
                            g0 += g * d0; g1 += g * d1; g2 += g * d2
        if mode == _COUNT:
            counts[p] = c
        elif mode != _FILL:
            out[p] += acc
            if mode == _SUM_GRAD:
                grad[p, 0] += g0; grad[p, 1] += g1; grad[p, 2] += g2


#: A cell list takes cells of half its radius when there are at most this many a point (else of the radius:
#: a few far points, such as an exterior sphere, can make the box, and the cells, far larger than the data).
CELLS_PER_POINT = 4


class CellList:
    """Points binned into cubic cells of side ``radius`` (or half of it), for the pairs of targets and points
    within ``radius``.

    One compiled loop (over the cells around each target) serves both uses:
    the sparse matrix of a tabulated radial function over those pairs
    (:meth:`matrix`) and its sum with weights, with gradients (:meth:`add_sum`).

    Parameters
    ----------
    points : (N, 3) array
        The sources.
    radius : float
        Pairs farther apart are left out.

    Examples
    --------
    >>> import numpy as np
    >>> pts = np.array([[0.0, 0, 0], [0.5, 0, 0], [3.0, 0, 0]])
    >>> tab = np.linspace(1.0, 0.0, 11)   # 1 - r sampled on [0, 1], every tenth
    >>> CellList(pts, 1.0).matrix(pts, tab, 0.1).toarray().round(2)
    array([[1. , 0.5, 0. ],
           [0.5, 1. , 0. ],
           [0. , 0. , 1. ]])
    """

    def __init__(self, points, radius: float):
        pts = np.ascontiguousarray(points, dtype=float)
        self.radius = float(radius)
        self.n = len(pts)
        self.lo = pts.min(axis=0)
        span = pts.max(axis=0) - self.lo
        # Cells of half the radius where there are not many more of them than points: a target then reads
        # 5^3 of them, 15.6 cubed radii (27 with cells of the radius), fewer pairs beyond the radius.
        self.reach = 1 + int(np.prod(np.ceil(2 * span / self.radius) + 1) <= CELLS_PER_POINT * max(self.n, 1))
        self.cell = self.radius / self.reach
        self.dims = np.maximum(np.ceil(span / self.cell).astype(np.int64), 1)
        key = _cell_keys(pts, self.lo, self.cell, self.dims)
        self.order = np.argsort(key, kind="stable")
        self.start = np.zeros(int(np.prod(self.dims)) + 1, np.int64)  # the first point of each cell
        np.cumsum(np.bincount(key, minlength=len(self.start) - 1), out=self.start[1:])
        self.sorted = np.ascontiguousarray(pts[self.order])
        self._rows = np.ascontiguousarray(self.sorted.T)  # (3, N): one coordinate a row, for the compiled loop
        self._order32 = self.order.astype(np.int32)

    def _pass(self, mode, targets, tables, wsorted, counts, csr, sums):
        """One :func:`_near_pass`: ``tables`` (tab, dtab, dr), ``csr`` (indptr, indices, data), ``sums`` (out, grad)."""
        tab, dtab, dr = tables
        _near_pass(mode, targets, self._rows, self._order32, self.start, self.lo, self.cell, self.reach, self.dims,
                   self.radius, tab, dtab, dr, wsorted, counts, *csr, *sums)

    def matrix(self, targets, tab, dr: float, dtype=np.float64) -> sp.csr_matrix:
        """CSR matrix (targets x points) of ``tab`` (sampled every ``dr``, interpolated linearly) at each
        pair's distance, over the pairs within the radius.

        Parameters
        ----------
        targets : (M, 3) float array, C-contiguous
        tab : (T,) array
            The function at ``r = 0, dr, 2 dr, ...``; it must reach beyond the radius.
        dr : float
        dtype : {numpy.float64, numpy.float32}
            Of the entries (computed in double precision, stored in this one).
        """
        m = len(targets)
        i64, f64 = np.zeros(1, np.int64), np.zeros(1)
        counts = np.zeros(m, np.int64)
        # (unused entries of the filling pass's type: the two passes share one compiled variant)
        self._pass(_COUNT, targets, (tab, tab, dr), f64, counts, (i64, np.zeros(1, np.int32), np.zeros(1, dtype)), (f64, np.zeros((1, 3))))
        indptr = np.zeros(m + 1, np.int64)
        np.cumsum(counts, out=indptr[1:])
        del counts
        indices = np.empty(indptr[-1], np.int32)
        data = np.empty(indptr[-1], dtype)
        self._pass(_FILL, targets, (tab, tab, dr), f64, i64, (indptr, indices, data), (f64, np.zeros((1, 3))))
        return sp.csr_matrix((data, indices, indptr), shape=(m, self.n))

    def self_sum(self, w, tab, dr: float) -> np.ndarray:
        """``sum_j w_j tab(|p_i - p_j|)`` over the points within the radius of each point, at every
        point (in the points' order): :meth:`add_sum` with the points as targets, taken in cell
        order (the points a target reads are those its neighbour targets read: cache-friendly).
        Each pair is evaluated from both ends: a loop that evaluates it once and adds it both
        ways writes to memory the loop also reads and does not vectorize, and took longer.

        Parameters
        ----------
        w : (N,) array
            One weight a point.
        tab : (T,) array
        dr : float
        """
        part = np.zeros(self.n)
        self.add_sum(self.sorted, w, tab, tab, dr, part)
        out = np.empty(self.n)
        out[self.order] = part
        return out

    def add_sum(self, targets, w, tab, dtab, dr: float, out, grad=None) -> None:
        """``out += sum_j w_j tab(|t - p_j|)`` over the points within the radius of each target (and, with
        ``grad``, ``grad += sum_j w_j dtab(|t - p_j|) (t - p_j)``, ``dtab`` being tab' / r), in place.

        Parameters
        ----------
        targets : (M, 3) float array, C-contiguous
        w : (N,) array
            One weight a point, in the points' order.
        tab, dtab : (T,) arrays
        dr : float
        out : (M,) array
        grad : (M, 3) array, optional
        """
        i64, f64 = np.zeros(1, np.int64), np.zeros(1)
        mode = _SUM if grad is None else _SUM_GRAD
        self._pass(mode, targets, (tab, dtab, dr), np.ascontiguousarray(w[self.order], dtype=float), i64,
                   (i64, np.zeros(1, np.int32), f64), (out, np.zeros((1, 3)) if grad is None else grad))


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
    fit = int(0.3 * limit / (max(n, 1) * NNZ_BYTES * 1.1))
    return int(min(max(fit, default_neighbours(n)), PRODUCT_NEIGHBOURS_MAX, max(n // 16, default_neighbours(n))))


#: A fixed cap on the bytes of stored near-field matrices a fit's products (the product's and its
#: looser companions') may keep, or None: only 30 % of the memory limit (the memory available)
#: bounds them.  Beyond the bound the near fields are summed afresh by the cell list at every
#: product instead of being stored (about a third slower a product).
NEAR_STORE_BYTES = None
#: The looser companions' stored near fields, as a share of the product's own (see :func:`store_near`).
COMPANION_SHARE = 0.6


def store_near(entries: float, limit: int | None = None) -> bool:
    """Whether a product whose near field has ``entries`` stored entries keeps it as a sparse matrix.

    The product and its looser companions (about ``COMPANION_SHARE`` more) must fit in
    30 % of ``limit`` (default :func:`memory_limit_or_default`, from the memory available)
    and in ``NEAR_STORE_BYTES`` when that is set; otherwise every product sums its near
    field on the fly (no memory, more time)."""
    need = NNZ_BYTES * float(entries) * (1 + COMPANION_SHARE)
    bound = 0.3 * memory_limit_or_default(limit)
    return need <= (bound if NEAR_STORE_BYTES is None else min(NEAR_STORE_BYTES, bound))


#: Radii :func:`neighbour_radius` found, by the centres (in any order) and k: a fit asks the same ones several
#: times (its memory plan on the centres as given, its products and the evaluator on them in space order), each a
#: k-nearest query of up to 1,000 neighbours.
_RADII: dict = {}
_RADII_KEPT = 64
#: Centres sampled by :func:`neighbour_radius`, a k-nearest query of each (benchmarks/recorded/fast_solver.md,
#: session 33: what 1,000 instead of 2,000 changed).
RADIUS_SAMPLE = 1000


def radius_sample(centres, count: int = RADIUS_SAMPLE) -> np.ndarray:
    """Indices of ``count`` centres picked by a hash of their coordinates (all of them when there are fewer).

    The same centres are picked whatever their order: a permutation of
    ``centres`` gives the same points (so the same median).
    """
    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    if n <= count:
        return np.arange(n)
    return _smallest(_coordinate_hash(centres), count)


def _smallest(key: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` smallest keys, in key order."""
    pick = np.argpartition(key, count - 1)[:count]
    return pick[np.argsort(key[pick], kind="stable")]


def _coordinate_hash(centres: np.ndarray) -> np.ndarray:
    """A 64-bit mix of each row's coordinate bits (splitmix64 of their weighted sum)."""
    bits = centres.view(np.uint64)
    with np.errstate(over="ignore"):
        h = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15) + bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F) \
            + bits[:, 2] * np.uint64(0x165667B19E3779F9)
        h ^= h >> np.uint64(30)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
        h *= np.uint64(0x94D049BB133111EB)
        h ^= h >> np.uint64(31)
    return h


def neighbour_radius(centres, tree: cKDTree, k: int) -> float:
    """Median distance from :data:`RADIUS_SAMPLE` centres (:func:`radius_sample`) to their ``k``-th nearest
    centre (self included); the same for the centres in any order."""
    import hashlib

    centres = np.ascontiguousarray(centres, dtype=float)
    n = len(centres)
    k = int(min(max(k, 8), max(n // 4, 2)))
    # The sample of radius_sample (its hashes computed once here) and, for the cache key, order-free sums of
    # the hashes: a permutation hits.
    h = _coordinate_hash(centres) if n > RADIUS_SAMPLE else np.zeros(1, np.uint64)
    sample = centres[_smallest(h, RADIUS_SAMPLE)] if n > RADIUS_SAMPLE else centres
    with np.errstate(over="ignore"):
        whole = (int(h.sum(dtype=np.uint64)), int(np.bitwise_xor.reduce(h)), int((h * h).sum(dtype=np.uint64)))
    if n <= RADIUS_SAMPLE:
        sample = sample[np.lexsort(sample.T[::-1])]
    key = (centres.shape, hashlib.blake2b(np.ascontiguousarray(sample).data, digest_size=16).digest(), whole, k)
    if key in _RADII:
        return _RADII[key]
    d, _ = tree.query(sample, k=[k], workers=-1)  # the k-th only, on every core
    radius = max(float(np.median(d[:, 0])), 1e-6 * max(float(np.ptp(centres, axis=0).max()), 1e-300))
    if len(_RADII) >= _RADII_KEPT:
        _RADII.pop(next(iter(_RADII)))
    _RADII[key] = radius
    return radius


#: Nearest-centre distances :func:`nearest_distance` found, by the centres' bytes (in their order): a fit asks for
#: the same centres' several times (its memory plans, its products' grids, its evaluator's), each a query of every
#: centre.
_NEAREST: dict = {}
_NEAREST_KEPT = 4


def nearest_distance(centres, tree: cKDTree) -> np.ndarray:
    """Distance from each centre to its nearest other centre (``tree`` is of ``centres``), row by row.

    The answer for the same centres in the same order is kept (the last
    ``_NEAREST_KEPT`` arrays of centres, keyed by a digest of their bytes);
    do not modify the array returned.
    """
    import hashlib

    centres = np.ascontiguousarray(centres, dtype=float)
    key = (centres.shape, hashlib.blake2b(centres.data, digest_size=16).digest())
    d = _NEAREST.get(key)
    if d is None:
        d = tree.query(centres, k=2, workers=-1)[0][:, 1]
        d.flags.writeable = False
        if len(_NEAREST) >= _NEAREST_KEPT:
            _NEAREST.pop(next(iter(_NEAREST)))
        _NEAREST[key] = d
    return d
