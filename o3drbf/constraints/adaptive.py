"""Fewer surface constraints where the surface is flat: thinning a uniform subset by the local flatness.

A uniform Poisson-disc subset (:func:`o3drbf.constraints.core.surface_constraints`)
is thinned where the points around a constraint lie close to a plane: each
constraint gets a spacing factor ``m >= 1`` from how far its neighbourhood
departs from its best plane (curvature, an edge, a second sheet), beyond the
points' noise, and a dart throw over the subset (the most curved constraints
first) drops a constraint that lies within ``m`` Poisson-disc radii of one
already kept.  Where ``m = 1`` every constraint is kept, so the curved parts
keep the uniform rule's constraints exactly.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, check_number

__all__ = ["MAX_FACTOR", "plane_deviation", "spacing_factors", "thin_by_factor", "adaptive_subset"]

#: Largest spacing factor of ``surface_adaptive``: a flat part keeps about
#: ``1 / MAX_FACTOR**2`` of the uniform rule's constraints
#: (docs/data/adaptive-constraints.md).
MAX_FACTOR = 1.6


def plane_deviation(points, centres, k: int = 48, tree: cKDTree | None = None, noise: float = 0.0,
                    chunk: int = 20_000) -> tuple[np.ndarray, np.ndarray]:
    """RMS distance of each centre's ``k`` nearest points to their best plane, beyond the noise.

    Parameters
    ----------
    points : (N, 3) array_like
        All the samples (at least 4).
    centres : (M, 3) array_like
        Where to measure (e.g. the surface constraints).
    k : int
        Neighbours per centre, 4..500 (capped at N).
    tree : cKDTree, optional
        A tree of ``points``.
    noise : float
        The points' noise across the surface (their units, >= 0): its
        variance is taken off the mean squared distance.
    chunk : int
        Centres per vectorized block.

    Returns
    -------
    deviation : (M,) ndarray
        ``sqrt(max(lambda_min / k - noise^2, 0))``, ``lambda_min`` the
        smallest eigenvalue of the neighbours' scatter matrix (their units).
    radius : (M,) ndarray
        Distance to the farthest of the ``k`` neighbours.
    """
    pts = as_points(points, min_count=4)
    cen = as_points(centres, min_count=1, name="centres")
    k = min(check_number("k", k, low=4, high=500, integer=True), len(pts))
    noise = check_number("noise", noise, low=0.0)
    tree = cKDTree(pts) if tree is None else tree
    dev = np.empty(len(cen))
    rad = np.empty(len(cen))
    for s in range(0, len(cen), chunk):
        d, nb = tree.query(cen[s:s + chunk], k=k, workers=-1)
        local = pts[nb]
        local = local - local.mean(axis=1, keepdims=True)
        cov = np.matmul(local.transpose(0, 2, 1), local)
        smallest = np.linalg.eigvalsh(cov)[:, 0]
        dev[s:s + chunk] = np.sqrt(np.maximum(smallest / k - noise * noise, 0.0))
        rad[s:s + chunk] = d[:, -1]
    return dev, rad


def spacing_factors(deviation, radius, spacing: float, tolerance: float, max_factor: float) -> np.ndarray:
    """Spacing factor ``m`` in ``[1, max_factor]`` per constraint from its neighbourhood's plane deviation.

    A paraboloid of curvature ``kappa`` departs from its plane by RMS
    ``kappa R^2 / (4 sqrt 3)`` over a disc of radius ``R``, and a linear
    interpolant between samples ``s`` apart sags by ``kappa s^2 / 8``; the
    spacing whose sag is ``tolerance * spacing`` is then
    ``s = R sqrt(tolerance * spacing / (0.866 deviation))`` and ``m = s / spacing``.

    Parameters
    ----------
    deviation, radius : (M,) array_like
        From :func:`plane_deviation`.
    spacing : float
        The uniform subset's spacing (> 0), same units.
    tolerance : float
        Allowed sag between constraints, in spacings (> 0).
    max_factor : float
        Largest factor (>= 1).

    Returns
    -------
    (M,) ndarray
    """
    dev = np.asarray(deviation, dtype=float)
    rad = np.asarray(radius, dtype=float)
    spacing = check_number("spacing", spacing, low=0.0, low_open=True)
    tolerance = check_number("tolerance", tolerance, low=0.0, low_open=True)
    max_factor = check_number("max_factor", max_factor, low=1.0)
    with np.errstate(divide="ignore"):
        s = rad * np.sqrt(tolerance * spacing / (np.sqrt(0.75) * dev))
    return np.clip(s / spacing, 1.0, max_factor)


def thin_by_factor(points, factors, seed: int = 0) -> np.ndarray:
    """Indices kept by a dart throw with per-point radii ``factor * r``, ``r`` the smallest pairwise distance.

    Points are visited in increasing factor (ties in a seeded random
    order); a point is dropped when a kept point lies closer than ``r``
    times the larger of the two factors.  Points whose factor is 1 are
    all kept (no two points are closer than ``r``).

    Returns
    -------
    (K,) int array
        Sorted indices into ``points``.
    """
    pts = as_points(points, min_count=1)
    fac = np.asarray(factors, dtype=float)
    if len(fac) != len(pts):
        raise ValueError(f"thin_by_factor: {len(fac)} factors for {len(pts)} points")
    if len(pts) < 2 or float(fac.max()) <= 1.0:
        return np.arange(len(pts))
    tree = cKDTree(pts)
    r = float(tree.query(pts, k=2)[0][:, 1].min())
    if r <= 0:
        return np.arange(len(pts))
    rng = np.random.default_rng(seed)
    order = np.lexsort((rng.permutation(len(pts)), fac))
    kept = np.zeros(len(pts), dtype=bool)
    reach = r * float(fac.max())
    for i in order.tolist():
        if fac[i] > 1.0:
            near = tree.query_ball_point(pts[i], reach)
            if near:
                near = np.asarray(near)
                near = near[kept[near]]
                if len(near) and np.any(np.linalg.norm(pts[near] - pts[i], axis=1) < r * np.maximum(fac[near], fac[i])):
                    continue
        kept[i] = True
    return np.flatnonzero(kept)


def adaptive_subset(points, idx, tolerance: float, max_factor: float, noise: float = 0.0, tree: cKDTree | None = None,
                    k: int = 48, seed: int = 0) -> np.ndarray:
    """The uniform subset ``idx`` of ``points`` thinned where the surface is flat.

    Parameters
    ----------
    points : (N, 3) array_like
    idx : (M,) int array_like
        A Poisson-disc subset of ``points``.
    tolerance : float
        Allowed sag between constraints, in spacings (:func:`spacing_factors`).
    max_factor : float
        Largest spacing factor (flat parts get ``max_factor^2`` times fewer constraints, at most).
    noise : float
        The points' noise (their units).
    tree : cKDTree, optional
        A tree of ``points``.
    k : int
        Neighbours per flatness measure.
    seed : int

    Returns
    -------
    (K,) int array
        A sorted subset of ``idx``.
    """
    pts = as_points(points, min_count=4)
    idx = np.asarray(idx, dtype=np.int64)
    if len(idx) < 3:
        return idx
    sub = pts[idx]
    spacing = float(cKDTree(sub).query(sub, k=2)[0][:, 1].mean())
    dev, rad = plane_deviation(pts, sub, k=k, tree=tree, noise=noise)
    fac = spacing_factors(dev, rad, spacing, tolerance, max_factor)
    return idx[thin_by_factor(sub, fac, seed=seed)]
