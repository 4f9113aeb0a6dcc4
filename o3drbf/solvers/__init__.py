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

import logging
import time
import warnings

import numpy as np

from o3drbf.rbf.kernels import Kernel
from o3drbf.rbf.sums import polynomial_basis
from o3drbf.solvers.base import ConvergenceWarning, Solution, available_memory, dense_memory, gigabytes, relative_residual
from o3drbf.solvers.dense import DENSE_MAX, solve_dense
from o3drbf.solvers.iterative import solve_gmres
from o3drbf.validation import as_points, check_choice, check_number, per_point

__all__ = ["Solution", "solve", "available_memory", "dense_memory", "ConvergenceWarning", "METHODS",
           "DENSE_MAX", "DENSE_AUTO_MAX", "FAST_EVALUATION_MIN", "choose_method"]

#: Solver methods. "fast" (grid products + preconditioned Krylov) is in o3drbf.solvers.fast.
METHODS = ("auto", "dense", "iterative", "fast")

#: ``method="auto"`` solves densely up to this many constraints and uses the
#: fast solver above (measured: 3k dense 4.3 s vs fast 5.7 s; 10k dense 36 s
#: vs fast 13 s).
DENSE_AUTO_MAX = 6_000

log = logging.getLogger("o3drbf")

#: Above this many centres a fast-solved surface is evaluated by fast sums too
#: (below it the compiled direct sum is as fast: measured 14.1 s vs 14.4 s for
#: 200,000 targets x 3,400 centres with fmm3dpy; the grid backend is faster).
FAST_EVALUATION_MIN = 20_000


def choose_method(n: int, memory_limit: int | None = None) -> tuple[str, str]:
    """The method ``"auto"`` picks for ``n`` constraints, and why.

    Dense only when it is both the faster choice (``n <= DENSE_AUTO_MAX``)
    and fits in memory; the fast solver otherwise.
    """
    limit = int(0.8 * available_memory()) if memory_limit is None else int(memory_limit)
    need = dense_memory(n)
    if n > DENSE_AUTO_MAX:
        return "fast", f"{n} constraints > {DENSE_AUTO_MAX}: the fast solver is faster there"
    if need > limit:
        return "fast", f"a dense solve of {n} constraints needs {gigabytes(need)}; limit {gigabytes(limit)}"
    return "dense", f"{n} constraints <= {DENSE_AUTO_MAX} and {gigabytes(need)} fits in {gigabytes(limit)}"


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
        (:mod:`o3drbf.solvers.fast`).  "auto": dense up to ``DENSE_AUTO_MAX`` constraints when it fits in
        memory, fast above (:func:`choose_method`).
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
        Products of the fast method (:func:`o3drbf.solvers.fast.fast_operator`): the
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
        method, why = choose_method(n + m, limit)
        log.info("solver: %s (%s)", method, why)
    if method == "dense" and n + m > DENSE_MAX:
        raise ValueError(
            f"a dense solve of {n} constraints is refused: above {DENSE_MAX} the installed OpenBLAS is known to "
            "crash and the fast solver is faster; use method='fast' (or 'auto')"
        )
    if method == "dense" and need > limit:
        raise MemoryError(
            f"a dense solve of {n} constraints needs about {gigabytes(need)} but the limit is {gigabytes(limit)}; "
            "use method='fast' (O(N log N)), or fewer constraints (surface_count)"
        )
    if method == "fast":
        from o3drbf.solvers import fast

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
        w, p, info = solve_dense(kernel, centres, y, lam, q)
        iterations = 0
    else:
        w, p, iterations, info = solve_gmres(kernel, centres, y, lam, q, 1e-10 if rtol is None else rtol, max_iterations, need <= limit, progress)
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


