"""The Gaussian-process posterior variance that a positive-definite kernel defines.

The regularized RBF interpolant with kernel phi and smoothing lambda_i is the
posterior mean of a Gaussian process with covariance phi(|x - y|) observed
with independent noise of variance lambda_i at the centres c_i.  Its
posterior variance,

    v(x) = phi(0) - k(x)^T (K + diag(lambda))^{-1} k(x),
    k(x)_i = phi(|x - c_i|),  K_ij = phi(|c_i - c_j|),

says how much the data pin f down at x: about lambda near well-sampled
constraints, phi(0) far from all of them.  (The polynomial part of the fit
is left out: this is the simple-kriging variance.)

:func:`posterior_variance` is the exact dense formula (O(N^3));
:func:`local_posterior_variance` conditions each target only on the ``m``
constraints nearest to the constraint nearest to it (one m x m Cholesky per
neighbourhood, shared by the targets that fall in it).  Conditioning on a
subset can only raise the variance, so the local value is an upper bound of
the exact one, and equals it when ``m = N``.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.spatial import cKDTree

from o3drbf.rbf.kernels import Kernel
from o3drbf.validation import as_points, check_number, per_point

__all__ = ["posterior_variance", "local_posterior_variance"]


def _check(kernel: Kernel, centres, smoothing, points):
    if not getattr(kernel, "positive_definite", False):
        raise ValueError(f"the {kernel.name!r} kernel is not positive definite, so it defines no posterior variance; "
                         "use a positive-definite kernel (multiorder, gaussian)")
    c = as_points(centres, "centres")
    lam = per_point("smoothing", smoothing, len(c))
    x = as_points(points, "points", min_count=0)
    return c, lam, x


def posterior_variance(kernel: Kernel, centres, smoothing, points, chunk: int = 4096) -> np.ndarray:
    """Exact GP posterior variance phi(0) - k^T (K + diag(lambda))^{-1} k at ``points``.

    Parameters
    ----------
    kernel : Kernel
        Positive definite.
    centres : (N, 3) array_like
        The constraints (the observations), same coordinates as ``points``.
    smoothing : float or (N,) array_like
        lambda_i >= 0, the noise variance of each observation.
    points : (P, 3) array_like
    chunk : int
        Targets per block of k(x) (memory ``8 * N * chunk`` bytes).

    Returns
    -------
    (P,) ndarray
        In [0, phi(0)] up to rounding (clipped there).

    Raises
    ------
    ValueError
        A kernel that is not positive definite, or bad shapes.
    """
    c, lam, x = _check(kernel, centres, smoothing, points)
    phi0 = kernel.value_at_zero
    k = kernel(_distances(c, c)) + np.diag(lam)
    factor = cho_factor(k, lower=True)
    out = np.empty(len(x))
    for s in range(0, len(x), int(chunk)):
        kx = kernel(_distances(c, x[s:s + chunk]))  # (N, chunk)
        z = solve_triangular(factor[0], kx, lower=True)
        out[s:s + chunk] = phi0 - np.einsum("ij,ij->j", z, z)
    return np.clip(out, 0.0, phi0)


def local_posterior_variance(kernel: Kernel, centres, smoothing, points, neighbours: int) -> np.ndarray:
    """GP posterior variance conditioned on a local neighbourhood of constraints.

    Each target x is conditioned on the ``neighbours`` constraints nearest to
    the constraint nearest to x (one Cholesky factor per such neighbourhood,
    shared by all the targets whose nearest constraint it is).

    Parameters
    ----------
    kernel : Kernel
        Positive definite.
    centres : (N, 3) array_like
    smoothing : float or (N,) array_like
        lambda_i >= 0.
    points : (P, 3) array_like
    neighbours : int
        m >= 1; ``m >= N`` gives the exact :func:`posterior_variance`.

    Returns
    -------
    (P,) ndarray
        In [0, phi(0)]; never below the exact value (up to rounding).
    """
    c, lam, x = _check(kernel, centres, smoothing, points)
    m = min(int(check_number("neighbours", neighbours, low=1, integer=True)), len(c))
    phi0 = kernel.value_at_zero
    out = np.full(len(x), phi0)
    if not len(x):
        return out
    tree = cKDTree(c)
    _, nearest = tree.query(x)
    groups, inverse = np.unique(nearest, return_inverse=True)
    if m == len(c):
        hood = np.broadcast_to(np.arange(m), (len(groups), m))
    else:
        _, hood = tree.query(c[groups], k=m)
        hood = hood.reshape(len(groups), m)
    order = np.argsort(inverse, kind="stable")  # targets sorted by neighbourhood
    chunk = max(1, int(2**25 // (8 * m * m)))  # targets per batch (~32 MB of m x m factors)
    eye = np.eye(m)
    for s in range(0, len(order), chunk):
        sel = order[s:s + chunk]
        used, local = np.unique(inverse[sel], return_inverse=True)
        idx = hood[used]  # (B, m)
        pts = c[idx]  # (B, m, 3)
        sq = np.einsum("bik,bik->bi", pts, pts)
        gram = np.matmul(pts, pts.transpose(0, 2, 1))
        kk = kernel(np.sqrt(np.maximum(sq[:, :, None] + sq[:, None, :] - 2.0 * gram, 0.0)))
        kk[:, np.arange(m), np.arange(m)] = phi0 + lam[idx]  # exact diagonal (the Gram formula rounds r = 0)
        try:
            inv_chol = np.linalg.solve(np.linalg.cholesky(kk), eye)  # (B, m, m): L^{-1}
        except np.linalg.LinAlgError:
            raise ValueError("a local kernel matrix is not positive definite (repeated constraints with zero smoothing?); "
                             "give them some smoothing or merge them") from None
        diff = x[sel][:, None, :] - pts[local]
        kx = kernel(np.sqrt(np.einsum("sik,sik->si", diff, diff)))  # (S, m)
        z = np.einsum("sij,sj->si", inv_chol[local], kx)
        out[sel] = phi0 - np.einsum("si,si->s", z, z)
    return np.clip(out, 0.0, phi0)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from scipy.spatial.distance import cdist

    return cdist(a, b)
