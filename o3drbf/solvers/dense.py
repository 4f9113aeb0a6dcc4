"""Dense solve of the regularized system: LAPACK Cholesky with a Schur
complement for the polynomial, or a symmetric indefinite solve."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from o3drbf.rbf.compiled import lower_pair, lower_single, supports
from o3drbf.rbf.sums import kernel_matrix
from o3drbf.solvers.base import dense_blas_threads

__all__ = ["solve_dense", "DenseFactor", "DENSE_MAX", "MIXED_MIN", "REFINE_RTOL", "REFINE_STEPS"]

#: Largest dense solve o3drbf runs.  The OpenBLAS shipped with numpy/scipy
#: wheels segfaults in a two-thread Cholesky of 16,000+ unknowns on this
#: class of machine (exit 139, no message), and the fast solver is faster
#: well before that (docs/data/design-measurements.md, "Solver choice").  Above it, method="dense" is refused.
DENSE_MAX = 12_000
#: Columns of the inverse a DenseFactor keeps for later refits (each N floats).
MAX_KEPT_COLUMNS = 1024
#: From this many constraints on, ``DenseFactor(precision="auto")`` factors in single precision and refines
#: every solve to double precision (``"mixed"``); below it the double factorization is kept
#: (docs/data/design-measurements.md, "Mixed-precision dense factorization").
MIXED_MIN = 2000
#: A mixed-precision solve is refined until every column's normwise backward error
#: ``||b - A x|| / (||A||_F ||x|| + ||b||)`` is at most this (a few times double precision's rounding) ...
REFINE_RTOL = 1e-15
#: ... in at most this many corrections; a solve that does not get there (or stops shrinking its residual)
#: refactors in double precision.
REFINE_STEPS = 8


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
    precision : {"auto", "mixed", "double"}
        "double": LAPACK's double-precision Cholesky, in place.  "mixed":
        the matrix is kept in double precision and a single-precision copy
        is factored (single-precision arithmetic: twice the floating-point
        rate of double); every solve is then refined
        (iterative refinement: residual ``b - A x`` in double precision,
        correction from the single factor) to a backward error of
        ``REFINE_RTOL``, and refactored in double precision if it does not
        get there in ``REFINE_STEPS`` corrections.  Half as much memory
        again as "double".  "auto": "mixed" from ``MIXED_MIN`` constraints.

    Attributes
    ----------
    precision : str
        "mixed" or "double": what the solves use now (a mixed factor that
        failed to refine is "double" from then on).

    Raises
    ------
    numpy.linalg.LinAlgError
        The matrix is not numerically positive definite.
    """

    def __init__(self, kernel, centres, lam, q, precision: str = "auto"):
        if precision not in ("auto", "mixed", "double"):
            raise ValueError(f"precision must be 'auto', 'mixed' or 'double', got {precision!r}")
        n = len(centres)
        self.precision = ("mixed" if n >= MIXED_MIN else "double") if precision == "auto" else precision
        self.matrix = None  # mixed: A (lower triangle, double) for the residuals of the refinement
        self.single = None  # mixed: the single-precision Cholesky factor
        self.norm = float("nan")  # mixed: ||A||_F
        self.factor = None  # double: scipy's (factor, lower)
        single = None
        if self.precision == "mixed" and supports(kernel):
            # The double matrix and its single copy in one pass over the kernel (no second pass to copy).
            a, single, self.norm = lower_pair(kernel, centres, np.broadcast_to(np.asarray(lam, dtype=float), (n,)))
        else:
            a = kernel_matrix(kernel, centres, lower=True)  # the factorization reads the lower triangle only
            a[np.diag_indices(n)] += lam
        if self.precision == "mixed":
            with dense_blas_threads(n):
                if single is None:
                    single, self.norm = lower_single(a)
                single, info = sla.lapack.spotrf(single, lower=1, overwrite_a=1, clean=0)
            if info == 0:
                self.matrix, self.single = a, single
            else:  # not positive definite in single precision: factor in double
                self.precision = "double"
        if self.precision == "double":
            with dense_blas_threads(n):
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
            self._base = (y.copy(), self.solve_matrix(np.column_stack([y, q])))
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
            z = self.solve_matrix(e)
            if len(self._columns) + len(new) > MAX_KEPT_COLUMNS:
                self._columns.clear()
            fresh = dict(zip(new, z.T))
            if len(new) <= MAX_KEPT_COLUMNS:
                self._columns.update(fresh)
        else:
            fresh = {}
        return np.column_stack([self._columns[int(j)] if int(j) in self._columns else fresh[int(j)] for j in idx])

    def solve_matrix(self, b) -> np.ndarray:
        """``A^{-1} b`` for ``A = Phi + diag(lambda_0)`` and ``b`` of shape (N,) or (N, K), in double precision.

        Mixed precision: refined from the single factor (see the class) until
        every column's backward error ``||b - A x|| / (||A||_F ||x|| + ||b||)``
        is at most ``REFINE_RTOL``; a solve that does not get there in
        ``REFINE_STEPS`` corrections, or stops shrinking it, refactors in
        double precision and solves again.
        """
        b = np.asarray(b, dtype=float)
        if self.single is None:
            with dense_blas_threads(len(b)):
                return sla.cho_solve(self.factor, b, check_finite=False)
        flat = b.ndim == 1
        b2 = b.reshape(len(b), -1)
        bnorm = np.linalg.norm(b2, axis=0)
        with dense_blas_threads(len(b2)):
            x = sla.lapack.spotrs(self.single, b2.astype(np.float32), lower=1)[0].astype(float)
            previous = np.inf
            for _ in range(REFINE_STEPS + 1):
                r = b2 - sla.blas.dsymm(1.0, self.matrix, x, side=0, lower=1)
                scale = np.maximum(self.norm * np.linalg.norm(x, axis=0) + bnorm, np.finfo(float).tiny)
                res = float((np.linalg.norm(r, axis=0) / scale).max())
                if res <= REFINE_RTOL:
                    return x.ravel() if flat else x
                if not res < 0.5 * previous:
                    break
                previous = res
                x += sla.lapack.spotrs(self.single, r.astype(np.float32), lower=1)[0]
        self.double()
        return self.solve_matrix(b)

    def double(self) -> None:
        """Drop the single-precision factor and factor ``A`` in double precision (in place); from now on "double"."""
        if self.single is None:
            return
        a, self.matrix, self.single = self.matrix, None, None
        self.precision = "double"
        with dense_blas_threads(len(a)):
            self.factor = sla.cho_factor(a, lower=True, overwrite_a=True, check_finite=False)

    def residual(self, y, lam, w, p) -> float:
        """Relative residual of ``(w, p)`` (all N weights) in the system with smoothing ``lam`` (``inf``: left out),
        ``|| [Phi w + lambda w + Q p - y ; Q^T w] || / ||y||`` over the kept constraints.

        ``Phi w`` is ``A w - lambda_0 w``: ``A w`` from the kept double-precision
        matrix (mixed precision) or as ``L (L^T w)`` from the Cholesky factor
        ``L`` (double): O(N^2) products, no kernel evaluated.
        """
        lam = np.asarray(lam, dtype=float)
        keep = np.isfinite(lam)
        w = np.where(keep, w, 0.0)
        if self.single is not None:
            a0w = sla.blas.dsymv(1.0, self.matrix, w, lower=1)
        else:
            c, _ = self.factor
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
    with dense_blas_threads(len(big)):
        sol = sla.solve(big, rhs, assume_a="sym", overwrite_a=True, overwrite_b=True, check_finite=False)
    return sol[:n], sol[n:], {"factorization": "symmetric-indefinite"}


