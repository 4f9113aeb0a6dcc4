"""Self-intersecting triangle pairs and watertightness, as Open3D defines them, fast.

Open3D's ``TriangleMesh.get_self_intersecting_triangles()`` compares every
pair of triangles (``O(F^2)``), which is why :func:`o3drbf.mesh.metrics.mesh_report` could not afford it.  This module
returns exactly the same pairs from a uniform grid over the triangles'
bounding boxes, so the cost grows with ``F`` times the number of triangles
near each triangle.

The definition matched (Open3D ``cpp/open3d/geometry/TriangleMesh.cpp``,
``GetSelfIntersectingTriangles``, and ``IntersectionTest::TriangleTriangle3d``):

1. only pairs ``(i, j)``, ``i < j``, that share **no vertex index** are
   tested (pairs that share a vertex or an edge are never reported, even if
   they overlap elsewhere; two distinct vertices at the same position do
   not count as shared);
2. their axis-aligned bounding boxes must overlap (closed intervals, so
   touching boxes pass);
3. the six corners are centred on their mean and divided, per axis, by
   their standard deviation (``ddof=1``) plus ``1e-12``;
4. Moller's 1997 test without divisions (``NoDivTriTriIsect``, with its
   ``EPSILON = 1e-6`` snapping of plane distances to zero, and its coplanar
   branch in the projection that maximises triangle ``i``'s area) is run on
   ``(triangle i, triangle j)`` in that order.

The arithmetic is ported operation for operation, so the result is the same
bit for bit wherever the compiler does not fuse multiply-adds differently.

:func:`nonmanifold_vertices` is Open3D's ``GetNonManifoldVertices`` (what
``IsVertexManifold`` tests), compiled and in parallel over the vertices.

:func:`is_watertight` is Open3D's ``IsWatertight``:
``IsEdgeManifold(allow_boundary_edges=False) and IsVertexManifold() and not
IsSelfIntersecting()``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit, prange

__all__ = ["self_intersecting_pairs", "nonmanifold_vertices", "is_watertight"]

# Moller's robustness threshold on plane distances (opttritri.h, EPSILON).
_EPSILON = 1e-6
# A triangle whose bounding box covers more grid cells than this is tested
# against every triangle instead of being put in the grid.
_MAX_CELLS = 64
# Grid cells per axis are capped so that the linear cell key fits in int64.
_MAX_DIM = 1 << 20
# The entries are sorted by cell with a counting sort where the grid has at most this many cells an entry.
_COUNTING_SORT_CELLS = 16


# --------------------------------------------------------------------------
# Moller (1997) triangle-triangle test, "NoDivTriTriIsect", as in Open3D's
# 3rdparty/tomasakeninemoeller/opttritri.h, on scalars.


@njit(cache=True)
def _edge_edge(ax, ay, v0x, v0y, u0x, u0y, u1x, u1y):
    """EDGE_EDGE_TEST: 1 if edge (V0, V0 + A) crosses edge (U0, U1) in 2-D."""
    bx = u0x - u1x
    by = u0y - u1y
    cx = v0x - u0x
    cy = v0y - u0y
    f = ay * bx - ax * by
    d = by * cx - bx * cy
    if (f > 0 and d >= 0 and d <= f) or (f < 0 and d <= 0 and d >= f):
        e = ax * cy - ay * cx
        if f > 0:
            if e >= 0 and e <= f:
                return True
        else:
            if e <= 0 and e >= f:
                return True
    return False


@njit(cache=True)
def _edge_against_tri(v0x, v0y, v1x, v1y, u0x, u0y, u1x, u1y, u2x, u2y):
    """EDGE_AGAINST_TRI_EDGES."""
    ax = v1x - v0x
    ay = v1y - v0y
    if _edge_edge(ax, ay, v0x, v0y, u0x, u0y, u1x, u1y):
        return True
    if _edge_edge(ax, ay, v0x, v0y, u1x, u1y, u2x, u2y):
        return True
    if _edge_edge(ax, ay, v0x, v0y, u2x, u2y, u0x, u0y):
        return True
    return False


@njit(cache=True)
def _point_in_tri(v0x, v0y, u0x, u0y, u1x, u1y, u2x, u2y):
    """POINT_IN_TRI (strict on all three sides)."""
    a = u1y - u0y
    b = -(u1x - u0x)
    c = -a * u0x - b * u0y
    d0 = a * v0x + b * v0y + c
    a = u2y - u1y
    b = -(u2x - u1x)
    c = -a * u1x - b * u1y
    d1 = a * v0x + b * v0y + c
    a = u0y - u2y
    b = -(u0x - u2x)
    c = -a * u2x - b * u2y
    d2 = a * v0x + b * v0y + c
    if d0 * d1 > 0.0:
        if d0 * d2 > 0.0:
            return True
    return False


@njit(cache=True)
def _coplanar(n, v, u):
    """coplanar_tri_tri: ``n`` (3,) normal of triangle ``v``; ``v``, ``u`` (3, 3)."""
    a0, a1, a2 = abs(n[0]), abs(n[1]), abs(n[2])
    if a0 > a1:
        if a0 > a2:
            i0, i1 = 1, 2
        else:
            i0, i1 = 0, 1
    else:
        if a2 > a1:
            i0, i1 = 0, 1
        else:
            i0, i1 = 0, 2
    v0x, v0y = v[0, i0], v[0, i1]
    v1x, v1y = v[1, i0], v[1, i1]
    v2x, v2y = v[2, i0], v[2, i1]
    u0x, u0y = u[0, i0], u[0, i1]
    u1x, u1y = u[1, i0], u[1, i1]
    u2x, u2y = u[2, i0], u[2, i1]
    if _edge_against_tri(v0x, v0y, v1x, v1y, u0x, u0y, u1x, u1y, u2x, u2y):
        return True
    if _edge_against_tri(v1x, v1y, v2x, v2y, u0x, u0y, u1x, u1y, u2x, u2y):
        return True
    if _edge_against_tri(v2x, v2y, v0x, v0y, u0x, u0y, u1x, u1y, u2x, u2y):
        return True
    if _point_in_tri(v0x, v0y, u0x, u0y, u1x, u1y, u2x, u2y):
        return True
    if _point_in_tri(u0x, u0y, v0x, v0y, v1x, v1y, v2x, v2y):
        return True
    return False


@njit(cache=True)
def _interval(vv0, vv1, vv2, d0, d1, d2, d0d1, d0d2):
    """NEWCOMPUTE_INTERVALS: (status, A, B, C, X0, X1); status 1 = coplanar."""
    if d0d1 > 0.0:
        return 0, vv2, (vv0 - vv2) * d2, (vv1 - vv2) * d2, d2 - d0, d2 - d1
    if d0d2 > 0.0:
        return 0, vv1, (vv0 - vv1) * d1, (vv2 - vv1) * d1, d1 - d0, d1 - d2
    if d1 * d2 > 0.0 or d0 != 0.0:
        return 0, vv0, (vv1 - vv0) * d0, (vv2 - vv0) * d0, d0 - d1, d0 - d2
    if d1 != 0.0:
        return 0, vv1, (vv0 - vv1) * d1, (vv2 - vv1) * d1, d1 - d0, d1 - d2
    if d2 != 0.0:
        return 0, vv2, (vv0 - vv2) * d2, (vv1 - vv2) * d2, d2 - d0, d2 - d1
    return 1, 0.0, 0.0, 0.0, 0.0, 0.0


@njit(cache=True)
def _moller(v, u):
    """NoDivTriTriIsect on triangles ``v``, ``u`` (3, 3): True if they intersect."""
    # plane of v: N1.X + d1 = 0
    e1x, e1y, e1z = v[1, 0] - v[0, 0], v[1, 1] - v[0, 1], v[1, 2] - v[0, 2]
    e2x, e2y, e2z = v[2, 0] - v[0, 0], v[2, 1] - v[0, 1], v[2, 2] - v[0, 2]
    n1x = e1y * e2z - e1z * e2y
    n1y = e1z * e2x - e1x * e2z
    n1z = e1x * e2y - e1y * e2x
    d1 = -(n1x * v[0, 0] + n1y * v[0, 1] + n1z * v[0, 2])
    du0 = (n1x * u[0, 0] + n1y * u[0, 1] + n1z * u[0, 2]) + d1
    du1 = (n1x * u[1, 0] + n1y * u[1, 1] + n1z * u[1, 2]) + d1
    du2 = (n1x * u[2, 0] + n1y * u[2, 1] + n1z * u[2, 2]) + d1
    if abs(du0) < _EPSILON:
        du0 = 0.0
    if abs(du1) < _EPSILON:
        du1 = 0.0
    if abs(du2) < _EPSILON:
        du2 = 0.0
    du0du1 = du0 * du1
    du0du2 = du0 * du2
    if du0du1 > 0.0 and du0du2 > 0.0:
        return False

    # plane of u: N2.X + d2 = 0
    e1x, e1y, e1z = u[1, 0] - u[0, 0], u[1, 1] - u[0, 1], u[1, 2] - u[0, 2]
    e2x, e2y, e2z = u[2, 0] - u[0, 0], u[2, 1] - u[0, 1], u[2, 2] - u[0, 2]
    n2x = e1y * e2z - e1z * e2y
    n2y = e1z * e2x - e1x * e2z
    n2z = e1x * e2y - e1y * e2x
    d2 = -(n2x * u[0, 0] + n2y * u[0, 1] + n2z * u[0, 2])
    dv0 = (n2x * v[0, 0] + n2y * v[0, 1] + n2z * v[0, 2]) + d2
    dv1 = (n2x * v[1, 0] + n2y * v[1, 1] + n2z * v[1, 2]) + d2
    dv2 = (n2x * v[2, 0] + n2y * v[2, 1] + n2z * v[2, 2]) + d2
    if abs(dv0) < _EPSILON:
        dv0 = 0.0
    if abs(dv1) < _EPSILON:
        dv1 = 0.0
    if abs(dv2) < _EPSILON:
        dv2 = 0.0
    dv0dv1 = dv0 * dv1
    dv0dv2 = dv0 * dv2
    if dv0dv1 > 0.0 and dv0dv2 > 0.0:
        return False

    # direction of the intersection line, and its largest component
    dx = n1y * n2z - n1z * n2y
    dy = n1z * n2x - n1x * n2z
    dz = n1x * n2y - n1y * n2x
    mx = abs(dx)
    index = 0
    bb = abs(dy)
    cc = abs(dz)
    if bb > mx:
        mx = bb
        index = 1
    if cc > mx:
        mx = cc
        index = 2
    vp0, vp1, vp2 = v[0, index], v[1, index], v[2, index]
    up0, up1, up2 = u[0, index], u[1, index], u[2, index]

    s, a, b, c, x0, x1 = _interval(vp0, vp1, vp2, dv0, dv1, dv2, dv0dv1, dv0dv2)
    if s == 1:
        return _coplanar(np.array((n1x, n1y, n1z)), v, u)
    s, d, e, f, y0, y1 = _interval(up0, up1, up2, du0, du1, du2, du0du1, du0du2)
    if s == 1:
        return _coplanar(np.array((n1x, n1y, n1z)), v, u)

    xx = x0 * x1
    yy = y0 * y1
    xxyy = xx * yy
    tmp = a * xxyy
    i10 = tmp + b * x1 * yy
    i11 = tmp + c * x0 * yy
    tmp = d * xxyy
    i20 = tmp + e * xx * y1
    i21 = tmp + f * xx * y0
    if i10 > i11:
        i10, i11 = i11, i10
    if i20 > i21:
        i20, i21 = i21, i20
    if i11 < i20 or i21 < i10:
        return False
    return True


@njit(cache=True)
def _triangle_triangle(verts, ti, tj, work):
    """Open3D's ``IntersectionTest::TriangleTriangle3d`` on triangles ``ti``, ``tj`` (3,).

    ``work`` is a scratch ``(2, 3, 3)`` array.
    """
    for ax in range(3):
        x0, x1, x2 = verts[ti[0], ax], verts[ti[1], ax], verts[ti[2], ax]
        x3, x4, x5 = verts[tj[0], ax], verts[tj[1], ax], verts[tj[2], ax]
        mu = (x0 + x1 + x2 + x3 + x4 + x5) / 6
        r0, r1, r2, r3, r4, r5 = x0 - mu, x1 - mu, x2 - mu, x3 - mu, x4 - mu, x5 - mu
        sigma = np.sqrt((r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3 + r4 * r4 + r5 * r5) / 5) + 1e-12
        work[0, 0, ax] = r0 / sigma
        work[0, 1, ax] = r1 / sigma
        work[0, 2, ax] = r2 / sigma
        work[1, 0, ax] = r3 / sigma
        work[1, 1, ax] = r4 / sigma
        work[1, 2, ax] = r5 / sigma
    return _moller(work[0], work[1])


# --------------------------------------------------------------------------
# pair search


@njit(cache=True)
def _shares_vertex(tris, i, j):
    for a in range(3):
        for b in range(3):
            if tris[i, a] == tris[j, b]:
                return True
    return False


@njit(cache=True)
def _boxes_overlap(bmin, bmax, i, j):
    for ax in range(3):
        if bmax[i, ax] < bmin[j, ax] or bmin[i, ax] > bmax[j, ax]:
            return False
    return True


@njit(cache=True)
def _test_pair(verts, tris, bmin, bmax, i, j, work):
    """Open3D's test of triangles ``i < j``: no shared vertex, boxes overlap, Moller."""
    if _shares_vertex(tris, i, j):
        return False
    if not _boxes_overlap(bmin, bmax, i, j):
        return False
    return _triangle_triangle(verts, tris[i], tris[j], work)


@njit(cache=True)
def _triangle_boxes(verts, tris):
    """Each triangle's bounding box ``(F, 3)`` twice, its longest side ``(F,)``, and the lowest and the
    highest corner of all the boxes ``(3,)``."""
    nf = tris.shape[0]
    bmin = np.empty((nf, 3))
    bmax = np.empty((nf, 3))
    extent = np.empty(nf)
    origin = np.full(3, np.inf)
    top = np.full(3, -np.inf)
    for f in range(nf):
        e = 0.0
        for ax in range(3):
            a, b, c = verts[tris[f, 0], ax], verts[tris[f, 1], ax], verts[tris[f, 2], ax]
            low, high = min(min(a, b), c), max(max(a, b), c)
            bmin[f, ax] = low
            bmax[f, ax] = high
            e = max(e, high - low)
            origin[ax] = min(origin[ax], low)
            top[ax] = max(top[ax], high)
        extent[f] = e
    return bmin, bmax, extent, origin, top


@njit(cache=True)
def _box_cells(bmin, bmax, origin, cell, max_dim, max_cells):
    """The grid cells of each box's lower and upper corner ``(F, 3)`` (within ``max_dim`` an axis), whether
    it covers at most ``max_cells`` cells, and the grid's cells an axis ``(3,)``."""
    nf = bmin.shape[0]
    lo = np.empty((nf, 3), np.int64)
    hi = np.empty((nf, 3), np.int64)
    small = np.empty(nf, np.bool_)
    dims = np.ones(3, np.int64)
    for f in range(nf):
        covered = 1
        for ax in range(3):
            a = min(max(np.int64(math.floor((bmin[f, ax] - origin[ax]) / cell)), 0), max_dim - 1)
            b = min(max(np.int64(math.floor((bmax[f, ax] - origin[ax]) / cell)), a), max_dim - 1)
            lo[f, ax] = a
            hi[f, ax] = b
            dims[ax] = max(dims[ax], b + 1)
            covered *= b - a + 1
        small[f] = covered <= max_cells
    return lo, hi, small, dims


@njit(cache=True)
def _by_cell(keys, ids, n_cells):
    """``keys`` and ``ids`` in increasing order of key, entries of one key in their order (a counting sort
    over the ``n_cells`` keys)."""
    start = np.zeros(n_cells + 1, np.int64)
    for k in keys:
        start[k + 1] += 1
    for c in range(n_cells):
        start[c + 1] += start[c]
    out_keys = np.empty_like(keys)
    out_ids = np.empty_like(ids)
    for e in range(keys.shape[0]):
        p = start[keys[e]]
        out_keys[p] = keys[e]
        out_ids[p] = ids[e]
        start[keys[e]] = p + 1
    return out_keys, out_ids


@njit(cache=True)
def _grid_entries(lo, hi, small, dims):
    """Cell keys and triangle ids ``(E,)`` of every (small triangle, cell) it covers."""
    n = 0
    for t in range(lo.shape[0]):
        if small[t]:
            n += (hi[t, 0] - lo[t, 0] + 1) * (hi[t, 1] - lo[t, 1] + 1) * (hi[t, 2] - lo[t, 2] + 1)
    keys = np.empty(n, dtype=np.int64)
    ids = np.empty(n, dtype=np.int64)
    m = 0
    for t in range(lo.shape[0]):
        if not small[t]:
            continue
        for x in range(lo[t, 0], hi[t, 0] + 1):
            for y in range(lo[t, 1], hi[t, 1] + 1):
                for z in range(lo[t, 2], hi[t, 2] + 1):
                    keys[m] = (x * dims[1] + y) * dims[2] + z
                    ids[m] = t
                    m += 1
    return keys, ids


@njit(cache=True, parallel=True)
def _pairs_in_cells(verts, tris, bmin, bmax, lo, dims, keys, ids, bounds, out, counts):
    """:func:`_pairs_in_range` over the chunks ``bounds[c] <= entry < bounds[c + 1]`` (whole cells) in
    parallel, chunk ``c`` writing into ``out[c]`` and its count into ``counts[c]``."""
    for c in prange(bounds.shape[0] - 1):
        counts[c] = _pairs_in_range(verts, tris, bmin, bmax, lo, dims, keys, ids, bounds[c], bounds[c + 1], out[c])


@njit(cache=True)
def _pairs_in_range(verts, tris, bmin, bmax, lo, dims, keys, ids, begin, total, out):
    """Pairs from each cell of the entries ``begin <= entry < total``, each reported once: in the cell
    holding the lower corner of the intersection of the two boxes.

    Writes the first ``len(out)`` pairs into ``out`` ``(M, 2)`` and returns
    how many there are in all.
    """
    n = 0
    work = np.empty((2, 3, 3))
    start = begin
    while start < total:
        stop = start + 1
        while stop < total and keys[stop] == keys[start]:
            stop += 1
        key = keys[start]
        for a in range(start, stop):
            for b in range(a + 1, stop):
                i, j = ids[a], ids[b]
                if i > j:
                    i, j = j, i
                ref = (max(lo[i, 0], lo[j, 0]) * dims[1] + max(lo[i, 1], lo[j, 1])) * dims[2] + max(lo[i, 2], lo[j, 2])
                if ref != key:
                    continue
                if _test_pair(verts, tris, bmin, bmax, i, j, work):
                    if n < out.shape[0]:
                        out[n, 0] = i
                        out[n, 1] = j
                    n += 1
        start = stop
    return n


@njit(cache=True)
def _pairs_of_big(verts, tris, bmin, bmax, big_ids, small, out):
    """Pairs with at least one triangle too large for the grid, by brute
    force; written to ``out`` as in :func:`_pairs_in_range`."""
    n = 0
    work = np.empty((2, 3, 3))
    nf = tris.shape[0]
    for t in range(big_ids.shape[0]):
        g = big_ids[t]
        for j in range(nf):
            if j == g or (not small[j] and j < g):
                continue
            i0, j0 = (g, j) if g < j else (j, g)
            if _test_pair(verts, tris, bmin, bmax, i0, j0, work):
                if n < out.shape[0]:
                    out[n, 0] = i0
                    out[n, 1] = j0
                n += 1
    return n


def _check_arrays(vertices: Any, triangles: Any) -> tuple[np.ndarray, np.ndarray]:
    verts = np.ascontiguousarray(np.asarray(vertices, dtype=np.float64))
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"vertices must be a (V, 3) array, got shape {verts.shape}; pass np.asarray(mesh.vertices)")
    if not np.isfinite(verts).all():
        raise ValueError("vertices hold NaN or infinite coordinates; remove or fix those vertices first")
    tris = np.asarray(triangles)
    if tris.size == 0:
        return verts, np.empty((0, 3), dtype=np.int64)
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise ValueError(f"triangles must be a (F, 3) integer array, got shape {tris.shape}; pass np.asarray(mesh.triangles)")
    if not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"triangles must hold integer vertex indices, got dtype {tris.dtype}")
    tris = np.ascontiguousarray(tris, dtype=np.int64)
    if tris.min() < 0 or tris.max() >= verts.shape[0]:
        raise ValueError(
            f"triangle indices must lie in [0, {verts.shape[0]}), got min {int(tris.min())}, max {int(tris.max())}; "
            "fix the triangles or pass the matching vertices"
        )
    return verts, tris


def self_intersecting_pairs(vertices: Any, triangles: Any) -> np.ndarray:
    """Pairs of triangles that intersect, exactly as Open3D's
    ``TriangleMesh.get_self_intersecting_triangles()`` returns them.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        Vertex positions (finite).
    triangles : (F, 3) array_like of int
        Vertex indices of each triangle, in ``[0, V)``.

    Returns
    -------
    (K, 2) ndarray of int64
        Triangle index pairs ``(i, j)`` with ``i < j``, sorted by ``i`` then
        ``j`` (Open3D returns the same set in an unspecified order).  Pairs
        of triangles that share a vertex index are never included.

    Raises
    ------
    ValueError
        If ``vertices`` is not ``(V, 3)`` or holds NaN/inf, or ``triangles``
        is not ``(F, 3)`` integers in ``[0, V)``.

    Notes
    -----
    See the module docstring for the definition.  Candidates come from a
    uniform grid whose cell is 1.5 times the median bounding-box size of the
    triangles (longest side, over triangles not collapsed to a point); a
    pair is tested only in the cell holding the lower corner of the
    intersection of the two boxes, so it is tested once.  Triangles
    covering more than 64 cells are tested against all triangles.  Time is
    about linear in ``F`` for meshes of roughly uniform triangles (a
    marching-cubes mesh), quadratic in the worst case (many large overlapping
    triangles).
    """
    verts, tris = _check_arrays(vertices, triangles)
    if tris.shape[0] < 2:
        return np.empty((0, 2), dtype=np.int64)
    bmin, bmax, extent, origin, top = _triangle_boxes(verts, tris)
    span = float((top - origin).max())
    extent = extent[extent > 0]  # triangles collapsed to a point say nothing of the size
    cell = 1.5 * float(np.median(extent)) if extent.size else span
    cell = max(cell, span / (_MAX_DIM - 2), np.finfo(float).tiny)
    lo, hi, small, dims = _box_cells(bmin, bmax, origin, cell, _MAX_DIM, _MAX_CELLS)
    keys, ids = _grid_entries(lo, hi, small, dims)
    n_cells = int(dims[0]) * int(dims[1]) * int(dims[2])
    if n_cells <= _COUNTING_SORT_CELLS * max(len(keys), 1024):
        keys, ids = _by_cell(keys, ids, n_cells)
    else:  # a grid much larger than its entries: a comparison sort
        order = np.argsort(keys, kind="stable")
        keys, ids = keys[order], ids[order]
    big_ids = np.flatnonzero(~small).astype(np.int64)
    # Chunks of whole cells (each starts where a cell's entries start), tested in parallel.
    total = len(keys)
    chunks = min(64, max(1, total // 4096))
    bounds = np.unique(np.r_[0, np.searchsorted(keys, keys[np.linspace(0, total, chunks + 1)[1:-1].astype(np.int64)]), total])
    pairs = []
    cap = max(256, tris.shape[0] // (8 * chunks))
    for _ in range(2):  # a second pass only if a chunk's buffer was too small
        out = np.empty((len(bounds) - 1, cap, 2), dtype=np.int64)
        counts = np.zeros(len(bounds) - 1, np.int64)
        _pairs_in_cells(verts, tris, bmin, bmax, lo, dims, keys, ids, bounds.astype(np.int64), out, counts)
        if counts.max(initial=0) <= cap:
            break
        cap = int(counts.max())
    pairs += [out[c, :counts[c]] for c in range(len(counts))]
    if big_ids.size:
        out = np.empty((max(1024, tris.shape[0] // 8), 2), dtype=np.int64)
        for _ in range(2):
            n = _pairs_of_big(verts, tris, bmin, bmax, big_ids, small, out)
            if n <= out.shape[0]:
                break
            out = np.empty((n, 2), dtype=np.int64)
        pairs.append(out[:n])
    out = np.concatenate(pairs, axis=0) if pairs else np.empty((0, 2), dtype=np.int64)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


@njit(cache=True, parallel=True)
def _nonmanifold(tris, start, incident, width, out):
    n = len(start) - 1
    chunks = min(n, 256)
    for c in prange(chunks):
        ea = np.empty(width, np.int64)  # work arrays once a chunk of vertices, not once a vertex
        eb = np.empty(width, np.int64)
        ids = np.empty(2 * width, np.int64)
        parent = np.empty(2 * width, np.int64)
        for v in range(c * n // chunks, (c + 1) * n // chunks):
            # The link of v: the edge opposite v in each incident triangle (Open3D's three cases, in its order).
            m = 0
            for i in range(start[v], start[v + 1]):
                t0, t1, t2 = tris[incident[i], 0], tris[incident[i], 1], tris[incident[i], 2]
                if t0 != v and t1 != v:
                    ea[m] = t0; eb[m] = t1; m += 1
                elif t0 != v and t2 != v:
                    ea[m] = t0; eb[m] = t2; m += 1
                elif t1 != v and t2 != v:
                    ea[m] = t1; eb[m] = t2; m += 1
            if m == 0:
                continue
            # Union-find over the link's vertices (a few: linear searches): manifold iff one piece.
            k = 0
            pieces = 0
            for e in range(m):
                a = -1
                b = -1
                for q in range(k):
                    if ids[q] == ea[e]:
                        a = q
                    if ids[q] == eb[e]:
                        b = q
                if a < 0:
                    ids[k] = ea[e]; parent[k] = k; a = k; k += 1; pieces += 1
                if b < 0:
                    ids[k] = eb[e]; parent[k] = k; b = k; k += 1; pieces += 1
                while parent[a] != a:
                    a = parent[a]
                while parent[b] != b:
                    b = parent[b]
                if a != b:
                    parent[max(a, b)] = min(a, b)
                    pieces -= 1
            out[v] = pieces > 1


@njit(cache=True)
def _incident_triangles(flat, start):
    """The triangle of each corner, grouped by vertex (vertex ``v``'s from ``start[v]``), in triangle order."""
    fill = start[:-1].copy()
    out = np.empty(flat.shape[0], np.int64)
    for c in range(flat.shape[0]):
        out[fill[flat[c]]] = c // 3
        fill[flat[c]] += 1
    return out


def nonmanifold_vertices(triangles, n_vertices: int) -> np.ndarray:
    """Indices of the vertices around which the triangles do not form one fan, as Open3D's
    ``TriangleMesh.get_non_manifold_vertices()`` (so ``is_vertex_manifold()`` is this being empty).

    A vertex is manifold when the edges opposite it in its triangles (its
    link) form one connected piece; vertices in no triangle, and triangles
    that repeat a vertex index, are skipped as Open3D skips them.

    Parameters
    ----------
    triangles : (F, 3) int array_like
    n_vertices : int
        Vertex count (indices are below it).

    Returns
    -------
    (K,) int64 array, ascending

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.mesh.intersections import nonmanifold_vertices
    >>> bowtie = np.array([[0, 1, 2], [0, 3, 4]])  # two triangles meeting at vertex 0 only
    >>> nonmanifold_vertices(bowtie, 5).tolist()
    [0]
    """
    tris = np.ascontiguousarray(np.asarray(triangles, dtype=np.int64).reshape(-1, 3))
    n = int(n_vertices)
    if len(tris) and (tris.min() < 0 or tris.max() >= n):
        raise ValueError(f"triangle indices must lie in [0, {n}), got [{tris.min()}, {tris.max()}]")
    flat = tris.ravel()
    start = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(flat, minlength=n), out=start[1:])
    incident = _incident_triangles(flat, start)  # each vertex's triangles, in triangle order
    out = np.zeros(n, np.bool_)
    if n:
        _nonmanifold(tris, start, incident, max(int(np.diff(start).max()), 1), out)
    return np.flatnonzero(out)


def is_watertight(mesh: Any) -> bool:
    """Open3D's ``TriangleMesh.is_watertight()``, with the fast pair search.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
        A legacy Open3D mesh.

    Returns
    -------
    bool
        ``mesh.is_edge_manifold(allow_boundary_edges=False)`` (every edge used
        by exactly two triangles: edge-manifold and closed) and
        ``mesh.is_vertex_manifold()`` (:func:`nonmanifold_vertices`) and no
        self-intersecting pair (:func:`self_intersecting_pairs`).  Like Open3D, an empty mesh counts
        as watertight.

    Raises
    ------
    ValueError
        If ``mesh`` is not a legacy ``TriangleMesh``, or its vertices or
        triangles are invalid (as :func:`self_intersecting_pairs`).
    """
    if isinstance(mesh, np.ndarray) or not all(
        hasattr(mesh, name) for name in ("vertices", "triangles", "is_edge_manifold", "is_vertex_manifold")
    ):
        kind = f"{type(mesh).__module__}.{type(mesh).__qualname__}"
        raise ValueError(f"mesh must be an open3d.geometry.TriangleMesh (legacy), got {kind}; convert with .to_legacy()")
    if not mesh.is_edge_manifold(allow_boundary_edges=False):
        return False
    verts = np.asarray(mesh.vertices).reshape(-1, 3)
    tris = np.asarray(mesh.triangles).reshape(-1, 3)
    if len(nonmanifold_vertices(tris, len(verts))):
        return False
    return self_intersecting_pairs(verts, tris).shape[0] == 0
