"""Uniform subsampling (Poisson-disc), spacing statistics and a spatial order of points."""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.validation import as_points, check_number

__all__ = ["poisson_disc", "mean_spacing", "fibonacci_sphere", "spatial_order", "neighbourhood_scatter"]


def mean_spacing(points, sample: int | None = None, tree: cKDTree | None = None, seed: int = 0) -> float:
    """Mean distance from each point to its nearest other point (the paper's
    "average minimum distance between surface samples").

    Parameters
    ----------
    points : (N, 3) array_like, N >= 2
    sample : int, optional
        Estimate from this many randomly chosen query points (all when
        ``None`` or ``N <= sample``): the mean is then exact.
    tree : scipy.spatial.cKDTree, optional
        A KD-tree of these same points, to reuse.
    seed : int
        For the random choice of query points.

    Returns
    -------
    float
    """
    pts = as_points(points, min_count=2)
    tree = cKDTree(pts) if tree is None else tree
    q = pts
    if sample is not None and len(pts) > check_number("sample", sample, low=1, integer=True):
        q = pts[np.random.default_rng(seed).choice(len(pts), sample, replace=False)]
    d, _ = tree.query(q, k=2, workers=-1)
    return float(d[:, 1].mean())


def _greedy(points: np.ndarray, order: np.ndarray, radius: float, trees: list | None = None) -> np.ndarray:
    """Dart throwing in a fixed order: accept a point unless an accepted one is
    within ``radius``; each acceptance marks its neighbours as taken (compiled,
    :func:`o3drbf.prep.darts.greedy_darts`; a KD-tree loop for a grid too
    fine to index, its tree kept in ``trees`` for the next call on the same points)."""
    from o3drbf.prep.darts import greedy_darts

    accepted = greedy_darts(points, order, radius)
    if accepted is not None:
        return accepted
    trees = [] if trees is None else trees
    if not trees:
        trees.append(cKDTree(points))
    tree = trees[0]
    taken = np.zeros(len(points), dtype=bool)
    accepted = []
    for idx in order.tolist():
        if taken[idx]:
            continue
        accepted.append(idx)
        taken[tree.query_ball_point(points[idx], radius)] = True
    return np.asarray(accepted, dtype=np.int64)


def _candidates(points: np.ndarray, cell: float, rng) -> np.ndarray:
    """One random point per grid cell of side ``cell``: a cheap pre-thinning
    that bounds the greedy pass by the output size, not the input size."""
    keys = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    keys -= keys.min(axis=0)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    order = rng.permutation(len(points))
    _, first = np.unique(flat[order], return_index=True)
    return np.sort(order[first])


def poisson_disc(points, count: int | None = None, radius: float | None = None, seed: int = 0) -> np.ndarray:
    """Indices of a Poisson-disc subset: no two kept points closer than a radius.

    Parameters
    ----------
    points : (N, 3) array_like
    count : int, optional
        Target number of points; the radius is searched so the subset has
        about this many (within a few percent).  ``count >= N`` keeps all.
    radius : float, optional
        Minimum distance between kept points.  Give ``count`` or ``radius``.
    seed : int
        Seed of the random visiting order: the result is deterministic.

    Returns
    -------
    (M,) int array
        Sorted indices into ``points``.
    """
    pts = as_points(points, min_count=1)
    n = len(pts)
    if (count is None) == (radius is None):
        raise ValueError("give exactly one of count or radius")
    rng = np.random.default_rng(seed)
    if radius is not None:
        radius = check_number("radius", radius, low=0.0, low_open=True)
        cand = _candidates(pts, radius / 3.0, rng)
        return np.sort(cand[_greedy(pts[cand], rng.permutation(len(cand)), radius)])
    count = check_number("count", count, low=1, integer=True)
    if count >= n:
        return np.arange(n)
    if float(np.ptp(pts, axis=0).max()) == 0:
        return np.array([0])
    # Start from the spacing of a random subset of `count` points; then secant
    # steps in log space (count ~ r^-2 on surfaces).  The candidates are
    # pre-thinned once at a quarter of the smallest radius likely to be tried.
    sub = pts[rng.choice(n, size=min(n, max(count, 2)), replace=False)]
    r = 1.2 * mean_spacing(sub)
    cand = _candidates(pts, r / 6.0, rng)
    cp = pts[cand]
    order = rng.permutation(len(cand))
    best = None
    trees = []  # the candidates' KD-tree, built only if the compiled darts cannot index them, then kept
    for _ in range(20):
        sel = _greedy(cp, order, r, trees)
        err = len(sel) - count
        if best is None or abs(err) < abs(len(best) - count):
            best = sel
        if abs(err) <= max(1, 0.02 * count):
            break
        r *= (len(sel) / count) ** 0.5
    return np.sort(cand[best])


def fibonacci_sphere(n: int, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``n`` nearly uniform points on a sphere (golden-angle spiral)."""
    n = check_number("n", n, low=1, integer=True)
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    rho = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    theta = math.pi * (3.0 - math.sqrt(5.0)) * i
    pts = np.column_stack([rho * np.cos(theta), rho * np.sin(theta), z])
    return np.asarray(center, dtype=float) + radius * pts


def spatial_order(points, bits: int = 10) -> np.ndarray:
    """The points' indices along a Z-order (Morton) curve over their bounding box, ``bits`` levels a side.

    Nearby points get nearby indices, so a sparse near-field matrix over points in this order
    reads its vector from a small window of memory, and k-d tree queries made in this order find
    their neighbours in the cache (both run about twice as fast as over points in scan or sampling order).  Ties keep their
    input order (a stable sort): the same points give the same order.

    Parameters
    ----------
    points : (N, 3) array_like
    bits : int
        Levels of the curve (1..21): cells of ``1 / 2**bits`` of the box's longest side.

    Returns
    -------
    (N,) int64 array
        A permutation of ``range(N)``.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.prep.sampling import spatial_order
    >>> spatial_order(np.array([[1.0, 1, 1], [0, 0, 0], [1, 0, 0], [0, 0, 0.1]]), bits=1).tolist()
    [1, 3, 2, 0]
    """
    x = np.asarray(points, dtype=float).reshape(-1, 3)
    if not 1 <= int(bits) <= 21:
        raise ValueError(f"bits must be in 1..21, got {bits}")
    if len(x) == 0:
        return np.zeros(0, np.int64)
    lo = x.min(axis=0)
    span = max(float((x.max(axis=0) - lo).max()), 1e-300)
    cells = 2 ** int(bits)
    key = np.minimum((x - lo) / span * cells, cells - 1).astype(np.int64)
    code = np.zeros(len(x), np.int64)
    for b in range(int(bits)):
        for axis in range(3):
            code |= ((key[:, axis] >> b) & 1) << (3 * b + (2 - axis))
    return np.argsort(code, kind="stable")


def neighbourhood_scatter(points: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each neighbourhood's centroid, offsets from it and scatter matrix (the least-squares plane's ingredients).

    Parameters
    ----------
    points : (N, 3) array
    idx : (M, k) int array
        The points of each of M neighbourhoods.

    Returns
    -------
    centroid : (M, 3) array
    dev : (M, k, 3) array
        Each neighbour minus its neighbourhood's centroid.
    scatter : (M, 3, 3) array
        ``dev^T dev`` (k times the covariance); its eigenvector of the smallest eigenvalue is the plane's normal.
    """
    nb = np.take(points, idx, axis=0)  # (M, k, 3) (take: a contiguous gather)
    centroid = nb.mean(axis=1)
    dev = nb - centroid[:, None, :]
    return centroid, dev, np.matmul(dev.transpose(0, 2, 1), dev)  # batched BLAS: several times faster than einsum here
