"""Denoised surface samples: points moved onto a local quadric fit of their neighbours.

A surface constraint taken as one raw point carries the whole noise of that
point; its neighbours among all the input points say where the surface is
much more precisely.  :func:`project_to_local_surface` fits each target's
``k`` nearest input points with a quadratic height field in their PCA frame
(one step of a moving-least-squares projection) and moves the target along
the local normal onto it, so every input point contributes to the
constraints, not just the subsample.  The quadric absorbs curvature, so
smooth, noise-free surfaces barely move (a sharp edge is rounded over the
neighbourhood: use it where the noise is worth more than the edge).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, check_number

__all__ = ["project_to_local_surface", "neighbourhood_size"]


def neighbourhood_size(points: int, targets: int, low: int = 24, high: int = 96) -> int:
    """Neighbours per target: about three times the points per target, within [low, high]."""
    return int(np.clip(round(3 * points / max(targets, 1)), low, high))


def project_to_local_surface(points, targets, k: int = 32, tree: cKDTree | None = None, chunk: int = 20_000,
                             noise: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Move each target onto the quadric fitted to its ``k`` nearest points.

    Parameters
    ----------
    points : (N, 3) array_like
        All the samples (at least 10).
    targets : (M, 3) array_like
        The points to move (e.g. the surface constraints, a subset of ``points``).
    k : int
        Neighbours per fit, 10..500 (capped at N).
    tree : cKDTree, optional
        A tree of ``points``, if one exists.
    chunk : int
        Targets per vectorized block (memory: about ``chunk * k * 60`` bytes).
    noise : float, optional
        The points' noise across the surface (their units).  Given, the fit
        is repeated once with Tukey weights on its residuals (``c = 4
        noise``), so neighbours on another sheet (a narrow gap, a thin
        wall) drop out, and a target that would move farther than ``4
        noise`` stays where it is.

    Returns
    -------
    moved : (M, 3) ndarray
        The projected targets.
    offset : (M,) ndarray
        Signed distance moved along the local normal.
    gain : (M,) ndarray
        Standard deviation of each fitted height per unit of point noise
        (independent noise, the final weights): ``sqrt(e6^T G^-1 X^T W^2 X
        G^-1 e6)`` with ``G = X^T W X``; ``noise * gain`` is a moved
        target's remaining noise (1 for a target left where it was).

    Notes
    -----
    In each target's neighbourhood (PCA frame centred on the neighbours'
    centroid, ``w`` the smallest axis), ``w = a u^2 + b uv + c v^2 + d u + e v
    + f`` is fitted by least squares with Gaussian weights
    ``exp(-2 r^2 / r_k^2)`` of the in-plane distance ``r`` to the target
    (``r_k`` the farthest neighbour's); the target keeps its ``(u, v)`` and
    takes the fitted ``w``.
    """
    pts = as_points(points, min_count=10)
    tg = np.asarray(as_points(targets, min_count=1), dtype=float)
    k = min(check_number("k", k, low=10, high=500, integer=True), len(pts))
    tree = cKDTree(pts) if tree is None else tree
    moved = np.empty_like(tg)
    offset = np.empty(len(tg))
    gain = np.ones(len(tg))
    for s in range(0, len(tg), chunk):
        q = tg[s:s + chunk]
        _, nb = tree.query(q, k=k, workers=-1)
        local = pts[nb]  # (Q, k, 3)
        centre = local.mean(axis=1, keepdims=True)
        local = local - centre
        cov = np.matmul(local.transpose(0, 2, 1), local)
        _, vecs = np.linalg.eigh(cov)  # ascending: column 0 is the normal
        frame = vecs[:, :, ::-1]  # u, v, w
        uvw = np.matmul(local, frame)
        me = np.matmul(q[:, None, :] - centre, frame)[:, 0, :]  # the target in the frame
        du, dv = uvw[..., 0] - me[:, :1], uvw[..., 1] - me[:, 1:2]
        r2 = du * du + dv * dv
        size = np.sqrt(r2.max(axis=1, keepdims=True)) + 1e-300
        x, y = du / size, dv / size  # centred on the target: the fit's constant is the height there
        w = np.exp(-2.0 * (r2 / (size * size)))
        design = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=2)
        coef, g = _weighted_fit(design, uvw[..., 2], w)
        if noise is not None and noise > 0:
            resid = uvw[..., 2] - np.matmul(design, coef[:, :, None])[..., 0]
            w = w * np.clip(1.0 - (resid / (4.0 * noise)) ** 2, 0.0, None) ** 2
            coef, g = _weighted_fit(design, uvw[..., 2], w)
        off = coef[:, 5] - me[:, 2]
        # variance of the intercept per unit noise: (G^-1 X^T W^2 X G^-1)[5, 5]
        e = np.linalg.solve(g, np.broadcast_to(np.eye(6)[5], (len(g), 6))[..., None])[..., 0]  # G^-1 e6 (G symmetric)
        xe = np.matmul(design, e[:, :, None])[..., 0]  # (Q, k)
        gn = np.sqrt(np.sum((w * xe) ** 2, axis=1))
        if noise is not None and noise > 0:
            keep = np.abs(off) <= 4.0 * noise
            off, gn = np.where(keep, off, 0.0), np.where(keep, gn, 1.0)
        moved[s:s + chunk] = q + off[:, None] * frame[:, :, 2]
        offset[s:s + chunk] = off
        gain[s:s + chunk] = gn
    return moved, offset, gain


def _weighted_fit(design: np.ndarray, z: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per neighbourhood, weighted least squares: (Q, k, 6), (Q, k), (Q, k) -> coefficients (Q, 6), Gram (Q, 6, 6)."""
    dw = design * w[..., None]
    gram = np.matmul(dw.transpose(0, 2, 1), design) + 1e-9 * np.eye(6)
    rhs = np.matmul(dw.transpose(0, 2, 1), z[..., None])
    return np.linalg.solve(gram, rhs)[:, :, 0], gram
