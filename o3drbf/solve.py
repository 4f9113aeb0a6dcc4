"""The regularized fit: solve for RBF weights and polynomial coefficients.

Notes
-----
The system (method.md section 2) is the saddle-point problem

    [ Phi + diag(lambda)   Q ] [ w ]   [ y ]
    [ Q^T                  0 ] [ p ] = [ 0 ]

with Phi_ij = phi(|c_i - c_j|), Q the polynomial basis at the centres, y the
target values (0 surface, -1 exterior, +1 interior) and lambda >= 0 the
per-constraint smoothing.  For a positive-definite kernel (multi-order,
Gaussian) Phi + diag(lambda) is factored by Cholesky and p comes from the
small Schur complement Q^T (Phi + Lambda)^{-1} Q.  Thin-plate r^3 is only
conditionally positive definite and is solved as a symmetric indefinite
system.  The iterative method (GMRES) solves the same system with a
Jacobi-preconditioned operator and must agree with the dense one.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import dataclass, field

import logging

import numpy as np
import scipy.linalg as sla
from scipy.sparse.linalg import LinearOperator, gmres

from ._validate import as_points, check_choice, check_number, per_point
from .kernels import Kernel
from .sums import kernel_matrix, kernel_sum, polynomial_basis

__all__ = ["Solution", "solve", "available_memory", "dense_memory", "ConvergenceWarning", "METHODS"]

#: Solver methods. "fast" (fast multipole + preconditioned Krylov) is in o3drbf.fast.
METHODS = ("auto", "dense", "iterative", "fast")

log = logging.getLogger("o3drbf")

#: Above this many centres a fast-solved surface is evaluated by fast sums too
#: (below it the compiled direct sum is as fast: measured 14.1 s vs 14.4 s for
#: 200,000 targets x 3,400 centres with fmm3dpy; the grid backend is faster).
FMM_EVALUATION_MIN = 20_000


class ConvergenceWarning(UserWarning):
    """An iterative solve stopped before reaching its tolerance."""


@dataclass
class Solution:
    """Weights, polynomial coefficients and a record of how they were found."""

    weights: np.ndarray
    poly: np.ndarray
    method: str
    residual: float
    seconds: float
    iterations: int = 0
    info: dict = field(default_factory=dict)


def available_memory() -> int:
    """Bytes of memory available now (MemAvailable), or 4 GiB if unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 4 * 2**30


def dense_memory(n: int) -> int:
    """Peak bytes of a dense solve of ``n`` constraints (the matrix, factored in place, plus slack)."""
    return int(8 * (n + 4) ** 2 * 1.1 + 64 * n)


def _gb(x: float) -> str:
    return f"{x / 2**30:.1f} GB"


def solve(
    kernel: Kernel,
    centres,
    values,
    smoothing=0.0,
    method: str = "auto",
    rtol: float | None = None,
    max_iterations: int = 1000,
    memory_limit: int | None = None,
    progress: bool = False,
    backend: str = "auto",
) -> Solution:
    """Fit weights and polynomial so that f(c_i) + lambda_i w_i = y_i.

    Parameters
    ----------
    kernel : Kernel
    centres : (N, 3) array_like
        Constraint positions (in the normalized box).
    values : (N,) array_like
        Target values y_i.
    smoothing : float or (N,) array_like
        lambda_i >= 0; 0 interpolates.
    method : {"auto", "dense", "iterative", "fast"}
        "dense": LAPACK Cholesky (or symmetric indefinite) with a residual
        check.  "iterative": GMRES on the dense operator (or a chunked
        matrix-free one when the matrix does not fit).  "fast": fast
        multipole products and a preconditioned Krylov solve
        (:mod:`o3drbf.fast`).  "auto": dense when it fits in memory.
    rtol : float, optional
        Relative residual target for the iterative methods, in (0, 1).
        Default 1e-10 for "iterative", 1e-6 for "fast" (a mesh needs far
        less; the multipole tolerance follows it).
    max_iterations : int
    memory_limit : int, optional
        Bytes the dense solve may use; default 80% of available memory.
    progress : bool
        Show a progress bar (iterative methods).
    backend : {"auto", "grid", "fmm"}
        Products of the fast method (:func:`o3drbf.fast.fast_operator`): the
        grid (Gaussian-split particle-mesh, multi-order kernel) or fmm3dpy.

    Returns
    -------
    Solution

    Raises
    ------
    ValueError
        Bad shapes or parameters, or too few constraints for the polynomial.
    MemoryError
        A dense solve that would not fit in ``memory_limit``; the message
        names the limit and the alternatives.
    """
    t0 = time.perf_counter()
    centres = as_points(centres, name="centres", min_count=1)
    n = len(centres)
    y = np.asarray(values, dtype=float)
    if y.shape != (n,):
        raise ValueError(f"values must have shape ({n},), got {y.shape}")
    if not np.isfinite(y).all():
        raise ValueError("values contain NaN or infinity")
    lam = per_point("smoothing", smoothing, n, low=0.0)
    check_choice("method", method, METHODS)
    check_choice("backend", backend, ("auto", "grid", "fmm"))
    if rtol is not None:
        rtol = check_number("rtol", rtol, low=0.0, high=1.0, low_open=True)
    q = polynomial_basis(centres, kernel.polynomial_degree)
    m = q.shape[1]
    if n < m + 1:
        raise ValueError(f"{kernel.name} basis needs at least {m + 1} constraints, got {n}")
    if m > 1 and np.linalg.matrix_rank(q) < m:
        raise ValueError("constraint points are coplanar: the linear polynomial of the thin-plate basis is not determined")
    limit = int(0.8 * available_memory()) if memory_limit is None else int(memory_limit)
    need = dense_memory(n + m)

    if method == "auto":
        method = "dense" if need <= limit else "fast"
        log.info(
            "solver: %s (a dense solve of %d constraints needs %s; limit %s)",
            method, n, _gb(need), _gb(limit),
        )
    if method == "dense" and need > limit:
        raise MemoryError(
            f"a dense solve of {n} constraints needs about {_gb(need)} but the limit is {_gb(limit)}; "
            "use method='fast' (fast multipole, O(N log N)), or fewer constraints (surface_count)"
        )
    if method == "fast":
        from . import fast  # imported lazily: optional dependency

        sol = fast.solve(kernel, centres, y, lam, rtol=1e-6 if rtol is None else rtol,
                         max_iterations=min(max_iterations, 200), progress=progress, backend=backend)
        split = sol.info["split"]
        log.info(
            "solver: fast products (%s) + two-level preconditioned FGMRES, %d constraints: %d iterations, "
            "residual %.1e, %.1f s",
            split.get("mode") or split.get("split"), n, sol.iterations, sol.residual, time.perf_counter() - t0,
        )
        sol.seconds = time.perf_counter() - t0
        return sol
    if method == "dense":
        w, p, info = _solve_dense(kernel, centres, y, lam, q)
        iterations = 0
    else:
        w, p, iterations, info = _solve_gmres(kernel, centres, y, lam, q, 1e-10 if rtol is None else rtol, max_iterations, need <= limit, progress)
    residual = relative_residual(kernel, centres, y, lam, q, w, p)
    sol = Solution(w, p, method, residual, time.perf_counter() - t0, iterations, info)
    if method == "dense" and residual > 1e-6:
        warnings.warn(
            f"dense solve residual {residual:.1e} is large: the system is ill-conditioned "
            "(near-duplicate constraints with lambda = 0?); increase lambda",
            ConvergenceWarning,
            stacklevel=2,
        )
    return sol


def relative_residual(kernel, centres, y, lam, q, w, p) -> float:
    """|| [Phi w + lambda w + Q p - y ; Q^T w] || / ||y|| (matrix-free)."""
    r1 = kernel_sum(kernel, centres, w, centres) + lam * w + q @ p - y
    r2 = q.T @ w
    denom = max(float(np.linalg.norm(y)), np.finfo(float).tiny)
    return float(math.sqrt(float(r1 @ r1 + r2 @ r2)) / denom)


def _solve_dense(kernel, centres, y, lam, q):
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


def _solve_gmres(kernel, centres, y, lam, q, rtol, max_iterations, matrix_fits, progress):
    n, m = q.shape
    if matrix_fits:
        a = kernel_matrix(kernel, centres, order="C")
        a[np.diag_indices(n)] += lam

        def apply_a(w):
            return a @ w

        diag = np.diag(a).copy()
    else:

        def apply_a(w):
            return kernel_sum(kernel, centres, w, centres) + lam * w

        diag = np.full(n, kernel.value_at_zero) + lam

    def matvec(x):
        w, p = x[:n], x[n:]
        return np.concatenate([apply_a(w) + q @ p, q.T @ w])

    op = LinearOperator((n + m, n + m), matvec=matvec, dtype=float)
    safe = np.where(np.abs(diag) > 0, diag, 1.0)
    # Jacobi on the kernel block, a scaled identity on the polynomial block.
    pscale = float(np.mean(np.abs(safe)))
    inv = np.concatenate([1.0 / safe, np.full(m, 1.0 / pscale)])
    prec = LinearOperator((n + m, n + m), matvec=lambda x: inv * x, dtype=float)
    rhs = np.concatenate([y, np.zeros(m)])
    count = [0]
    bar = _bar(progress, max_iterations, "GMRES")

    def callback(res):
        count[0] += 1
        if bar is not None:
            bar.update(1)
            bar.set_postfix(residual=f"{float(res):.1e}")

    restart = min(n + m, 200)
    x, info = gmres(op, rhs, rtol=rtol, atol=0.0, restart=restart, maxiter=max(1, max_iterations // restart + 1),
                    M=prec, callback=callback, callback_type="pr_norm")
    if bar is not None:
        bar.close()
    if info != 0:
        warnings.warn(
            f"GMRES did not reach rtol={rtol:g} within {count[0]} iterations; "
            "the residual reached is in Solution.residual. Raise max_iterations or use method='dense'.",
            ConvergenceWarning,
            stacklevel=3,
        )
    return x[:n], x[n:], count[0], {"preconditioner": "jacobi", "converged": info == 0}


def _bar(enabled: bool, total: int, desc: str):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="it", leave=False, disable=os.environ.get("O3DRBF_NO_PROGRESS") == "1")
