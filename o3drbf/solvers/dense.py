"""Dense solve of the regularized system: LAPACK Cholesky with a Schur
complement for the polynomial, or a symmetric indefinite solve."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from o3drbf.rbf.sums import kernel_matrix

__all__ = ["solve_dense", "DENSE_MAX"]

#: Largest dense solve o3drbf runs.  The OpenBLAS shipped with numpy/scipy
#: wheels segfaults in a two-thread Cholesky of 16,000+ unknowns on this
#: class of machine (exit 139, no message), and the fast solver is faster
#: well before that (10k: 13 s vs 36 s).  Above it, method="dense" is refused.
DENSE_MAX = 12_000


def solve_dense(kernel, centres, y, lam, q):
    """Solve the saddle-point system directly.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) ndarray
    y : (N,) ndarray
        Target values.
    lam : (N,) ndarray
        Per-constraint smoothing.
    q : (N, M) ndarray
        Polynomial basis at the centres.

    Returns
    -------
    w : (N,) ndarray
    p : (M,) ndarray
    info : dict
        ``{"factorization": "cholesky" | "symmetric-indefinite"}``.
    """
    n, m = q.shape
    if kernel.positive_definite:
        a = kernel_matrix(kernel, centres)
        a[np.diag_indices(n)] += lam
        try:
            factor = sla.cho_factor(a, lower=True, overwrite_a=True, check_finite=False)
        except np.linalg.LinAlgError:
            factor = None
        if factor is not None:
            x = sla.cho_solve(factor, np.column_stack([y, q]), check_finite=False)
            u, v = x[:, 0], x[:, 1:]
            if m:
                s = q.T @ v
                p = np.linalg.solve(s, q.T @ u)
                w = u - v @ p
            else:
                p, w = np.zeros(0), u
            return w, p, {"factorization": "cholesky"}
        del a
    # Symmetric indefinite saddle-point system (thin-plate, or Cholesky failed).
    big = np.zeros((n + m, n + m), order="F")
    big[:n, :n] = kernel_matrix(kernel, centres)
    big[np.arange(n), np.arange(n)] += lam
    big[:n, n:] = q
    big[n:, :n] = q.T
    rhs = np.concatenate([y, np.zeros(m)])
    sol = sla.solve(big, rhs, assume_a="sym", overwrite_a=True, overwrite_b=True, check_finite=False)
    return sol[:n], sol[n:], {"factorization": "symmetric-indefinite"}


