"""Compiled direct sums (Numba): sum_i w_i phi(|x - c_i|) and its gradient
without forming the matrix, parallel over targets.

Private: :func:`o3drbf.rbf.sums.kernel_sum` calls :func:`direct_sum` when the
kernel has a compiled form here, and the NumPy path in ``sums``/``kernels``
is the reference it is tested against.
"""

from __future__ import annotations

import functools
import math

import numpy as np

try:  # numba is a dependency, but the library still works (slower) without it
    import numba  # its threading layer is chosen by o3drbf.startup.prefer_numba_workqueue

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

__all__ = ["HAVE_NUMBA", "direct_sum", "direct_sum_at_centres", "direct_matrix", "lower_single", "lower_pair", "lower_matrix_single", "supports", "check_sum_arrays", "table_sum", "table_matrix", "supports_table", "kernel_table", "KernelTable"]

# kernel codes
_MULTIORDER, _GAUSSIAN, _THINPLATE = 0, 1, 2


def _params(kernel):
    """(code, parameter vector) for kernels with a compiled form, else None."""
    name = kernel.name
    if name == "multiorder":
        if kernel.coefficients is None or kernel.regime != "real":
            return None
        (A, B), a, b = kernel.coefficients, kernel.decay_rates[0].real, kernel.decay_rates[1].real
        if abs(a - b) < 1e-2 * (a + b):
            return None  # near-confluent: A, B large; the NumPy divided difference handles it
        d1, d3, d4, d5 = kernel.series_coefficients()
        return _MULTIORDER, np.array([A.real, B.real, a, b, kernel.scale, d1, d3, d4, d5], dtype=float)
    if name == "gaussian":
        return _GAUSSIAN, np.array([kernel.sigma], dtype=float)
    if name == "thinplate":
        return _THINPLATE, np.zeros(1)
    return None


def supports(kernel) -> bool:
    return HAVE_NUMBA and _params(kernel) is not None


if HAVE_NUMBA:

    @numba.njit(cache=True, fastmath=False, inline="always")
    def _q(y):
        # q(y) = 1 - e^{-y} (1 + y), by its series where the formula cancels.
        if y < 1e-2:
            y2 = y * y
            return y2 * (0.5 + y * (-1.0 / 3.0 + y * (1.0 / 8.0 + y * (-1.0 / 30.0 + y * (1.0 / 144.0)))))
        return -math.expm1(-y) - y * math.exp(-y)

    @numba.njit(cache=True, inline="always")
    def _phi(code, p, r):
        if code == 0:
            A, B, a, b, c = p[0], p[1], p[2], p[3], p[4]
            ar = a * r
            if ar < 1e-3:
                return (-p[5] - p[6] * r * r / 6.0 + p[7] * r**3 / 24.0 - p[8] * r**4 / 120.0) / c
            if b * r > 1e-3:
                # e^{-ar} < 4e-18 beyond ar = 40: skip the exp
                ea = math.exp(-ar) if ar < 40.0 else 0.0
                return (1.0 + A * ea + B * math.exp(-b * r)) / (c * r)
            return (A * math.expm1(-ar) + B * math.expm1(-b * r)) / (c * r)
        if code == 1:
            s = r / p[0]
            return math.exp(-s * s)
        return r * r * r

    @numba.njit(cache=True, inline="always")
    def _dphi_over_r(code, p, r):
        if code == 0:
            A, B, a, b, c = p[0], p[1], p[2], p[3], p[4]
            ar = a * r
            if ar < 1e-3:
                return (-p[6] / 3.0 + p[7] * r / 8.0 - p[8] * r * r / 30.0) / c
            if b * r > 1e-2:
                br = b * r
                ea = math.exp(-ar) if ar < 40.0 else 0.0
                return -(1.0 + A * ea * (1.0 + ar) + B * math.exp(-br) * (1.0 + br)) / (c * r * r * r)
            return (A * _q(ar) + B * _q(b * r)) / (c * r * r * r)
        if code == 1:
            s = r / p[0]
            return -2.0 / (p[0] * p[0]) * math.exp(-s * s)
        return 3.0 * r

    @numba.njit(cache=True, inline="always")
    def _phi_and_dphi_over_r(code, p, r):
        if code == 0 and p[2] * r >= 1e-3 and p[3] * r > 1e-2:
            A, B, a, b, c = p[0], p[1], p[2], p[3], p[4]
            ar = a * r
            br = b * r
            ea = math.exp(-ar) if ar < 40.0 else 0.0
            eb = math.exp(-br)
            cr = c * r
            return (1.0 + A * ea + B * eb) / cr, -(1.0 + A * ea * (1.0 + ar) + B * eb * (1.0 + br)) / (cr * r * r)
        return _phi(code, p, r), _dphi_over_r(code, p, r)

    @numba.njit(cache=True, parallel=True)
    def _sum(code, p, centres, weights, targets, out):
        m, n = targets.shape[0], centres.shape[0]
        for j in numba.prange(m):
            x, y, z = targets[j, 0], targets[j, 1], targets[j, 2]
            acc = 0.0
            for i in range(n):
                dx, dy, dz = x - centres[i, 0], y - centres[i, 1], z - centres[i, 2]
                acc += weights[i] * _phi(code, p, math.sqrt(dx * dx + dy * dy + dz * dz))
            out[j] = acc

    @numba.njit(cache=True, parallel=True)
    def _sum_grad(code, p, centres, weights, targets, out, grad):
        m, n = targets.shape[0], centres.shape[0]
        for j in numba.prange(m):
            x, y, z = targets[j, 0], targets[j, 1], targets[j, 2]
            acc = 0.0
            gx = 0.0
            gy = 0.0
            gz = 0.0
            for i in range(n):
                dx, dy, dz = x - centres[i, 0], y - centres[i, 1], z - centres[i, 2]
                r = math.sqrt(dx * dx + dy * dy + dz * dz)
                w = weights[i]
                v, d = _phi_and_dphi_over_r(code, p, r)
                acc += w * v
                g = w * d
                gx += g * dx
                gy += g * dy
                gz += g * dz
            out[j] = acc
            grad[j, 0] = gx
            grad[j, 1] = gy
            grad[j, 2] = gz

    @numba.njit(cache=True, parallel=True)
    def _matrix(code, p, x, y, out):
        for j in numba.prange(y.shape[0]):
            for i in range(x.shape[0]):
                dx, dy, dz = x[i, 0] - y[j, 0], x[i, 1] - y[j, 1], x[i, 2] - y[j, 2]
                out[i, j] = _phi(code, p, math.sqrt(dx * dx + dy * dy + dz * dz))

    @numba.njit(cache=True, inline="always")
    def _lower_column(code, p, x, out, j):
        for i in range(j, x.shape[0]):
            dx, dy, dz = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
            out[i, j] = _phi(code, p, math.sqrt(dx * dx + dy * dy + dz * dz))

    @numba.njit(cache=True, parallel=True)
    def _matrix_lower(code, p, x, out):
        n = x.shape[0]
        half = (n + 1) // 2
        # Columns t and n - 1 - t in one task: every task fills about n + 1 entries.
        for t in numba.prange(half):
            _lower_column(code, p, x, out, t)
            if n - 1 - t != t:
                _lower_column(code, p, x, out, n - 1 - t)


if HAVE_NUMBA:

    @numba.njit(cache=True, inline="always")
    def _single_column(a, out, j):
        d = a[j, j]
        out[j, j] = np.float32(d)
        acc = 0.0
        for i in range(j + 1, a.shape[0]):
            v = a[i, j]
            out[i, j] = np.float32(v)
            acc += v * v
        return d * d + 2.0 * acc

    @numba.njit(cache=True, parallel=True)
    def _lower_single(a, out, squares):
        n = a.shape[0]
        half = (n + 1) // 2
        for t in numba.prange(half):  # columns t and n - 1 - t in one task, as in _matrix_lower
            squares[t] = _single_column(a, out, t)
            u = n - 1 - t
            if u != t:
                squares[u] = _single_column(a, out, u)


if HAVE_NUMBA:

    @numba.njit(cache=True, inline="always")
    def _pair_column(code, p, x, diagonal, out, single, j):
        d = _phi(code, p, 0.0) + diagonal[j]
        out[j, j] = d
        single[j, j] = np.float32(d)
        acc = 0.0
        for i in range(j + 1, x.shape[0]):
            dx, dy, dz = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
            v = _phi(code, p, math.sqrt(dx * dx + dy * dy + dz * dz))
            out[i, j] = v
            single[i, j] = np.float32(v)
            acc += v * v
        return d * d + 2.0 * acc

    @numba.njit(cache=True, parallel=True)
    def _matrix_lower_pair(code, p, x, diagonal, out, single, squares):
        n = x.shape[0]
        half = (n + 1) // 2
        for t in numba.prange(half):  # columns t and n - 1 - t in one task, as in _matrix_lower
            squares[t] = _pair_column(code, p, x, diagonal, out, single, t)
            u = n - 1 - t
            if u != t:
                squares[u] = _pair_column(code, p, x, diagonal, out, single, u)


if HAVE_NUMBA:

    @numba.njit(cache=True, inline="always")
    def _single_kernel_column(code, p, x, diagonal, out, j):
        out[j, j] = np.float32(_phi(code, p, 0.0) + diagonal[j])
        for i in range(j + 1, x.shape[0]):
            dx, dy, dz = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
            out[i, j] = np.float32(_phi(code, p, math.sqrt(dx * dx + dy * dy + dz * dz)))

    @numba.njit(cache=True, parallel=True)
    def _matrix_lower_single(code, p, x, diagonal, out):
        n = x.shape[0]
        half = (n + 1) // 2
        for t in numba.prange(half):  # columns t and n - 1 - t in one task, as in _matrix_lower
            _single_kernel_column(code, p, x, diagonal, out, t)
            u = n - 1 - t
            if u != t:
                _single_kernel_column(code, p, x, diagonal, out, u)


def _lower_inputs(kernel, x, diagonal):
    """``(code, parameters, x, diagonal)`` for the compiled lower-triangle builders, checked: a kernel with a
    compiled form, (N, 3) finite points, N finite diagonal values."""
    if not supports(kernel):
        raise ValueError(f"kernel {kernel.name!r} has no compiled form here; use direct_matrix's NumPy fallback and lower_single")
    code, p = _params(kernel)
    x = np.ascontiguousarray(x, float)
    diagonal = np.array(diagonal, dtype=float)  # a writable copy: one compiled signature (a read-only view would be another)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x must have shape (N, 3), got {x.shape}")
    if diagonal.shape != (len(x),):
        raise ValueError(f"diagonal must have shape ({len(x)},), one per point, got {diagonal.shape}")
    if not (np.isfinite(x).all() and np.isfinite(diagonal).all()):
        raise ValueError("x or diagonal has NaN or infinite entries; compiled kernels need finite input")
    return code, p, x, diagonal


def lower_matrix_single(kernel, x: np.ndarray, diagonal: np.ndarray) -> np.ndarray:
    """The lower triangle of ``A = Phi(x, x) + diag(diagonal)`` in float32, Fortran order, upper triangle
    uninitialised: each entry evaluated in double and rounded once, the same numbers as
    :func:`lower_single` of :func:`lower_pair`'s double matrix, without that matrix (a quarter of the bytes
    touched).  For a factorization that single precision serves (a preconditioner's coarse level).

    Parameters
    ----------
    kernel, x, diagonal
        As for :func:`lower_pair`.

    Returns
    -------
    (N, N) float32 ndarray
    """
    code, p, x, diagonal = _lower_inputs(kernel, x, diagonal)
    out = np.empty((len(x), len(x)), dtype=np.float32, order="F")
    _matrix_lower_single(code, p, x, diagonal, out)
    return out


def lower_pair(kernel, x: np.ndarray, diagonal: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``A = Phi(x, x) + diag(diagonal)``: its lower triangle in float64 and float32, and ``||A||_F``, in one pass.

    The same numbers as ``direct_matrix(kernel, x, x, lower=True)`` with
    ``diagonal`` added to its diagonal, then :func:`lower_single` of that:
    each entry is evaluated once and stored twice, so the float32 copy costs
    no second pass over the matrix.  The upper triangles are left
    uninitialised.

    Parameters
    ----------
    kernel : Kernel
        One with a compiled form (:func:`supports`).
    x : (N, 3) array_like
        Finite points.
    diagonal : (N,) array_like
        Added to the diagonal (the smoothing).

    Returns
    -------
    matrix : (N, N) float64 ndarray, Fortran order
    single : (N, N) float32 ndarray, Fortran order
    frobenius : float
        ``||A||_F`` of the symmetric matrix (off-diagonal entries counted twice).
    """
    code, p, x, diagonal = _lower_inputs(kernel, x, diagonal)
    out = np.empty((len(x), len(x)), order="F")
    single = np.empty((len(x), len(x)), dtype=np.float32, order="F")
    squares = np.zeros(len(x))
    _matrix_lower_pair(code, p, x, diagonal, out, single, squares)
    return out, single, float(np.sqrt(squares.sum()))


def lower_single(a: np.ndarray) -> tuple[np.ndarray, float]:
    """The lower triangle of the symmetric ``a`` (square, Fortran order, float64) as float32, and ``a``'s Frobenius norm.

    Only the lower triangle (diagonal included) of ``a`` is read, and only
    that of the result written (either upper triangle may be uninitialised,
    as :func:`direct_matrix` leaves it with ``lower=True``).

    Returns
    -------
    single : (N, N) float32 ndarray, Fortran order
    frobenius : float
        ``||a||_F`` of the symmetric matrix (off-diagonal entries counted twice).
    """
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.dtype != np.float64 or not a.flags.f_contiguous:
        raise ValueError(f"a must be a square Fortran-order float64 array, got {a.dtype} {a.shape}")
    out = np.empty(a.shape, dtype=np.float32, order="F")
    squares = np.zeros(a.shape[0])
    if HAVE_NUMBA:
        _lower_single(a, out, squares)
    else:  # pragma: no cover
        for j in range(a.shape[0]):
            out[j:, j] = a[j:, j]
            squares[j] = a[j, j] ** 2 + 2.0 * float(a[j + 1:, j] @ a[j + 1:, j])
    return out, float(np.sqrt(squares.sum()))


def check_sum_arrays(centres, weights, targets) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arrays handed to compiled code: ``(N, 3)``, ``(N,)``, ``(M, 3)`` float64, finite, contiguous.

    Numba does not bounds-check: a shape mismatch would read past an array,
    and a NaN distance would turn into a wild table index.  So every entry
    point checks here and raises ``ValueError`` instead.
    """
    c = np.ascontiguousarray(centres, dtype=float)
    w = np.ascontiguousarray(weights, dtype=float)
    t = np.ascontiguousarray(targets, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centres must have shape (N, 3), got {c.shape}")
    if w.shape != (c.shape[0],):
        raise ValueError(f"weights must have shape ({c.shape[0]},), one per centre, got {w.shape}")
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"targets must have shape (M, 3), got {t.shape}")
    for name, a in (("centres", c), ("weights", w), ("targets", t)):
        if not np.isfinite(a).all():
            raise ValueError(f"{name} have NaN or infinite entries; compiled sums need finite input")
    return c, w, t


def direct_sum(kernel, centres, weights, targets, gradient: bool = False):
    """Compiled kernel sum; same contract as :func:`o3drbf.rbf.sums.kernel_sum`."""
    code, p = _params(kernel)
    c, w, t = check_sum_arrays(centres, weights, targets)
    out = np.empty(len(t))
    if gradient:
        grad = np.empty((len(t), 3))
        _sum_grad(code, p, c, w, t, out, grad)
        return out, grad
    _sum(code, p, c, w, t, out)
    return out


if HAVE_NUMBA:

    @numba.njit(cache=True, inline="always")
    def _pair_into(code, p, centres, weights, target, acc, i, j):
        # the pair (i, j), i != j, evaluated once: into i's sums if i is a target, into j's if j is one
        dx, dy, dz = centres[i, 0] - centres[j, 0], centres[i, 1] - centres[j, 1], centres[i, 2] - centres[j, 2]
        v, d = _phi_and_dphi_over_r(code, p, math.sqrt(dx * dx + dy * dy + dz * dz))
        if target[i]:
            w = weights[j]
            g = w * d
            acc[i, 0] += w * v
            acc[i, 1] += g * dx
            acc[i, 2] += g * dy
            acc[i, 3] += g * dz
        if target[j]:
            w = weights[i]
            g = w * d
            acc[j, 0] += w * v
            acc[j, 1] -= g * dx
            acc[j, 2] -= g * dy
            acc[j, 3] -= g * dz

    @numba.njit(cache=True, inline="always")
    def _column_into(code, p, centres, weights, target, acc, j):
        if target[j]:
            acc[j, 0] += weights[j] * _phi(code, p, 0.0)  # the centre's own term (its gradient term is zero)
        for i in range(j + 1, centres.shape[0]):
            if target[i] or target[j]:
                _pair_into(code, p, centres, weights, target, acc, i, j)

    @numba.njit(cache=True, parallel=True)
    def _sum_grad_at_centres(code, p, centres, weights, target, acc):
        # acc: (threads, N, 4) sums per thread (value, gradient); each pair i > j is evaluated once
        n = centres.shape[0]
        half = (n + 1) // 2
        for t in numba.prange(half):  # columns t and n - 1 - t in one task, as in _matrix_lower
            own = acc[numba.get_thread_id()]
            _column_into(code, p, centres, weights, target, own, t)
            if n - 1 - t != t:
                _column_into(code, p, centres, weights, target, own, n - 1 - t)


def direct_sum_at_centres(kernel, centres, weights, index) -> tuple[np.ndarray, np.ndarray]:
    """``sum_i w_i phi(|c_k - c_i|)`` and its gradient at the centres ``c_k``, ``k`` in ``index``.

    What ``direct_sum(kernel, centres, weights, centres[index], gradient=True)`` computes, with
    each pair of centres evaluated once for both of its ends (``phi`` is symmetric and its gradient
    antisymmetric): about half the kernel evaluations when most centres are wanted.  The sums are
    added in another order, so they agree with ``direct_sum``'s to rounding.

    Parameters
    ----------
    kernel : Kernel
        One with a compiled form (:func:`supports`).
    centres : (N, 3) array_like
    weights : (N,) array_like
    index : (K,) int array_like
        Distinct indices into ``centres``.

    Returns
    -------
    values : (K,) ndarray
    gradients : (K, 3) ndarray
    """
    if not supports(kernel):
        raise ValueError(f"kernel {kernel.name!r} has no compiled form here; use kernel_sum")
    code, p = _params(kernel)
    c, w, _ = check_sum_arrays(centres, weights, np.zeros((0, 3)))
    index = np.asarray(index)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer) or (len(index) and (index.min() < 0 or index.max() >= len(c))):
        raise ValueError(f"index must be a 1-D array of integers in [0, {len(c)}), got {index.dtype} {index.shape}")
    target = np.zeros(len(c), dtype=np.bool_)
    target[index] = True
    if int(target.sum()) != len(index):
        raise ValueError("index has repeated entries; pass each centre once")
    acc = np.zeros((numba.get_num_threads(), len(c), 4))
    _sum_grad_at_centres(code, p, c, w, target, acc)
    total = acc.sum(axis=0)[index]
    return np.ascontiguousarray(total[:, 0]), np.ascontiguousarray(total[:, 1:])


def _matrix_points(x, y):
    """``x`` and ``y`` as contiguous (N, 3) float arrays of finite points, or ValueError naming the bad one."""
    x = np.ascontiguousarray(x, float)
    y = np.ascontiguousarray(y, float)
    for name, a in (("x", x), ("y", y)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"{name} must have shape (N, 3), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} has NaN or infinite entries; compiled kernels need finite input")
    return x, y


def direct_matrix(kernel, x, y, lower: bool = False, dtype=np.float64):
    """Compiled dense kernel matrix, Fortran order.

    ``lower=True`` (``y`` must be ``x``) fills only the lower triangle, the
    diagonal included, and leaves the rest uninitialised: half the kernel
    evaluations, and all a lower Cholesky factorization reads.  ``dtype``
    float32 stores each entry, evaluated in double, rounded once (not with
    ``lower``).
    """
    code, p = _params(kernel)
    x, y = _matrix_points(x, y)
    dtype = np.dtype(dtype)
    if dtype not in (np.float64, np.float32) or (lower and dtype != np.float64):
        raise ValueError(f"dtype must be float64, or float32 without lower=True; got {dtype} (lower={lower})")
    out = np.empty((len(x), len(y)), dtype=dtype, order="F")
    if lower:
        if x.shape != y.shape or not np.array_equal(x, y):
            raise ValueError("lower=True needs y = x (a symmetric matrix)")
        _matrix_lower(code, p, x, out)
    else:
        _matrix(code, p, x, y, out)
    return out


# ---------------------------------------------------------------------------
# Tabulated multi-order kernel (approximate, ~1e-9 relative): for evaluating
# a fitted surface on grids and at mesh vertices, where it replaces two
# exponentials per pair by a table lookup and a cubic.  Never used to solve.

_TAYLOR_TERMS = 12
_TABLE_STEP = 0.02  # nodes per decay length: spacing 0.02 / |rate|
_TAYLOR_AR = 0.3  # a r below which the Taylor series is used


class KernelTable:
    """Cubic Hermite tables of g(r) = 4 pi delta^2 r phi(r) for a MultiOrder kernel.

    Two uniform segments: [0, r1) with spacing 0.02/|a| (where the short
    range term lives) and [r1, r2) with spacing 0.02/|b|; beyond r2 both
    exponentials are below e^-40 and phi = 1 / (4 pi delta^2 r).  Below
    a r = 0.3 a 12-term Taylor series is used.  Built from the exact
    (NumPy) kernel, so every regime is covered.
    """

    def __init__(self, kernel):
        a, b = kernel.decay_rates
        abs_a, abs_b = abs(a), abs(b)
        re_a, re_b = a.real, b.real
        self.c = float(kernel.scale)
        self.r_taylor = _TAYLOR_AR / abs_a
        r2 = max(8.0, 40.0 / re_b)
        r1 = min(40.0 / re_a, r2)
        h1 = _TABLE_STEP / abs_a
        h2 = _TABLE_STEP / abs_b
        n1 = max(1, int(np.ceil(r1 / h1)))
        r1 = n1 * h1
        n2 = max(0, int(np.ceil((r2 - r1) / h2)))
        r2 = r1 + n2 * h2
        self.r1, self.r2, self.h1, self.h2 = r1, r2, h1, h2
        self.coef1 = self._segment(kernel, 0.0, h1, n1)
        self.coef2 = self._segment(kernel, r1, h2, n2) if n2 else np.zeros((1, 4))
        # Taylor: phi C = sum_n (-1)^n D_n r^{n-1} / n!, D_n = (ab)^2 (a^{n-2} - b^{n-2}) / (a^2 - b^2)
        n = np.arange(1, _TAYLOR_TERMS + 1)
        d = np.array([self._dn(a, b, k) for k in n])
        fact = np.array([math.factorial(int(k)) for k in n], dtype=float)
        self.taylor_value = ((-1.0) ** n * d / fact) / self.c  # coefficient of r^{n-1}
        # phi'/r C = sum_{n>=3} (-1)^n (n-1) D_n r^{n-3} / n!
        self.taylor_grad = np.array([(-1.0) ** k * (k - 1) * d[k - 1] / fact[k - 1] for k in n[2:]]) / self.c

    @staticmethod
    def _dn(a, b, n):
        if abs(a - b) < 1e-9 * abs(a + b):  # confluent: limit of the divided difference
            return float(((a * b) ** 2 * (n - 2) * a ** (n - 3) / (2 * a)).real) if n != 2 else 0.0
        return float(((a * b) ** 2 * (a ** (n - 2) - b ** (n - 2)) / (a * a - b * b)).real)

    def _segment(self, kernel, start, h, n):
        r = start + h * np.arange(n + 1)
        phi = kernel(r)
        dphi = kernel.derivative(r)
        g = self.c * r * phi
        dg = self.c * (phi + r * dphi)
        g0, g1, d0, d1 = g[:-1], g[1:], h * dg[:-1], h * dg[1:]
        return np.ascontiguousarray(np.column_stack([g0, d0, 3 * (g1 - g0) - 2 * d0 - d1, 2 * (g0 - g1) + d0 + d1]))

    def args(self):
        return (self.coef1, self.coef2, self.r1, self.r2, self.h1, self.h2, self.r_taylor, self.c, self.taylor_value, self.taylor_grad)


if HAVE_NUMBA:

    @numba.njit(cache=True, inline="always")
    def _table_eval(r, coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg, want_grad):
        """(phi(r), phi'(r)/r) from the tables."""
        if r < rt:
            v = 0.0
            for k in range(tv.shape[0] - 1, -1, -1):
                v = v * r + tv[k]
            gr = 0.0
            if want_grad:
                for k in range(tg.shape[0] - 1, -1, -1):
                    gr = gr * r + tg[k]
            return v, gr
        if r >= r2:
            return 1.0 / (c * r), -1.0 / (c * r * r * r)
        if r < r1:
            x = r / h1
            i = min(int(x), coef1.shape[0] - 1)
            t = x - i
            k0, k1, k2, k3 = coef1[i, 0], coef1[i, 1], coef1[i, 2], coef1[i, 3]
            h = h1
        else:
            x = (r - r1) / h2
            i = min(int(x), coef2.shape[0] - 1)
            t = x - i
            k0, k1, k2, k3 = coef2[i, 0], coef2[i, 1], coef2[i, 2], coef2[i, 3]
            h = h2
        g = k0 + t * (k1 + t * (k2 + t * k3))
        cr = c * r
        if not want_grad:
            return g / cr, 0.0
        dg = (k1 + t * (2.0 * k2 + 3.0 * t * k3)) / h
        return g / cr, (dg * r - g) / (cr * r * r)

    @numba.njit(cache=True, parallel=True)
    def _table_sum(centres, weights, targets, out, coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg):
        for j in numba.prange(targets.shape[0]):
            x, y, z = targets[j, 0], targets[j, 1], targets[j, 2]
            acc = 0.0
            for i in range(centres.shape[0]):
                dx, dy, dz = x - centres[i, 0], y - centres[i, 1], z - centres[i, 2]
                v, _ = _table_eval(math.sqrt(dx * dx + dy * dy + dz * dz), coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg, False)
                acc += weights[i] * v
            out[j] = acc

    @numba.njit(cache=True, parallel=True)
    def _table_sum_grad(centres, weights, targets, out, grad, coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg):
        for j in numba.prange(targets.shape[0]):
            x, y, z = targets[j, 0], targets[j, 1], targets[j, 2]
            acc = 0.0
            gx = 0.0
            gy = 0.0
            gz = 0.0
            for i in range(centres.shape[0]):
                dx, dy, dz = x - centres[i, 0], y - centres[i, 1], z - centres[i, 2]
                v, d = _table_eval(math.sqrt(dx * dx + dy * dy + dz * dz), coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg, True)
                w = weights[i]
                acc += w * v
                gx += w * d * dx
                gy += w * d * dy
                gz += w * d * dz
            out[j] = acc
            grad[j, 0] = gx
            grad[j, 1] = gy
            grad[j, 2] = gz


    @numba.njit(cache=True, parallel=True)
    def _table_matrix(x, y, out, coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg):
        for j in numba.prange(y.shape[0]):
            for i in range(x.shape[0]):
                dx, dy, dz = x[i, 0] - y[j, 0], x[i, 1] - y[j, 1], x[i, 2] - y[j, 2]
                v, _ = _table_eval(math.sqrt(dx * dx + dy * dy + dz * dz), coef1, coef2, r1, r2, h1, h2, rt, c, tv, tg, False)
                out[i, j] = v


def table_matrix(table: KernelTable, x, y, dtype=np.float64):
    """Approximate (tabulated) dense kernel matrix ``phi(|x_i - y_j|)``, Fortran order: ``direct_matrix``'s
    contract without ``lower``, the entries to the tables' accuracy (for a preconditioner, never to solve)."""
    x, y = _matrix_points(x, y)
    dtype = np.dtype(dtype)
    if dtype not in (np.float64, np.float32):
        raise ValueError(f"dtype must be float64 or float32, got {dtype}")
    out = np.empty((len(x), len(y)), dtype=dtype, order="F")
    _table_matrix(x, y, out, *table.args())
    return out


def supports_table(kernel) -> bool:
    return HAVE_NUMBA and kernel.name == "multiorder"


def kernel_table(kernel) -> KernelTable | None:
    """The tables of ``kernel`` (:class:`KernelTable`), built once for equal kernels; None where it has none."""
    return _kernel_table(kernel) if supports_table(kernel) else None


@functools.lru_cache(maxsize=8)
def _kernel_table(kernel) -> KernelTable:
    return KernelTable(kernel)


def table_sum(table: KernelTable, centres, weights, targets, gradient: bool = False):
    """Approximate (tabulated) kernel sum; same contract as ``direct_sum``."""
    c, w, t = check_sum_arrays(centres, weights, targets)
    coef1, coef2 = table.args()[:2]
    if coef1.ndim != 2 or coef1.shape[1] != 4 or coef1.shape[0] < 1 or coef2.ndim != 2 or coef2.shape[1] != 4 or coef2.shape[0] < 1:
        raise ValueError(f"kernel table has shapes {coef1.shape}, {coef2.shape}; expected (n, 4) each with n >= 1")
    out = np.empty(len(t))
    if gradient:
        grad = np.empty((len(t), 3))
        _table_sum_grad(c, w, t, out, grad, *table.args())
        return out, grad
    _table_sum(c, w, t, out, *table.args())
    return out
