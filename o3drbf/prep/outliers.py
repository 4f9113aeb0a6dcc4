"""Outlier removal before fitting: connected components and statistics.

Stray points far from the object would each pull the implicit surface
toward them.  The paper keeps the largest connected component (or the n
largest) of the points, neighbours being points within a radius, or voxels
in each other's 26-neighbourhood (method.md section 5).  Open3D's
statistical outlier removal is offered as well.

Every function returns the indices it keeps (sorted) and an
:class:`OutlierReport` of what it removed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from o3drbf.prep.sampling import neighbourhood_scatter, spatial_order
from o3drbf.validation import as_points, check_number

__all__ = ["OutlierReport", "largest_components", "voxel_components", "statistical_outliers", "isolated_points"]


@dataclass(frozen=True, eq=False)
class OutlierReport:
    """What an outlier filter removed.

    Attributes
    ----------
    method : str
    total : int
        Input count.
    kept : int
    removed_indices : (R,) int array
        Sorted indices of the removed inputs.
    components : int or None
        Number of connected components (component filters).
    kept_sizes : list of int
        Sizes of the kept components, largest first.
    largest_removed : int
        Size of the largest removed component (0 if none).
    parameters : dict
    """

    method: str
    total: int
    kept: int
    removed_indices: np.ndarray
    components: int | None = None
    kept_sizes: list = field(default_factory=list)
    largest_removed: int = 0
    parameters: dict = field(default_factory=dict)

    @property
    def removed(self) -> int:
        return int(len(self.removed_indices))

    def __str__(self) -> str:
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.parameters.items())
        text = f"{self.method}({params}): kept {self.kept} of {self.total}, removed {self.removed}"
        if self.components is not None:
            text += (
                f"; {self.components} component(s), kept sizes {self.kept_sizes}, "
                f"largest removed component {self.largest_removed}"
            )
        return text


def _keep_largest(labels: np.ndarray, n_components: int, keep: int, method: str, parameters: dict):
    """Indices in the ``keep`` largest components (ties: the one with the lowest index first)."""
    sizes = np.bincount(labels, minlength=n_components)
    first = np.full(n_components, len(labels), dtype=np.int64)
    np.minimum.at(first, labels, np.arange(len(labels)))
    order = np.lexsort((first, -sizes))  # largest first, then earliest
    chosen = order[:keep]
    mask = np.isin(labels, chosen)
    kept = np.flatnonzero(mask)
    report = OutlierReport(
        method=method,
        total=len(labels),
        kept=len(kept),
        removed_indices=np.flatnonzero(~mask),
        components=int(n_components),
        kept_sizes=[int(sizes[c]) for c in chosen],
        largest_removed=int(sizes[order[keep]]) if n_components > keep else 0,
        parameters=parameters,
    )
    return kept, report


def largest_components(points, radius: float, keep: int = 1):
    """Keep the ``keep`` largest connected components of the points.

    Two points are connected when they are within ``radius`` of each other
    (single linkage: a component is everything reachable in such steps).

    Parameters
    ----------
    points : (N, 3) array_like
    radius : float
        Neighbourhood radius (> 0), e.g. two or three mean spacings.
    keep : int
        How many components to keep (>= 1), largest first; ties go to the
        component holding the lower point index.

    Returns
    -------
    kept : (K,) int array
        Sorted indices of the kept points.
    report : OutlierReport
    """
    pts = as_points(points)
    radius = check_number("radius", radius, low=0.0, low_open=True)
    keep = check_number("keep", keep, low=1, integer=True)
    n = len(pts)
    pairs = cKDTree(pts).query_pairs(radius, output_type="ndarray")
    graph = sparse.coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return _keep_largest(labels, count, keep, "largest_components", {"radius": radius, "keep": keep})


# The 13 offsets of one half of the 26-neighbourhood (the other half by symmetry).
_HALF_26 = np.array([o for o in np.ndindex(3, 3, 3) if o > (1, 1, 1)], dtype=np.int64) - 1


def voxel_components(voxels, keep: int = 1):
    """Keep the ``keep`` largest 26-connected components of occupied voxels.

    Parameters
    ----------
    voxels : (V, 3) int array_like
        Integer indices of the occupied voxels (e.g. ``np.argwhere(occupancy)``);
        duplicates count once per row.
    keep : int
        How many components to keep (>= 1), largest (in voxels) first.

    Returns
    -------
    kept : (K,) int array
        Sorted row indices of the kept voxels.
    report : OutlierReport
    """
    try:
        ijk = np.asarray(voxels)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"voxels must be a (V, 3) integer array: {exc}") from None
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ValueError(f"voxels must have shape (V, 3), got {ijk.shape}")
    if len(ijk) == 0:
        raise ValueError("voxels is empty: the grid has no occupied voxel")
    if not np.issubdtype(ijk.dtype, np.integer):
        if not np.issubdtype(ijk.dtype, np.number) or not np.isfinite(ijk).all() or (ijk != np.round(ijk)).any():
            raise ValueError("voxels must hold integer voxel indices")
        ijk = ijk.astype(np.int64)
    keep = check_number("keep", keep, low=1, integer=True)
    ijk = ijk.astype(np.int64) - ijk.min(axis=0) + 1
    dims = ijk.max(axis=0) + 2
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    rows, cols = [], []
    # Duplicated voxels are connected to each other.
    dup = np.flatnonzero(skey[1:] == skey[:-1])
    rows.append(order[dup])
    cols.append(order[dup + 1])
    for o in _HALF_26:
        nkey = key + (o[0] * dims[1] + o[1]) * dims[2] + o[2]
        pos = np.minimum(np.searchsorted(skey, nkey), len(skey) - 1)
        hit = skey[pos] == nkey
        rows.append(np.flatnonzero(hit))
        cols.append(order[pos[hit]])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    n = len(ijk)
    graph = sparse.coo_matrix((np.ones(len(r), dtype=np.int8), (r, c)), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return _keep_largest(labels, count, keep, "voxel_components", {"keep": keep})


def statistical_outliers(points, nb_neighbors: int = 20, std_ratio: float = 2.0):
    """Open3D's statistical outlier removal.

    A point is removed when its mean distance to its ``nb_neighbors``
    nearest neighbours exceeds the global mean of that quantity by more than
    ``std_ratio`` standard deviations.

    Parameters
    ----------
    points : (N, 3) array_like
    nb_neighbors : int
        Neighbours per point (>= 1).
    std_ratio : float
        Threshold in standard deviations (> 0); smaller removes more.

    Returns
    -------
    kept : (K,) int array
        Sorted indices of the kept points.
    report : OutlierReport
    """
    import open3d as o3d

    pts = as_points(points, min_count=2)
    nb_neighbors = check_number("nb_neighbors", nb_neighbors, low=1, integer=True)
    std_ratio = check_number("std_ratio", std_ratio, low=0.0, low_open=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, index = pcd.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    kept = np.sort(np.asarray(index, dtype=np.int64))
    mask = np.ones(len(pts), dtype=bool)
    mask[kept] = False
    report = OutlierReport(
        method="statistical_outliers",
        total=len(pts),
        kept=len(kept),
        removed_indices=np.flatnonzero(mask),
        parameters={"nb_neighbors": nb_neighbors, "std_ratio": std_ratio},
    )
    return kept, report


def _small_components(pts, tree, radius: float, min_component: int, near=None, rows=None) -> np.ndarray:
    """Mask of the points in connected components (neighbours within ``radius``) of fewer than ``min_component``.

    A point with ``min_component - 1`` others within the radius is in a component at least that large, and
    so is every point connected to it.  Only the rest (candidates: the k nearest ``near``, when they reach that
    far, show who they are) can be in a small component, and only through other candidates: the graph is
    built on them alone, every point outside them merged into one node that marks a large component.
    Row r of ``near`` is point ``rows[r]`` (default: point r)."""
    n = len(pts)
    m = min_component - 1
    if near is None or near[0].shape[1] <= m:
        pairs = tree.query_pairs(radius, output_type="ndarray")
        graph = sparse.coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, labels = connected_components(graph, directed=False)
        return np.bincount(labels)[labels] < min_component
    cand = np.flatnonzero(near[0][:, m] > radius)  # (column 0: the point itself)
    if rows is not None:
        cand = np.sort(rows[cand])
    out = np.zeros(n, dtype=bool)
    if len(cand) == 0:
        return out
    slot = np.full(n, len(cand), dtype=np.int64)  # every point that is not a candidate: node len(cand)
    slot[cand] = np.arange(len(cand))
    lists = tree.query_ball_point(pts[cand], radius, workers=-1)
    rows = np.repeat(np.arange(len(cand)), [len(a) for a in lists])
    cols = slot[np.concatenate(lists).astype(np.int64)] if len(rows) else rows
    graph = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(len(cand) + 1, len(cand) + 1))
    _, labels = connected_components(graph, directed=False)
    size = np.bincount(labels)
    small = (size[labels[:-1]] < min_component) & (labels[:-1] != labels[-1])
    out[cand[small]] = True
    return out


#: Clouds of at least this many points are queried in spatial order by isolated_points.
SPATIAL_QUERIES = 20_000
#: isolated_points defaults (tuned on stacked tori, cubes and range scans;
#: docs/data/design-measurements.md, "Outliers").  The component radius must be well above the
#: percolation radius of random surface samples: a few median spacings still
#: leave some noise-free random samples in components under the minimum size.
ISOLATED_NEIGHBOURS = 24
ISOLATED_RADIUS_SPACINGS = 5.0
ISOLATED_MIN_COMPONENT = 10
ISOLATED_OFF_SURFACE = 5.0
ISOLATED_OFF_SPACINGS = 1.5


def isolated_points(
    points,
    spacing: float | None = None,
    *,
    k: int = ISOLATED_NEIGHBOURS,
    radius_spacings: float = ISOLATED_RADIUS_SPACINGS,
    min_component: int = ISOLATED_MIN_COMPONENT,
    off_surface: float = ISOLATED_OFF_SURFACE,
    off_spacings: float = ISOLATED_OFF_SPACINGS,
) -> np.ndarray:
    """Mask of sparse isolated points (e.g. uniform outliers), without cameras.

    Two local rules; neither compares component sizes across the cloud, so
    separate genuine objects are never dropped for being separate:

    - component: a point in a connected component (neighbours within
      ``radius_spacings`` spacings) of fewer than ``min_component`` points
      (so a genuine object of fewer points than that, farther than the
      radius from everything else, is removed too);
    - off-surface: a point farther from the plane of its ``k`` nearest
      neighbours than both ``off_surface`` times the neighbours' own RMS
      distance to that plane and ``off_spacings`` spacings (an outlier
      hovering near a surface; at an edge or in noise the neighbours' RMS is
      large too, so the point is kept).

    Parameters
    ----------
    points : (N, 3) array_like
    spacing : float, optional
        Point spacing (> 0); default the median nearest-neighbour distance.
    k : int
        Neighbours of the local plane (5..200).
    radius_spacings : float
        Component radius in spacings (> 0).
    min_component : int
        Smallest component kept (>= 1; 1 disables the rule).
    off_surface : float
        Off-plane threshold in neighbour RMS (> 0).
    off_spacings : float
        Off-plane threshold in spacings (>= 0).

    Returns
    -------
    (N,) bool array
        True for the isolated points (to remove).
    """
    pts = as_points(points, min_count=2)
    n = len(pts)
    k = check_number("k", k, low=5, high=200, integer=True)
    radius_spacings = check_number("radius_spacings", radius_spacings, low=0.0, low_open=True)
    min_component = check_number("min_component", min_component, low=1, integer=True)
    off_surface = check_number("off_surface", off_surface, low=0.0, low_open=True)
    off_spacings = check_number("off_spacings", off_spacings, low=0.0)
    tree = cKDTree(pts)
    kk = min(k, n - 1)
    # The plane's neighbours, queried first: their nearest is the spacing's (the same distances as k=2).
    # Row r of the answers is point rows[r]: the queries go in spatial order (twice as fast on large clouds).
    rows = spatial_order(pts) if n >= SPATIAL_QUERIES else np.arange(n)
    q = pts[rows]
    near = tree.query(q, k=kk + 1, workers=-1) if kk >= 3 else None
    if spacing is None:
        d = near[0] if near is not None else tree.query(pts, k=2, workers=-1)[0]
        spacing = float(np.median(d[:, 1]))
        if not spacing > 0:
            raise ValueError("points are (mostly) duplicates: their median spacing is zero; remove duplicates first")
    spacing = check_number("spacing", spacing, low=0.0, low_open=True)
    isolated = np.zeros(n, dtype=bool)
    if min_component > 1:
        isolated |= _small_components(pts, tree, radius_spacings * spacing, min_component, near, rows)
    if near is not None:
        off = np.empty(n, dtype=bool)
        for s in range(0, n, PLANE_CHUNK):
            offset, rms = _plane_offsets(pts, q[s : s + PLANE_CHUNK], near[1][s : s + PLANE_CHUNK, 1:])
            off[s : s + PLANE_CHUNK] = (offset > off_surface * rms) & (offset > off_spacings * spacing)
        isolated[rows] |= off
    return isolated


#: Points whose neighbour planes :func:`isolated_points` fits at once: the (chunk, k, 3) work arrays stay
#: small and in cache instead of holding every point's neighbours at once
#: (benchmarks/recorded/fast_solver.md, session 26).
PLANE_CHUNK = 16384


def _plane_offsets(pts, q, idx):
    """(distance of each ``q`` from the least-squares plane of its neighbours ``pts[idx]`` (rows of k),
    the neighbours' RMS distance from that plane)."""
    centroid, dev, scatter = neighbourhood_scatter(pts, idx)
    _, vecs = np.linalg.eigh(scatter / idx.shape[1])
    normal = vecs[:, :, 0]
    rms = np.sqrt((np.matmul(dev, normal[:, :, None])[..., 0] ** 2).mean(axis=1))
    return np.abs(np.einsum("ni,ni->n", q - centroid, normal)), rms
