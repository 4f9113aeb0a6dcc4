"""GMRES on the dense (or chunked matrix-free) operator, Jacobi preconditioned."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.sparse.linalg import LinearOperator, gmres

from o3drbf.progress import progress_bar
from o3drbf.rbf.sums import kernel_matrix, kernel_sum
from o3drbf.solvers.base import ConvergenceWarning

__all__ = ["solve_gmres"]


def solve_gmres(kernel, centres, y, lam, q, rtol, max_iterations, matrix_fits, progress):
    """Solve the saddle-point system by GMRES (restart 200).

    ``matrix_fits`` chooses between an explicit matrix and chunked kernel
    sums.  Returns ``(w, p, iterations, info)``.
    """
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
    bar = progress_bar(progress, total=max_iterations, desc="GMRES", unit="it")

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


