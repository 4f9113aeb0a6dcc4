"""Kernel matrices and kernel sums, evaluated in memory-bounded chunks.

``kernel_sum`` computes f(x) - P(x) = sum_i w_i phi(|x - c_i|) (and its
gradient) at any number of targets with a fixed working-memory budget: the
reference ("direct") evaluator that every faster method is checked against.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist

from o3drbf.rbf import compiled as _direct
from o3drbf.rbf.kernels import Kernel

__all__ = ["kernel_matrix", "kernel_sum", "polynomial_basis", "DEFAULT_CHUNK_BYTES"]

#: Working memory for one chunk of a kernel sum (several temporaries of this size).
DEFAULT_CHUNK_BYTES = 32 * 2**20


def polynomial_basis(points: np.ndarray, degree: int) -> np.ndarray:
    """The polynomial basis at ``points``: ``(N, 0)``, ``[1]`` or ``[1 x y z]``."""
    points = np.asarray(points, dtype=float)
    n = len(points)
    if degree < 0:
        return np.zeros((n, 0))
    if degree == 0:
        return np.ones((n, 1))
    if degree == 1:
        return np.column_stack([np.ones(n), points])
    raise ValueError(f"polynomial degree must be -1, 0 or 1, got {degree}")


def kernel_matrix(
    kernel: Kernel, x: np.ndarray, y: np.ndarray | None = None, order: str = "F", compiled: bool = True,
    lower: bool = False, dtype=np.float64, table=None,
) -> np.ndarray:
    """Phi_ij = phi(|x_i - y_j|) as a dense array (Fortran order by default,
    so LAPACK can factor it in place).

    ``lower=True`` (with ``y`` omitted) promises the caller reads only the
    lower triangle (e.g. a lower Cholesky factorization): the compiled path
    then evaluates only that half and leaves the upper triangle uninitialised.
    ``dtype=np.float32`` stores the entries, evaluated in double, in single
    precision (half the memory; for a preconditioner's products).
    ``table`` (an :class:`o3drbf.rbf.compiled.KernelTable` of ``kernel``, not
    with ``lower``): the entries from its tables, to their accuracy (faster;
    for a preconditioner, never for a solve's own matrix).
    """
    x = np.asarray(x, dtype=float)
    if lower and y is not None:
        raise ValueError("lower=True is for the symmetric matrix of x with itself; omit y")
    y = x if y is None else np.asarray(y, dtype=float)
    if table is not None and not lower:
        if order == "F":
            return _direct.table_matrix(table, x, y, dtype=dtype)
        return _direct.table_matrix(table, y, x, dtype=dtype).T
    if compiled and _direct.supports(kernel) and not (lower and np.dtype(dtype) != np.float64):
        if order == "F":
            return _direct.direct_matrix(kernel, x, y, lower=lower, dtype=dtype)
        if not lower:  # phi(|x_i - y_j|) is symmetric in the pair: the Fortran (y, x) matrix's transpose
            return _direct.direct_matrix(kernel, y, x, dtype=dtype).T
    r = cdist(x, y)
    out = kernel(r).astype(dtype, copy=False)
    return np.asfortranarray(out) if order == "F" else np.ascontiguousarray(out)


def _rows_per_chunk(n_centres: int, chunk_bytes: int) -> int:
    return max(1, int(chunk_bytes // (8 * max(n_centres, 1))))


def kernel_sum(
    kernel: Kernel,
    centres: np.ndarray,
    weights: np.ndarray,
    targets: np.ndarray,
    gradient: bool = False,
    chunk_bytes: int = DEFAULT_CHUNK_BYTES,
    compiled: bool = True,
    table=None,
):
    """sum_i w_i phi(|x - c_i|) at every target x, and optionally its gradient.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array
    weights : (N,) array
    targets : (M, 3) array
    gradient : bool
        Also return the (M, 3) gradient.
    chunk_bytes : int
        Working memory per chunk; total memory is O(M + N + chunk_bytes).
    compiled : bool
        Use the compiled (Numba) loop when the kernel has one (no matrix is
        formed); ``False`` forces the NumPy reference path.
    table : o3drbf.rbf.compiled.KernelTable, optional
        Evaluate the multi-order kernel from these tables instead (faster,
        and accurate to the tables' tolerance rather than to rounding:
        docs/data/design-measurements.md, "Tabulated kernel").  For meshing, never for solving.

    Returns
    -------
    values : (M,) array
    gradients : (M, 3) array, only if ``gradient``
    """
    centres = np.asarray(centres, dtype=float)
    weights = np.asarray(weights, dtype=float)
    targets = np.asarray(targets, dtype=float)
    if table is not None:
        return _direct.table_sum(table, centres, weights, targets, gradient=gradient)
    if compiled and _direct.supports(kernel):
        return _direct.direct_sum(kernel, centres, weights, targets, gradient=gradient)
    m = len(targets)
    values = np.empty(m)
    grads = np.empty((m, 3)) if gradient else None
    wc = weights[:, None] * centres if gradient else None
    step = _rows_per_chunk(len(centres), chunk_bytes)
    for start in range(0, m, step):
        t = targets[start : start + step]
        r = cdist(t, centres)
        values[start : start + step] = kernel(r) @ weights
        if gradient:
            d = kernel.derivative_over_r(r)
            # sum_i w_i phi'(r)/r (x - c_i) = x (D w) - D (w c)
            grads[start : start + step] = t * (d @ weights)[:, None] - d @ wc
    return (values, grads) if gradient else values
