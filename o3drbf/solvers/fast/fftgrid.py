"""The FFT grid of a grid sum (:class:`Mesh`): the Gaussian stencil's spreading and gathering, the grid
kernel's transform, the far-field potential, and the work arrays a solve's potentials reuse.

A potential's transforms take about six bytes a zero-padded node; fresh arrays of that size at every
product cost their pages' first touch every time (benchmarks/recorded/fast_solver.md, session 25),
so within :func:`reused_work` (a fast solve) one set per thread is kept and reused: the memory one
potential takes anyway, held from one product to the next."""

from __future__ import annotations

import math
import os
import threading
from contextlib import contextmanager

import numpy as np
import scipy.fft as _sfft

from o3drbf.solvers.fast.neighbours import LOOP_MATH, njit, prange

__all__ = ["Mesh", "PublicTransforms", "fft_workers", "reused_work", "work_arrays"]

_WORK = threading.local()


class PublicTransforms:
    """The three transforms :meth:`Mesh.potential` takes from scipy.fft's pocketfft module, by scipy.fft's
    public functions (each result copied into ``out``): the stand-in where that module is not found.
    Forward transforms unnormalized, inverse ones by 1/n, as :meth:`Mesh.potential` asks."""

    @staticmethod
    def r2c(a, axes, forward, inorm, out, nthreads):
        out[...] = _sfft.rfft(a, axis=axes[0], workers=nthreads)
        return out

    @staticmethod
    def c2c(a, axes, forward, inorm, out, nthreads):
        out[...] = (_sfft.fft if forward else _sfft.ifft)(a, axis=axes[0], workers=nthreads)
        return out

    @staticmethod
    def c2r(a, axes, lastsize, forward, inorm, out, nthreads):
        out[...] = _sfft.irfft(a, n=lastsize, axis=axes[0], workers=nthreads)
        return out


try:  # scipy.fft's own transforms, which take an output array (in place); not public API, hence the stand-in
    from scipy.fft._pocketfft import pypocketfft as _pfft
except ImportError:  # pragma: no cover (a scipy without it)
    _pfft = PublicTransforms


@contextmanager
def reused_work():
    """Within it, this thread's grid potentials share one set of work arrays (the largest asked for),
    freed when the outermost such block ends; outside, each potential takes new ones."""
    depth = getattr(_WORK, "depth", 0)
    _WORK.depth = depth + 1
    try:
        yield
    finally:
        _WORK.depth = depth
        if depth == 0:
            _WORK.buffer = None


def work_arrays(real_shape, real_dtype, complex_shape, complex_dtype):
    """A real and a complex array of these shapes (contents undefined), not overlapping: views of this
    thread's reused buffer inside :func:`reused_work`, else new."""
    real_dtype, complex_dtype = np.dtype(real_dtype), np.dtype(complex_dtype)
    nr = -(-int(np.prod(real_shape)) * real_dtype.itemsize // 64) * 64
    nc = int(np.prod(complex_shape)) * complex_dtype.itemsize
    if not getattr(_WORK, "depth", 0):
        return np.empty(real_shape, real_dtype), np.empty(complex_shape, complex_dtype)
    buf = getattr(_WORK, "buffer", None)
    if buf is None or buf.nbytes < nr + nc:
        _WORK.buffer = None  # the smaller one freed before the larger is taken
        buf = _WORK.buffer = np.empty(nr + nc, np.uint8)
    return np.ndarray(real_shape, real_dtype, buf, 0), np.ndarray(complex_shape, complex_dtype, buf, nr)


@njit(cache=True, parallel=True, fastmath=LOOP_MATH)
def _spread(pts, w, origin, h, s, half, grid):
    """Spread ``w`` onto ``grid`` with the Gaussian stencil, in parallel over slabs along x.

    Slabs of ``W = 2 half + 1`` nodes: a point's stencil starts in its slab and reaches at most into
    the next one, so the even slabs are spread at the same time, then the odd ones (no two threads
    add to one node).  Each node gets its sums in the same order whatever the thread count (LOOP_MATH
    reorders only within a point's stencil).  The grid
    is addressed flat with unsigned offsets (no negative-index wrap to test), so that a stencil row
    is one vector operation."""
    W = 2 * half + 1
    c = 1.0 / ((2 * math.pi) ** 1.5 * s ** 3)
    inv = 1.0 / (2 * s * s)
    n = pts.shape[0]
    ny, nz = grid.shape[1], grid.shape[2]
    flat = grid.reshape(-1)
    nslab = grid.shape[0] // W + 1
    slab = np.empty(n, np.int64)
    count = np.zeros(nslab + 1, np.int64)
    for p in range(n):
        ix = int(math.floor((pts[p, 0] - origin[0]) / h + 0.5)) - half
        slab[p] = min(max(ix // W, 0), nslab - 1)
        count[slab[p] + 1] += 1
    start = np.cumsum(count)
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for p in range(n):
        order[fill[slab[p]]] = p
        fill[slab[p]] += 1
    for phase in range(2):
        for t in prange((nslab - phase + 1) // 2):
            sl = 2 * t + phase
            wx = np.empty(W); wy = np.empty(W); wz = np.empty(W)
            for idx in range(start[sl], start[sl + 1]):
                p = order[idx]
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
                        base = np.uint64(((ix + a) * ny + iy + b) * nz + iz)
                        for q in range(W):
                            flat[base + np.uint64(q)] += vb * wz[q]


@njit(cache=True, parallel=True, fastmath=LOOP_MATH)
def _gather(pts, origin, h, s, half, u, out, grad, want):
    """The Gaussian stencil's weighted sum of ``u`` at each point into ``out`` (and, with ``want``, its
    gradient into ``grad``); ``u`` addressed flat with unsigned offsets, as in :func:`_spread`."""
    W = 2 * half + 1
    c = 1.0 / ((2 * math.pi) ** 1.5 * s ** 3)
    inv = 1.0 / (2 * s * s)
    ny, nz = u.shape[1], u.shape[2]
    flat = u.reshape(-1)
    for p in prange(pts.shape[0]):
        wx = np.empty(W); wy = np.empty(W); wz = np.empty(W)
        dx = np.empty(W); dy = np.empty(W); dz = np.empty(W)
        fx = (pts[p, 0] - origin[0]) / h; fy = (pts[p, 1] - origin[1]) / h; fz = (pts[p, 2] - origin[2]) / h
        ix = int(math.floor(fx + 0.5)) - half; iy = int(math.floor(fy + 0.5)) - half; iz = int(math.floor(fz + 0.5)) - half
        for a in range(W):
            d = (fx - ix - a) * h; wx[a] = math.exp(-d * d * inv); dx[a] = -d / (s * s) * wx[a]
            d = (fy - iy - a) * h; wy[a] = math.exp(-d * d * inv); dy[a] = -d / (s * s) * wy[a]
            d = (fz - iz - a) * h; wz[a] = math.exp(-d * d * inv); dz[a] = -d / (s * s) * wz[a]
        acc = 0.0; g0 = 0.0; g1 = 0.0; g2 = 0.0
        if want:
            for a in range(W):
                for b in range(W):
                    base = np.uint64(((ix + a) * ny + iy + b) * nz + iz)
                    row = 0.0; rowd = 0.0
                    for q in range(W):
                        v = flat[base + np.uint64(q)]
                        row += v * wz[q]
                        rowd += v * dz[q]
                    acc += wx[a] * wy[b] * row
                    g0 += dx[a] * wy[b] * row
                    g1 += wx[a] * dy[b] * row
                    g2 += wx[a] * wy[b] * rowd
            grad[p, 0] = c * g0; grad[p, 1] = c * g1; grad[p, 2] = c * g2
        else:
            for a in range(W):
                for b in range(W):
                    base = np.uint64(((ix + a) * ny + iy + b) * nz + iz)
                    row = 0.0
                    for q in range(W):
                        row += flat[base + np.uint64(q)] * wz[q]
                    acc += wx[a] * wy[b] * row
        out[p] = c * acc


def fft_workers() -> int:
    """Threads of the grid's FFTs: ``OMP_NUM_THREADS`` (default: every core), at most the cores."""
    try:
        return max(1, min(int(os.environ.get("OMP_NUM_THREADS") or os.cpu_count() or 1), os.cpu_count() or 1))
    except ValueError:
        return 1


class Mesh:
    """A grid of spacing h over a box, with the FFT of the grid kernel K (zero-padded: aperiodic).

    The convolution is done axis by axis (z, y, x) so that the zero-padded
    array of the aperiodic convolution never exists whole: the grid is
    padded along one axis at a time, the last axis in slabs, and the
    output cropped back axis by axis; K is even along every axis, so its
    transform is real and even and one octant of it is kept."""

    #: Bytes of work arrays a slab of the last transform may take (small, so that a slab's padding,
    #: transforms and product stay in the cores' caches).
    SLAB_BYTES = 4 * 2**20

    def __init__(self, lo, hi, h, s, half, ktable, dtype=np.float64):
        self.h, self.s, self.half, self.dtype = h, s, half, dtype
        pad = (half + 2) * h
        self.origin = np.asarray(lo, float) - pad
        self.shape = tuple(int(math.ceil((hi[i] - lo[i] + 2 * pad) / h)) + 1 for i in range(3))
        self.fshape = tuple(_sfft.next_fast_len(2 * m - 1, real=True) for m in self.shape)
        fx, fy, fz = self.fshape
        half_len = [p // 2 + 1 for p in self.fshape]
        workers = fft_workers()
        # Each index's distance to the nearest end along x and y (K is even: K[i] = K[f - i]).
        self._mx = np.minimum(np.arange(fx), fx - np.arange(fx))
        self._my = np.minimum(np.arange(fy), fy - np.arange(fy))
        iz = np.minimum(np.arange(fz), fz - np.arange(fz)).astype(np.int64)
        n2yz = np.arange(half_len[1], dtype=np.int64)[:, None] ** 2 + iz[None, :] ** 2  # y >= 0 only: K[y] = K[fy - y]
        # K at h * sqrt(n2), times the node volume h^3 twice: the convolution's quadrature over the spread
        # weights and the gather's over the potential (so a potential needs no scaling of its own)
        vals = ktable(np.arange((fx // 2) ** 2 + int(n2yz.max()) + 1)) * h**6
        # A batch of x-slabs of K at a time: its (real, even) transform along z (each distinct row once), then
        # along y (the rows mirrored), first octant kept.
        part = np.empty(half_len, dtype=np.float64)
        sq = np.arange(half_len[0], dtype=np.int64) ** 2
        batch = max(1, int(4 * self.SLAB_BYTES // (16 * fy * half_len[2])))
        for i in range(0, half_len[0], batch):
            zt = _sfft.rfft(vals[n2yz[None] + sq[i : i + batch, None, None]], axis=2, workers=workers).real
            part[i : i + batch] = _sfft.rfft(zt[:, self._my], axis=1, workers=workers).real
        del n2yz, vals, zt
        # Along x: the even sequence of the slabs, in column blocks.
        khat = np.empty(half_len, dtype=dtype)
        step = max(1, int(self.SLAB_BYTES // (16 * fx * half_len[2])))
        for j in range(0, half_len[1], step):
            col = part[self._mx, j : j + step]
            khat[:, j : j + step] = _sfft.rfft(col, axis=0, workers=workers).real
        del part
        self.khat = khat

    @staticmethod
    def nbytes(lo, hi, h, half, single: bool = False, part: str = "all") -> int:
        """Bytes of a grid's kernel transform plus the work arrays of one potential (``single``: float32 FFTs).

        ``part``: "all", "kept" (one octant of the real kernel transform, kept while the grid lives:
        1 byte a zero-padded node, 0.5 in single precision) or "work" (the grid padded along z
        and y and its transform, freed after one potential or, inside :func:`reused_work`, reused by
        the next: 7 bytes a zero-padded node, 3.5 in single precision)."""
        pad = (half + 2) * h
        shape = [math.ceil((hi[i] - lo[i] + 2 * pad) / h) + 1 for i in range(3)]
        kept, work = (0.5, 3.5) if single else (1.0, 7.0)
        per = {"all": kept + work, "kept": kept, "work": work}[part]
        return int(per * np.prod([2.0 * m for m in shape]))

    def potential(self, pts, w, scratch: bool = False):
        """The far-field potential on the (unpadded) grid of the weights ``w`` at ``pts``.

        The grid and its transform live in the work arrays of :func:`work_arrays` (this thread's
        reused ones inside :func:`reused_work`), transformed in place axis by axis.  The result is
        a new float64 array of the grid's shape, or with ``scratch`` the real work array itself, valid
        until this thread's next potential (for a caller that gathers from it at once): in the grid's
        precision and padded along z (its first ``shape[2]`` planes are the grid)."""
        mx, my, mz = self.shape
        fx, fy, fz = self.fshape
        workers = fft_workers()
        real = np.dtype(self.dtype)
        grid, b = work_arrays((mx, my, fz), real, (mx, fy, fz // 2 + 1), np.result_type(real, np.complex64))
        grid[...] = 0  # zero-padded along z from the start (no padded copy)
        _spread(pts, w, self.origin, self.h, self.s, self.half, grid)
        _pfft.r2c(grid, (2,), True, 0, b[:, :my], workers)
        b[:, my:] = 0
        _pfft.c2c(b, (1,), True, 0, b, workers)
        # Along x, slab by slab of y: pad, transform, multiply by K's transform, back, crop; in one padded buffer.
        step = max(1, int(self.SLAB_BYTES // (b.itemsize * fx * b.shape[2])))
        buf = np.empty((fx, step, b.shape[2]), dtype=b.dtype)
        for j in range(0, fy, step):
            blk = buf[:, : min(step, fy - j)]
            blk[:mx], blk[mx:] = b[:, j : j + step], 0
            _pfft.c2c(blk, (0,), True, 0, blk, workers)
            self._times_khat(blk, j, j + blk.shape[1])
            _pfft.c2c(blk, (0,), False, 2, blk, workers)
            b[:, j : j + step] = blk[:mx]
        _pfft.c2c(b, (1,), False, 2, b, workers)
        _pfft.c2r(b[:, :my], (2,), fz, False, 2, grid, workers)
        if scratch:  # the transform's own output, padded along z (gathers read it in place, in its precision)
            return grid
        del b, buf, blk  # a new result, the complex array given up first (freed unless it is the reused buffer)
        out = np.empty((mx, my, mz))
        out[...] = grid[:, :, :mz]
        return out

    def _times_khat(self, blk, j0, j1):
        """``blk *= K's transform`` over columns ``j0 <= y < j1`` of the whole x range, from the kept octant
        (K[x] = K[fx - x], K[y] = K[fy - y]): by views, the mirrored halves read backwards."""
        fx, fy = self.fshape[0], self.fshape[1]
        hx = self.khat.shape[0]
        if j1 - 1 <= fy - (j1 - 1):  # every column in the first half
            ky = slice(j0, j1)
        elif j0 >= fy - j0:  # every column mirrored: y -> fy - y
            ky = slice(fy - j0, fy - j1, -1)
        else:  # (the one block across the middle)
            blk *= self.khat[np.ix_(self._mx, self._my[j0:j1])]
            return
        blk[:hx] *= self.khat[:, ky]
        blk[hx:] *= self.khat[fx - hx : 0 : -1, ky]

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
