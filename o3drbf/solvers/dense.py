"""Dense solve of the regularized system: LAPACK Cholesky with a Schur
complement for the polynomial, or a symmetric indefinite solve."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from o3drbf.rbf.sums import kernel_matrix
from o3drbf.solvers.base import dense_blas_threads

__all__ = ["solve_dense", "DenseFactor", "DENSE_MAX"]

#: Largest dense solve o3drbf runs.  The OpenBLAS shipped with numpy/scipy
#: wheels segfaults in a two-thread Cholesky of 16,000+ unknowns on this
#: class of machine (exit 139, no message), and the fast solver is faster
#: well before that (docs/data/design-measurements.md, "Solver choice").  Above it, method="dense" is refused.
DENSE_MAX = 12_000
#: Columns of the inverse a DenseFactor keeps for later refits (each N floats).
MAX_KEPT_COLUMNS = 1024


class DenseFactor:
    """``Phi + diag(lambda_0)`` factored once (Cholesky), solved for any smoothing close to ``lambda_0``.

    A robust refit changes the smoothing of a few constraints (down-weighted
    or dropped).  With ``E`` the columns of those k constraints and
    ``D = diag(lambda_k - lambda_0,k)``, the Woodbury identity

        (A + E D E^T)^{-1} = A^{-1} - A^{-1} E (D^{-1} + E^T A^{-1} E)^{-1} E^T A^{-1}

    solves the new system with k extra back-substitutions and a k x k solve
    instead of a new O(N^3) factorization.  ``lambda = inf`` leaves a
    constraint out (``D^{-1} = 0``: its weight is exactly zero and the rest is
    the system without it).  The back-substitutions that do not depend on
    the smoothing are kept for the next refit: ``A^{-1} [y, Q]`` and the
    columns of ``A^{-1}`` of every constraint changed so far (up to
    ``MAX_KEPT_COLUMNS``, N floats each), so a robust loop that changes the
    same few constraints round after round back-substitutes only the new ones.

    Parameters
    ----------
    kernel : Kernel
        Positive definite (multi-order, Gaussian).
    centres : (N, 3) ndarray
    lam : (N,) ndarray
        The smoothing factored, ``lambda_0 >= 0``.
    q : (N, M) ndarray
        Polynomial basis at the centres.

    Raises
    ------
    numpy.linalg.LinAlgError
        The matrix is not numerically positive definite.
    """

    def __init__(self, kernel, centres, lam, q):
        n = len(centres)
        a = kernel_matrix(kernel, centres, lower=True)  # the factorization reads the lower triangle only
        a[np.diag_indices(n)] += lam
        with dense_blas_threads():
            self.factor = sla.cho_factor(a, lower=True, overwrite_a=True, check_finite=False)
        self.lam0 = np.array(lam, dtype=float)
        self.q = q
        # Back-substitutions that do not depend on the smoothing, kept across refits:
        # A^{-1} [y, Q] for the last y, and A^{-1} e_j for constraints already changed once.
        self._base = None
        self._columns: dict[int, np.ndarray] = {}

    def solve(self, y, lam=None):
        """Weights and polynomial for targets ``y`` and smoothing ``lam`` (default ``lambda_0``).

        Parameters
        ----------
        y : (N,) ndarray
        lam : (N,) ndarray, optional
            May differ from ``lambda_0`` anywhere (cost grows with the number
            of changed constraints) and be ``inf`` where a constraint is left out.

        Returns
        -------
        w : (N,) ndarray
            Zero where ``lam`` is infinite.
        p : (M,) ndarray
        changed : int
            Constraints whose smoothing differs from ``lambda_0``.
        """
        q = self.q
        n, m = q.shape
        y = np.asarray(y, dtype=float)
        if self._base is None or not np.array_equal(self._base[0], y):
            self._base = (y.copy(), sla.cho_solve(self.factor, np.column_stack([y, q]), check_finite=False))
        x = self._base[1].copy()
        changed = np.zeros(0, dtype=int) if lam is None else np.flatnonzero(np.asarray(lam) != self.lam0)
        if len(changed):
            k = len(changed)
            z = self._inverse_columns(changed)
            d = np.asarray(lam, dtype=float)[changed] - self.lam0[changed]
            inner = z[changed]
            inner[np.diag_indices(k)] += np.where(np.isinf(d), 0.0, 1.0 / np.where(np.isinf(d), 1.0, d))
            x = x - z @ np.linalg.solve(inner, x[changed])
            out = np.isinf(np.asarray(lam, dtype=float))
            x[out] = 0.0
        u, v = x[:, 0], x[:, 1:]
        if m:
            p = np.linalg.solve(q.T @ v, q.T @ u)
            w = u - v @ p
        else:
            p, w = np.zeros(0), u
        return w, p, len(changed)

    def _inverse_columns(self, idx: np.ndarray) -> np.ndarray:
        """Columns ``idx`` of ``A^{-1}`` (N x k), each back-substituted once and kept (up to MAX_KEPT_COLUMNS)."""
        n = len(self.lam0)
        new = [int(j) for j in idx if int(j) not in self._columns]
        if new:
            e = np.zeros((n, len(new)))
            e[new, np.arange(len(new))] = 1.0
            z = sla.cho_solve(self.factor, e, check_finite=False)
            if len(self._columns) + len(new) > MAX_KEPT_COLUMNS:
                self._columns.clear()
            fresh = dict(zip(new, z.T))
            if len(new) <= MAX_KEPT_COLUMNS:
                self._columns.update(fresh)
        else:
            fresh = {}
        return np.column_stack([self._columns[int(j)] if int(j) in self._columns else fresh[int(j)] for j in idx])

    def residual(self, y, lam, w, p) -> float:
        """Relative residual of ``(w, p)`` (all N weights) in the system with smoothing ``lam`` (``inf``: left out),
        ``|| [Phi w + lambda w + Q p - y ; Q^T w] || / ||y||`` over the kept constraints.

        ``Phi w`` is ``L (L^T w) - lambda_0 w`` with the kept Cholesky factor ``L``
        (two triangular products, O(N^2) without evaluating the kernel).
        """
        c, _ = self.factor
        lam = np.asarray(lam, dtype=float)
        keep = np.isfinite(lam)
        w = np.where(keep, w, 0.0)
        a0w = sla.blas.dtrmv(c, sla.blas.dtrmv(c, w, lower=1, trans=1), lower=1)
        r1 = (a0w + (np.where(keep, lam, 0.0) - self.lam0) * w + self.q @ p - y)[keep]
        r2 = self.q.T @ w
        return float(np.sqrt(r1 @ r1 + r2 @ r2) / max(float(np.linalg.norm(np.asarray(y)[keep])), np.finfo(float).tiny))


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
        try:
            w, p, _ = DenseFactor(kernel, centres, lam, q).solve(y)
            return w, p, {"factorization": "cholesky"}
        except np.linalg.LinAlgError:
            pass
    # Symmetric indefinite saddle-point system (thin-plate, or Cholesky failed).
    big = np.zeros((n + m, n + m), order="F")
    big[:n, :n] = kernel_matrix(kernel, centres)
    big[np.arange(n), np.arange(n)] += lam
    big[:n, n:] = q
    big[n:, :n] = q.T
    rhs = np.concatenate([y, np.zeros(m)])
    with dense_blas_threads():
        sol = sla.solve(big, rhs, assume_a="sym", overwrite_a=True, overwrite_b=True, check_finite=False)
    return sol[:n], sol[n:], {"factorization": "symmetric-indefinite"}


