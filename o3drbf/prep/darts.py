"""Compiled dart throwing for :func:`o3drbf.prep.sampling.poisson_disc` (Numba, imported when first used).

Visits points in a given order and accepts one unless an accepted point lies
within the radius (``|p - q| <= radius``, the test of SciPy's
``cKDTree.query_ball_point``); candidates come from a uniform grid of cells
a little larger than the radius, so every point within the radius is in one
of the 27 cells around a point's own.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["greedy_darts", "MAX_CELLS", "MAX_ROWS_PER_POINT"]

#: Largest number of grid cells (the flat cell index must fit an int64); beyond it the caller uses a KD-tree.
MAX_CELLS = 2**62
#: Most rows of cells (a table entry each) per point; beyond it (a radius tiny for the cloud's extent) the caller uses a KD-tree.
MAX_ROWS_PER_POINT = 16
#: Grid cell over radius: a little above 1, so that rounding in the cell index never puts a point within
#: the radius two cells away.
CELL_FACTOR = 1.0 + 1e-6


@njit(cache=True)
def _throw(points, order, radius, origin, cell, dims, sorted_keys, row_start, position, accepted):
    # points sorted by cell (so one cell's points are neighbours in memory); position[i]: where point i went;
    # row_start[(i * dims[1] + j)]: the first sorted point of the row of cells (i, j, *)
    r2 = radius * radius
    taken = np.zeros(points.shape[0], dtype=np.bool_)  # by sorted position
    count = 0
    for idx in order:
        at = position[idx]
        if taken[at]:
            continue
        accepted[count] = idx
        count += 1
        x, y, z = points[at, 0], points[at, 1], points[at, 2]
        ci = int(np.floor((x - origin[0]) / cell))
        cj = int(np.floor((y - origin[1]) / cell))
        ck = int(np.floor((z - origin[2]) / cell))
        k0, k1 = max(ck - 1, 0), min(ck + 1, dims[2] - 1)
        for i in range(max(ci - 1, 0), min(ci + 2, dims[0])):
            for j in range(max(cj - 1, 0), min(cj + 2, dims[1])):
                row = i * dims[1] + j
                first, last = row_start[row], row_start[row + 1]
                if first == last:
                    continue
                # cells k0..k1 of this row are consecutive keys: one range, searched within the row
                keys = sorted_keys[first:last]
                lo = first + np.searchsorted(keys, row * dims[2] + k0, side="left")
                hi = first + np.searchsorted(keys, row * dims[2] + k1, side="right")
                for t in range(lo, hi):
                    dx, dy, dz = points[t, 0] - x, points[t, 1] - y, points[t, 2] - z
                    if dx * dx + dy * dy + dz * dz <= r2:
                        taken[t] = True
    return count


def greedy_darts(points: np.ndarray, order: np.ndarray, radius: float) -> np.ndarray | None:
    """Accepted indices, in the order of acceptance; None when the grid would have more than ``MAX_CELLS`` cells
    or more than ``MAX_ROWS_PER_POINT`` rows of cells per point.

    Parameters
    ----------
    points : (M, 3) float array
        Finite.
    order : (M,) int array
        A permutation of ``range(M)``: the visiting order.
    radius : float
        > 0.

    Returns
    -------
    (K,) int64 ndarray or None
    """
    pts = np.ascontiguousarray(points, dtype=np.float64)
    order = np.ascontiguousarray(order, dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] != 3 or order.shape != (len(pts),):
        raise ValueError(f"points must be (M, 3) and order (M,), got {pts.shape} and {order.shape}")
    if len(pts) == 0:
        return np.zeros(0, dtype=np.int64)
    cell = float(radius) * CELL_FACTOR
    origin = pts.min(axis=0)
    span = pts.max(axis=0) - origin
    dims_f = np.floor(span / cell) + 1
    if not np.isfinite(dims_f).all() or float(np.prod(dims_f)) >= MAX_CELLS or dims_f[0] * dims_f[1] > MAX_ROWS_PER_POINT * len(pts) + 1024:
        return None
    dims = dims_f.astype(np.int64)
    ijk = np.floor((pts - origin) / cell).astype(np.int64)
    np.clip(ijk, 0, dims - 1, out=ijk)
    keys = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    members = np.argsort(keys, kind="stable")
    sorted_keys = np.ascontiguousarray(keys[members])
    rows = dims[0] * dims[1]
    row_start = np.searchsorted(sorted_keys // dims[2], np.arange(rows + 1)).astype(np.int64)
    position = np.empty(len(pts), dtype=np.int64)
    position[members] = np.arange(len(pts))
    accepted = np.empty(len(pts), dtype=np.int64)
    n = _throw(np.ascontiguousarray(pts[members]), order, float(radius), origin, cell, dims, sorted_keys, row_start, position, accepted)
    return accepted[:n].copy()
