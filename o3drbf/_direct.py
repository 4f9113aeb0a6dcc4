"""Compiled direct sums (Numba): sum_i w_i phi(|x - c_i|) and its gradient
without forming the matrix, parallel over targets.

Private: :func:`o3drbf.sums.kernel_sum` calls :func:`direct_sum` when the
kernel has a compiled form here, and the NumPy path in ``sums``/``kernels``
is the reference it is tested against.
"""

from __future__ import annotations

import math

import numpy as np

try:  # numba is a dependency, but the library still works (slower) without it
    import os

    import numba

    if "NUMBA_THREADING_LAYER" not in os.environ:
        # Numba's own "workqueue" threads: with the OpenMP layer, the solve
        # (OpenBLAS) and the sums both ran 2-3x slower next to Open3D's
        # OpenMP runtime (measured: dense solve of 3,373 constraints 3.1 s ->
        # 1.0 s, 128^3 extraction 13.6 s -> 7.3 s), and an old system TBB
        # makes numba warn.  workqueue must not be entered from two Python
        # threads at once: o3drbf calls it from one thread at a time.
        numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

__all__ = ["HAVE_NUMBA", "direct_sum", "direct_matrix", "supports"]

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
        d1, d3, d4, d5 = kernel._d1, kernel._d3, kernel._d4, kernel._d5
        return _MULTIORDER, np.array([A.real, B.real, a, b, kernel._c, d1, d3, d4, d5], dtype=float)
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


def direct_sum(kernel, centres, weights, targets, gradient: bool = False):
    """Compiled kernel sum; same contract as :func:`o3drbf.sums.kernel_sum`."""
    code, p = _params(kernel)
    c = np.ascontiguousarray(centres, dtype=float)
    w = np.ascontiguousarray(weights, dtype=float)
    t = np.ascontiguousarray(targets, dtype=float)
    out = np.empty(len(t))
    if gradient:
        grad = np.empty((len(t), 3))
        _sum_grad(code, p, c, w, t, out, grad)
        return out, grad
    _sum(code, p, c, w, t, out)
    return out


def direct_matrix(kernel, x, y):
    """Compiled dense kernel matrix, Fortran order."""
    code, p = _params(kernel)
    out = np.empty((len(x), len(y)), order="F")
    _matrix(code, p, np.ascontiguousarray(x, float), np.ascontiguousarray(y, float), out)
    return out
