"""Flexible GMRES with inexact (relaxed) products, restarted from the true residual."""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg as sla

__all__ = ["fgmres", "RESTART"]

#: Iterations of an FGMRES cycle before it restarts from the true residual (the fast solve's default).  A restart
#: throws the Krylov space away, and the million-centre system of the user's path stalled after a restart at 50
#: (benchmarks/recorded/fast_solver.md, session 19).  The basis is stored only as far as it is used.
RESTART = 100


def fgmres(matvec, b, prec, rtol, max_iterations, restart, true_matvec, bar=None, final=True, start=None):
    """Flexible GMRES (right preconditioned), restarted from the true residual.

    ``matvec(x, rel)`` may be inexact with relative accuracy ``rel`` (relaxed
    as the residual falls); ``true_matvec`` is the accurate product used at
    every restart; ``start`` a starting guess ``(x0, r0)`` (default 0), ``r0``
    its residual ``b - true_matvec(x0)`` when the caller knows it, else None
    (one product finds it).  Returns x, iterations, true relative residual,
    history, and the true residual vector ``b - true_matvec(x)`` (None after
    one cycle with ``final`` False, which does not compute it).
    """
    n = len(b)
    bn = float(np.linalg.norm(b))
    if bn == 0:
        return np.zeros(n), 0, 0.0, [], np.zeros(n)
    x0, r0 = (None, None) if start is None else start
    if x0 is None:
        x = np.zeros(n)
        r = b.copy()
    else:
        x = np.array(x0, dtype=float)
        r = b - true_matvec(x) if r0 is None else np.array(r0, dtype=float)
    beta = float(np.linalg.norm(r))
    its = 0
    history = []
    while True:
        if beta <= rtol * bn or its >= max_iterations:
            return x, its, beta / bn, history, r
        m = min(restart, max_iterations - its)
        V = np.empty((m + 1, n))
        Z = np.empty((m, n))
        H = np.zeros((m + 1, m))
        V[0] = r / beta
        g = np.zeros(m + 1)
        g[0] = beta
        cs, sn = np.zeros(m), np.zeros(m)
        est = beta
        j_used = 0
        for j in range(m):
            Z[j] = prec(V[j])
            # Relaxed accuracy: eps * ||r_0|| / ||r_j|| (inexact Krylov).
            w = matvec(Z[j], bn / max(est, 1e-300))
            its += 1
            for i in range(j + 1):  # modified Gram-Schmidt, twice for safety
                H[i, j] = w @ V[i]
                w -= H[i, j] * V[i]
            for i in range(j + 1):
                c = w @ V[i]
                H[i, j] += c
                w -= c * V[i]
            hnext = float(np.linalg.norm(w))
            H[j + 1, j] = hnext
            if hnext > 0:
                V[j + 1] = w / hnext
            for i in range(j):  # apply previous Givens rotations
                t = cs[i] * H[i, j] + sn[i] * H[i + 1, j]
                H[i + 1, j] = -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
                H[i, j] = t
            den = math.hypot(H[j, j], H[j + 1, j])
            cs[j], sn[j] = (1.0, 0.0) if den == 0 else (H[j, j] / den, H[j + 1, j] / den)
            H[j, j] = den
            H[j + 1, j] = 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            est = abs(g[j + 1])
            history.append(est / bn)
            j_used = j + 1
            if bar is not None:
                bar.update(1)
                bar.set_postfix(residual=f"{est / bn:.1e}")
            if est <= rtol * bn or hnext == 0:
                break
        y = sla.solve_triangular(H[:j_used, :j_used], g[:j_used], check_finite=False)
        x = x + Z[:j_used].T @ y
        del V, Z
        if not final:  # one cycle, no true residual (a nested solve)
            return x, its, est / bn, history, None
        r = b - true_matvec(x)
        beta = float(np.linalg.norm(r))
        if est <= rtol * bn and beta > rtol * bn and history and history[-1] < 1e-3 * beta / bn:
            # The recurrence converged but the true residual did not move:
            # the products are not accurate enough to go further.
            return x, its, beta / bn, history, r
