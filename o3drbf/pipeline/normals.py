"""Normals: given normals checked and repaired, missing ones estimated and oriented (when there are no cameras)."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.pointset import PointSet

__all__ = ["estimate_normals", "check_given_normals", "ensure_normals"]

log = logging.getLogger("o3drbf")


def estimate_normals(points, k: int = 30, seed: int = 0) -> np.ndarray:
    """Outward unit normals for a point cloud without them (Open3D).

    Normals are estimated from ``k`` nearest neighbours, oriented
    consistently over a neighbour graph, then flipped as a whole so that most
    point away from the centroid (right for closed, roughly star-shaped
    objects; give normals or cameras when that does not hold).

    Parameters
    ----------
    points : (N, 3) array_like
    k : int
    seed : int
        Unused (Open3D's estimate is deterministic); kept for symmetry.

    Returns
    -------
    (N, 3) ndarray

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import estimate_normals
    >>> estimated = estimate_normals(points, k=20)
    >>> bool((estimated * normals).sum(axis=1).min() > 0.9)  # outward, close to the true normals
    True
    """
    import open3d as o3d

    from o3drbf.validation import as_points

    pts = as_points(points, min_count=4)
    k = min(int(k), len(pts) - 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    try:
        pcd.orient_normals_consistent_tangent_plane(min(k, 15))
    except RuntimeError:  # degenerate neighbour graphs
        pcd.orient_normals_towards_camera_location(pts.mean(axis=0))
        return -np.asarray(pcd.normals)
    n = np.asarray(pcd.normals).copy()
    # The tangent-plane orientation is consistent within each connected piece
    # of the neighbour graph, not across pieces: flip each piece on its own so
    # that its normals point away from its own centroid (separate objects,
    # e.g. stacked tori, are each oriented outward).
    labels = _neighbour_components(pts, k=min(k, 10))
    for c in np.unique(labels):
        sel = labels == c
        if np.einsum("ij,ij->i", n[sel], pts[sel] - pts[sel].mean(axis=0)).mean() < 0:
            n[sel] = -n[sel]
    return n


def _neighbour_components(points: np.ndarray, k: int) -> np.ndarray:
    """Connected components of the symmetric k-nearest-neighbour graph (labels)."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    _, nb = cKDTree(points).query(points, k=k + 1, workers=-1)
    rows = np.repeat(np.arange(len(points)), k)
    graph = sparse.coo_matrix((np.ones(rows.size), (rows, nb[:, 1:].ravel())), shape=(len(points), len(points)))
    return connected_components(graph, directed=False)[1]


def check_given_normals(data: PointSet, *, seed: int = 0):
    """Check the given normals against the points (and cameras), and repair them when they are wrong.

    See :func:`o3drbf.prep.orientation.check_normals`: normals that point
    opposite ways between neighbours are re-oriented consistently, normals
    that all point inward are flipped, and with ``point_camera`` a normal
    facing away from its camera is flipped.  A repair is logged as a warning.

    Parameters
    ----------
    data : PointSet
    seed : int

    Returns
    -------
    PointSet
        ``data`` itself when there were no given normals or they passed.
    NormalCheck or None
        None without given normals.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import check_given_normals
    >>> flipped = PointSet.create(points, -normals)  # every normal pointing inward
    >>> repaired, check = check_given_normals(flipped)
    >>> bool((repaired.normals * normals).sum(axis=1).min() > 0)
    True
    """
    if data.normals is None or data.normals_estimated:
        return data, None
    from o3drbf.prep.orientation import check_normals

    normals, check = check_normals(data.points, data.normals, data.cameras, data.point_camera, seed=seed)
    if not check.changed:
        return data, check
    log.warning("normals repaired (%s): %s", check.action, check.reason)
    return data.with_normals(normals), check


def ensure_normals(data: PointSet, *, seed: int = 0) -> tuple[PointSet, bool]:
    """Estimate normals when there are neither normals nor cameras.

    Returns the PointSet (with normals) and whether they were estimated.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet, ensure_normals
    >>> data, estimated = ensure_normals(PointSet.create(points))
    >>> estimated, bool((data.normals * normals).sum(axis=1).min() > 0.9)  # outward, as the true normals
    (True, True)
    """
    if data.normals is not None or data.cameras is not None:
        return data, False
    log.info("no normals given: estimating and orienting normals with Open3D (30 neighbours)")
    return data.with_normals(estimate_normals(data.points, seed=seed), estimated=True), True
