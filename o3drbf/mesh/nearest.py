"""Exact distances from points to a triangle mesh, through a uniform grid of the triangles.

:func:`point_mesh_distance` returns, for each point, the Euclidean distance
to the nearest point of the nearest triangle, in double precision.  The
triangles are binned by their bounding boxes into a uniform grid; each point
searches the cells around its own in growing shells and stops as soon as the
nearest triangle found is closer than every cell not yet searched, so the
answer is exact, not an approximation.  Points that a few shells do not
settle (far from every triangle) are tested against every triangle, or, for
many points and triangles, answered by Open3D's
``RaycastingScene.compute_distance``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, prange

from o3drbf.mesh.arrays import raycasting_scene

__all__ = ["point_mesh_distance", "SEARCH_SHELLS"]

#: Shells of cells a point searches around its own before Open3D answers it instead.
SEARCH_SHELLS = 8
# The grid's cell is this multiple of the triangles' median bounding-box size (longest side).
_CELL_FACTOR = 2.0
# At most this many grid cells (the cell grows for a mesh of a few large and many tiny triangles).
_MAX_CELLS = 1 << 24
# A triangle whose bounding box covers more cells than this is tested against every point instead.
_MAX_COVERED = 64
# Points the shells leave unsettled are tested against every triangle up to this many pairs, else answered by Open3D.
_BRUTE_PAIRS = 50_000_000


@njit(cache=True, inline="always")
def _dist2_triangle(px, py, pz, verts, t0, t1, t2):
    """Squared distance from p to triangle (t0, t1, t2): Ericson's closest point, by its Voronoi regions
    (Real-Time Collision Detection, 5.1.5); a triangle of no area by its three sides."""
    ax, ay, az = verts[t0, 0], verts[t0, 1], verts[t0, 2]
    abx, aby, abz = verts[t1, 0] - ax, verts[t1, 1] - ay, verts[t1, 2] - az
    acx, acy, acz = verts[t2, 0] - ax, verts[t2, 1] - ay, verts[t2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    if not nx * nx + ny * ny + nz * nz > 0.0:  # no area (collinear or coincident corners): its sides hold its nearest point
        e1 = _dist2_segment(apx, apy, apz, abx, aby, abz)
        e2 = _dist2_segment(apx, apy, apz, acx, acy, acz)
        e3 = _dist2_segment(apx - abx, apy - aby, apz - abz, acx - abx, acy - aby, acz - abz)
        return min(e1, min(e2, e3))
    ab_ac = abx * acx + aby * acy + abz * acz
    d1 = abx * apx + aby * apy + abz * apz  # ab.ap, ac.ap; then the same of bp = ap - ab and cp = ap - ac
    d2 = acx * apx + acy * apy + acz * apz
    d3, d4 = d1 - (abx * abx + aby * aby + abz * abz), d2 - ab_ac
    d5, d6 = d1 - ab_ac, d2 - (acx * acx + acy * acy + acz * acz)
    if d1 <= 0.0 and d2 <= 0.0:  # vertex a
        return apx * apx + apy * apy + apz * apz
    if d3 >= 0.0 and d4 <= d3:  # vertex b
        return (apx - abx) ** 2 + (apy - aby) ** 2 + (apz - abz) ** 2
    if d6 >= 0.0 and d5 <= d6:  # vertex c
        return (apx - acx) ** 2 + (apy - acy) ** 2 + (apz - acz) ** 2
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:  # edge ab
        return _dist2_segment(apx, apy, apz, abx, aby, abz)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:  # edge ac
        return _dist2_segment(apx, apy, apz, acx, acy, acz)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:  # edge bc
        return _dist2_segment(apx - abx, apy - aby, apz - abz, acx - abx, acy - aby, acz - abz)
    denom = va + vb + vc  # |ab x ac|^2 > 0
    v = vb / denom
    w = vc / denom
    qx, qy, qz = apx - v * abx - w * acx, apy - v * aby - w * acy, apz - v * abz - w * acz
    return qx * qx + qy * qy + qz * qz


@njit(cache=True, inline="always")
def _dist2_segment(px, py, pz, dx, dy, dz):
    """Squared distance from p (relative to the segment's start) to the segment of direction d."""
    dd = dx * dx + dy * dy + dz * dz
    t = 0.0
    if dd > 0.0:
        t = min(max((px * dx + py * dy + pz * dz) / dd, 0.0), 1.0)
    qx, qy, qz = px - t * dx, py - t * dy, pz - t * dz
    return qx * qx + qy * qy + qz * qz


@njit(cache=True, inline="always")
def _cell_range(verts, tris, t, a, origin, cell, dims):
    """The cells ``lo..hi`` along axis ``a`` that triangle ``t``'s bounding box covers."""
    x0, x1, x2 = verts[tris[t, 0], a], verts[tris[t, 1], a], verts[tris[t, 2], a]
    lo = min(max(int(math.floor((min(x0, min(x1, x2)) - origin[a]) / cell)), 0), dims[a] - 1)
    hi = min(max(int(math.floor((max(x0, max(x1, x2)) - origin[a]) / cell)), lo), dims[a] - 1)
    return lo, hi


@njit(cache=True)
def _bin_triangles(verts, tris, origin, cell, dims, max_covered):
    """Counting sort of the (cell, triangle) entries of every triangle covering at most ``max_covered``
    cells: ``start`` (cells + 1,), the triangles ``ids`` by cell, and the other triangles ``big``."""
    ncell = dims[0] * dims[1] * dims[2]
    start = np.zeros(ncell + 1, dtype=np.int64)
    small = np.zeros(tris.shape[0], dtype=np.bool_)
    nbig = 0
    for t in range(tris.shape[0]):
        x0, x1 = _cell_range(verts, tris, t, 0, origin, cell, dims)
        y0, y1 = _cell_range(verts, tris, t, 1, origin, cell, dims)
        z0, z1 = _cell_range(verts, tris, t, 2, origin, cell, dims)
        if (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1) > max_covered:
            nbig += 1
            continue
        small[t] = True
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                for z in range(z0, z1 + 1):
                    start[(x * dims[1] + y) * dims[2] + z + 1] += 1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    ids = np.empty(start[ncell], dtype=np.int64)
    big = np.empty(nbig, dtype=np.int64)
    nbig = 0
    for t in range(tris.shape[0]):
        if not small[t]:
            big[nbig] = t
            nbig += 1
            continue
        x0, x1 = _cell_range(verts, tris, t, 0, origin, cell, dims)
        y0, y1 = _cell_range(verts, tris, t, 1, origin, cell, dims)
        z0, z1 = _cell_range(verts, tris, t, 2, origin, cell, dims)
        for x in range(x0, x1 + 1):
            for y in range(y0, y1 + 1):
                for z in range(z0, z1 + 1):
                    c = (x * dims[1] + y) * dims[2] + z
                    ids[fill[c]] = t
                    fill[c] += 1
    return start, ids, big


@njit(cache=True, parallel=True)
def _nearest(points, verts, tris, origin, cell, dims, start, ids, big, shells, out, settled):
    for q in prange(points.shape[0]):
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        best = np.inf
        for b in range(big.shape[0]):
            t = big[b]
            best = min(best, _dist2_triangle(px, py, pz, verts, tris[t, 0], tris[t, 1], tris[t, 2]))
        fx, fy, fz = (px - origin[0]) / cell, (py - origin[1]) / cell, (pz - origin[2]) / cell
        cx, cy, cz = math.floor(fx), math.floor(fy), math.floor(fz)
        done = False
        for k in range(shells + 1):
            for dx in range(-k, k + 1):
                x = cx + dx
                if x < 0 or x >= dims[0]:
                    continue
                for dy in range(-k, k + 1):
                    y = cy + dy
                    if y < 0 or y >= dims[1]:
                        continue
                    edge = abs(dx) == k or abs(dy) == k
                    for dz in range(-k, k + 1):
                        if not edge and abs(dz) != k:  # inside the shell: searched already
                            continue
                        z = cz + dz
                        if z < 0 or z >= dims[2]:
                            continue
                        c = (int(x) * dims[1] + int(y)) * dims[2] + int(z)
                        for e in range(start[c], start[c + 1]):
                            t = ids[e]
                            best = min(best, _dist2_triangle(px, py, pz, verts, tris[t, 0], tris[t, 1], tris[t, 2]))
            # Every point of space nearer p than the searched block's walls lies in a searched cell, and so
            # does some cell of any triangle that reaches there: nothing unsearched is nearer than that.
            reach = min(min(fx - (cx - k), cx + k + 1 - fx), min(min(fy - (cy - k), cy + k + 1 - fy), min(fz - (cz - k), cz + k + 1 - fz)))
            if best <= (reach * cell) ** 2:
                done = True
                break
        out[q] = math.sqrt(best)
        settled[q] = done


@njit(cache=True, parallel=True)
def _every_triangle(points, index, verts, tris, out):
    for i in prange(index.shape[0]):
        q = index[i]
        best = np.inf
        for t in range(tris.shape[0]):
            best = min(best, _dist2_triangle(points[q, 0], points[q, 1], points[q, 2], verts, tris[t, 0], tris[t, 1], tris[t, 2]))
        out[q] = math.sqrt(best)


def point_mesh_distance(points: Any, vertices: Any, triangles: Any) -> np.ndarray:
    """Distance from each point to the nearest point of a triangle mesh (exact, double precision).

    Parameters
    ----------
    points : (N, 3) array_like of float
    vertices : (V, 3) array_like of float
    triangles : (F, 3) array_like of int
        Vertex indices, at least one triangle.

    Returns
    -------
    (N,) ndarray of float
        Unsigned distances, in the units of the points.

    Notes
    -----
    Triangles are binned into a uniform grid whose cell is twice their
    median bounding-box size; a triangle covering more than 64 cells is
    tested against every point.  Each point searches up to
    :data:`SEARCH_SHELLS` shells of cells around its own, stopping once the
    nearest triangle found is nearer than the searched block's walls.  The
    points still unsettled after that (far from the mesh) are tested
    against every triangle, or, when that would take more than 50 million
    tests, answered by Open3D's ``RaycastingScene.compute_distance``
    (single precision).

    Examples
    --------
    >>> import numpy as np
    >>> verts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> point_mesh_distance([[0.2, 0.2, 0.5], [2.0, 0, 0]], verts, [[0, 1, 2]]).round(6).tolist()
    [0.5, 1.0]
    """
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    verts = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64).reshape(-1, 3))
    tris = np.ascontiguousarray(np.asarray(triangles, dtype=np.int64).reshape(-1, 3))
    if not len(tris):
        raise ValueError("the mesh has no triangles: no distance to it")
    if not len(pts):
        return np.zeros(0)
    if not np.isfinite(verts).all():
        raise ValueError("the mesh has NaN or infinite vertex coordinates; remove or fix those vertices first")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise ValueError(f"triangle indices must lie in [0, {len(verts)}); fix the triangles or pass the matching vertices")
    used = verts[np.unique(tris)] if len(verts) > 3 * len(tris) else verts  # (many unused vertices: not in the grid's box)
    origin = used.min(axis=0)
    span = np.maximum(used.max(axis=0) - origin, 1e-300)
    sample = verts[tris[:: max(1, len(tris) // 4096)]]  # (m, 3, 3): the cell sets the speed only
    extent = (sample.max(axis=1) - sample.min(axis=1)).max(axis=1)
    extent = extent[extent > 0]
    cell = _CELL_FACTOR * float(np.median(extent)) if extent.size else float(span.max())
    cell = max(cell, (float(np.prod(span)) / _MAX_CELLS) ** (1 / 3))
    dims = np.maximum(np.ceil(span / cell).astype(np.int64), 1)
    while int(np.prod(dims)) > _MAX_CELLS:  # (flat meshes: the volume's bound above does not hold the count)
        cell *= 1.25
        dims = np.maximum(np.ceil(span / cell).astype(np.int64), 1)
    start, ids, big = _bin_triangles(verts, tris, origin, cell, dims, _MAX_COVERED)
    out = np.empty(len(pts))
    settled = np.zeros(len(pts), dtype=np.bool_)
    _nearest(pts, verts, tris, origin, cell, dims, start, ids, big, SEARCH_SHELLS, out, settled)
    far = np.flatnonzero(~settled)
    if len(far) and len(far) * len(tris) <= _BRUTE_PAIRS:
        _every_triangle(pts, far, verts, tris, out)
    elif len(far):
        import open3d as o3d

        centre = origin + 0.5 * span
        scene = raycasting_scene(verts - centre, tris)
        query = o3d.core.Tensor(np.ascontiguousarray(pts[far] - centre, dtype=np.float32))
        out[far] = scene.compute_distance(query).numpy().astype(float)
    return out
