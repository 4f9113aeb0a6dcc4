"""Quality measures for reconstructed surfaces (method.md, section 6).

Small pure functions over ``(N, 3)`` point arrays and Open3D legacy
``TriangleMesh`` objects:

- :func:`fitness_error` -- distance from the input points to the surface;
- :func:`mean_curvature`, :func:`average_curvature` -- the paper's measure of
  detail (high) versus blobbiness (low);
- :func:`chamfer`, :func:`f_score`, :func:`normal_consistency` -- comparison
  of two surfaces (or point sets);
- :func:`mesh_report` -- counts, topology (manifoldness, Euler
  characteristic, genus, components), area and volume.

The fitness error and :func:`point_distances` are exact, in double precision
(:mod:`o3drbf.mesh.nearest`).  The comparisons' point-to-mesh distances use
Open3D's ``RaycastingScene``, which works in float32; coordinates are shifted
to the mesh's bounding-box centre first so that the absolute error stays near
``1e-7`` times the mesh size, wherever the mesh sits.  Mesh sampling is done
here, in NumPy, so that a ``seed`` fixes it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from o3drbf.mesh.arrays import MeshArrays, mesh_arrays, raycasting_scene, triangle_components, unique_edges
from o3drbf.mesh.intersections import nonmanifold_vertices, self_intersecting_pairs
from o3drbf.mesh.nearest import point_mesh_distance
from o3drbf.validation import as_points, check_number

__all__ = [
    "fitness_error",
    "point_distances",
    "mean_curvature",
    "average_curvature",
    "chamfer",
    "f_score",
    "normal_consistency",
    "mesh_report",
    "drop_specks",
]

# A triangle whose doubled area is below this fraction of its longest edge
# squared is treated as degenerate: it adds no area and no cotangent weight.
_DEGENERATE = 1e-12


# --------------------------------------------------------------------------
# input checks and shared helpers


def _is_mesh(obj: Any) -> bool:
    return hasattr(obj, "triangles") and hasattr(obj, "vertices") and not isinstance(obj, np.ndarray)


def _triangle_frames(verts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cross products ``(F, 3)`` (twice the area times the unit normal) and areas ``(F,)``."""
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    cross = np.cross(b - a, c - a)
    return cross, 0.5 * np.linalg.norm(cross, axis=1)


class _Surface:
    """A mesh prepared for distance queries (float32 ``RaycastingScene``,
    coordinates shifted by ``origin``)."""

    def __init__(self, verts: np.ndarray, tris: np.ndarray):
        import open3d as o3d

        self.verts, self.tris = verts, tris
        self.origin = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        self._o3c = o3d.core
        self.scene = raycasting_scene(verts - self.origin, tris)

    def _query(self, points: np.ndarray):
        return self._o3c.Tensor(np.ascontiguousarray(points - self.origin, dtype=np.float32))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance ``(N,)`` from each point to the surface."""
        return self.scene.compute_distance(self._query(points)).numpy().astype(float)

    def closest_triangle(self, points: np.ndarray) -> np.ndarray:
        """Index ``(N,)`` of the triangle holding the closest surface point."""
        out = self.scene.compute_closest_points(self._query(points))
        return out["primitive_ids"].numpy().astype(np.int64)


def _sample_surface(verts: np.ndarray, tris: np.ndarray, n: int, rng: np.random.Generator, name: str):
    """``n`` points ``(n, 3)`` uniform by area, and the triangle of each ``(n,)``."""
    _, area = _triangle_frames(verts, tris)
    total = area.sum()
    if not total > 0:
        raise ValueError(f"{name} has zero surface area; cannot sample points on it")
    cdf = np.cumsum(area)
    face = np.minimum(np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right"), len(tris) - 1)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = verts[tris[face, 0]], verts[tris[face, 1]], verts[tris[face, 2]]
    return a + u[:, None] * (b - a) + v[:, None] * (c - a), face


class _Shape:
    """One side of a comparison: either a mesh (sampled, queried exactly) or
    a point set (used as is, queried through a KD-tree)."""

    def __init__(self, obj: Any, name: str, n_samples: int, rng: np.random.Generator):
        if _is_mesh(obj):
            verts, tris = mesh_arrays(obj, name)
            self.samples, _ = _sample_surface(verts, tris, n_samples, rng, name)
            self.surface: _Surface | None = _Surface(verts, tris)
            self.tree = None
        else:
            self.samples = as_points(obj, name=name)
            self.surface = None
            self.tree = cKDTree(self.samples)

    def distance(self, points: np.ndarray) -> np.ndarray:
        if self.surface is not None:
            return self.surface.distance(points)
        return self.tree.query(points, k=1)[0]


def _directed(a: Any, b: Any, n_samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances from the samples of ``a`` to ``b`` and from those of ``b`` to ``a``."""
    n_samples = check_number("n_samples", n_samples, low=1, integer=True)
    seed = check_number("seed", seed, low=0, integer=True)
    rng = np.random.default_rng(seed)
    sa = _Shape(a, "a", n_samples, rng)
    sb = _Shape(b, "b", n_samples, rng)
    return sb.distance(sa.samples), sa.distance(sb.samples)


# --------------------------------------------------------------------------
# fitness


def fitness_error(points: Any, mesh: Any) -> dict[str, float]:
    """Distance from the input points to a reconstructed surface.

    Parameters
    ----------
    points : (N, 3) array_like or open3d.geometry.PointCloud
        The input (e.g. surface-constraint) points.
    mesh : open3d.geometry.TriangleMesh, MeshArrays or (vertices, triangles)
        The reconstructed surface.

    Returns
    -------
    dict
        ``mean``, ``rms`` and ``max`` of the unsigned point-to-triangle
        distance, in the units of the points.

    Raises
    ------
    ValueError
        If ``points`` is not ``(N, 3)``, is empty or holds NaN/inf, or
        ``mesh`` is empty, has no triangles or has non-finite vertices.

    Notes
    -----
    Distances come from :func:`o3drbf.mesh.nearest.point_mesh_distance`
    (exact, double precision).
    """
    pts = as_points(points, name="points")
    verts, tris = mesh_arrays(mesh)
    d = point_mesh_distance(pts, verts, tris)
    return {"mean": float(d.mean()), "rms": float(np.sqrt(np.mean(d * d))), "max": float(d.max())}


def point_distances(points: Any, mesh: Any) -> np.ndarray:
    """Unsigned distance from each point to a mesh (exact point-to-triangle).

    Parameters
    ----------
    points : (N, 3) array_like
        E.g. the vertices of a reconstruction, to colour it by its distance
        to a reference.
    mesh : open3d.geometry.TriangleMesh

    Returns
    -------
    (N,) ndarray of float
        In the units of the points (:func:`o3drbf.mesh.nearest.point_mesh_distance`,
        as :func:`fitness_error`).

    Raises
    ------
    ValueError
        Bad points, or a mesh that is empty, has no triangles or has
        non-finite vertices.
    """
    pts = as_points(points, name="points")
    verts, tris = mesh_arrays(mesh)
    return point_mesh_distance(pts, verts, tris)


# --------------------------------------------------------------------------
# curvature


def _cotangent_laplacian(verts: np.ndarray, tris: np.ndarray) -> tuple[sparse.csr_matrix, np.ndarray]:
    """Cotangent Laplacian ``L`` ``(V, V)`` and mixed (Voronoi) vertex areas ``(V,)``.

    ``(L @ x)_i = sum_j (cot a_ij + cot b_ij) / 2 * (x_j - x_i)``, so the
    mean-curvature normal is ``K_i = (L @ x)_i / A_i`` (Meyer et al. 2002, eq. 8).
    """
    nv = verts.shape[0]
    p = verts[tris]  # (F, 3 corners, 3)
    # For corner k: the two edges leaving it, to corners k+1 and k+2.
    e1 = np.roll(p, -1, axis=1) - p
    e2 = np.roll(p, -2, axis=1) - p
    dots = np.einsum("fkd,fkd->fk", e1, e2)
    cross = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)  # 2 * area
    sq = np.einsum("fkd,fkd->fk", e1, e1)  # |edge from k to k+1|^2
    ok = cross > _DEGENERATE * sq.max(axis=1)
    cot = np.zeros_like(dots)
    cot[ok] = dots[ok] / cross[ok, None]

    # Off-diagonal weights: the side opposite corner k joins corners k+1, k+2.
    i = np.roll(tris, -1, axis=1).ravel()
    j = np.roll(tris, -2, axis=1).ravel()
    w = 0.5 * cot.ravel()
    off = sparse.coo_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(nv, nv))
    off = off.tocsr()
    lap = off - sparse.diags(np.asarray(off.sum(axis=1)).ravel())

    # Mixed area (Meyer et al. 2002, fig. 4).
    area = 0.5 * cross
    # Voronoi share of corner k: (|e1|^2 cot(k+2) + |e2|^2 cot(k+1)) / 8,
    # e1 (k -> k+1) is opposite corner k+2, e2 (k -> k+2) opposite k+1.
    sq2 = np.einsum("fkd,fkd->fk", e2, e2)
    voronoi = (sq * np.roll(cot, -2, axis=1) + sq2 * np.roll(cot, -1, axis=1)) / 8.0
    obtuse = dots < 0  # angle at corner k is obtuse
    any_obtuse = obtuse.any(axis=1)
    share = np.where(any_obtuse[:, None], np.where(obtuse, area[:, None] / 2, area[:, None] / 4), voronoi)
    share[~ok] = 0.0
    mixed = np.bincount(tris.ravel(), weights=share.ravel(), minlength=nv)
    return lap.tocsr(), mixed


def mean_curvature(mesh: Any) -> np.ndarray:
    """Discrete mean-curvature magnitude ``|H| = |k1 + k2| / 2`` at each vertex.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh

    Returns
    -------
    (V,) ndarray
        ``|H|`` per vertex, in inverse length units (``1/R`` on a sphere of
        radius ``R``).  NaN where it is undefined: boundary vertices (on an
        edge used by one triangle only), unreferenced vertices and vertices
        whose triangles are all degenerate.

    Raises
    ------
    ValueError
        If ``mesh`` is empty, has no triangles or has non-finite vertices.

    Notes
    -----
    With the cotangent Laplacian and the mixed Voronoi area ``A_i`` (Desbrun
    et al. 1999; Meyer et al. 2002)::

        K_i = 1 / (2 A_i) * sum_j (cot a_ij + cot b_ij) (x_j - x_i) = 2 H_i n_i

    and ``|H_i| = |K_i| / 2``.  Degenerate (zero-area) triangles are skipped.
    """
    verts, tris = mesh_arrays(mesh)
    lap, area = _cotangent_laplacian(verts, tris)
    k = lap @ verts
    h = np.full(verts.shape[0], np.nan)
    good = area > 0
    h[good] = 0.5 * np.linalg.norm(k[good], axis=1) / area[good]
    edges, _, counts = unique_edges(tris)
    h[edges[counts == 1].ravel()] = np.nan
    return h


def average_curvature(mesh: Any) -> float:
    """The paper's average curvature: mean of :func:`mean_curvature` over vertices.

    Vertices where the curvature is undefined (NaN: boundary, unreferenced,
    degenerate) are left out.  High values mean sharp detail, low values a
    blobby surface; a sphere of radius ``R`` gives ``1/R``.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh

    Returns
    -------
    float

    Raises
    ------
    ValueError
        As :func:`mean_curvature`, and if no vertex has a defined curvature
        (e.g. every vertex lies on the boundary).
    """
    h = mean_curvature(mesh)
    good = np.isfinite(h)
    if not good.any():
        raise ValueError("mesh has no interior vertex with a defined curvature (all on the boundary or degenerate)")
    return float(h[good].mean())


# --------------------------------------------------------------------------
# comparisons


def chamfer(a: Any, b: Any, n_samples: int = 100_000, seed: int = 0) -> dict[str, float]:
    """Symmetric distances between two surfaces or point sets.

    Parameters
    ----------
    a, b : open3d.geometry.TriangleMesh or (N, 3) array_like or open3d.geometry.PointCloud
        A mesh is sampled with ``n_samples`` points uniformly by area; a point
        set is used as given (all its points).
    n_samples : int, default 100_000
        Points drawn on each mesh.
    seed : int, default 0
        Seed of the sampling (``a`` is sampled first, then ``b``).

    Returns
    -------
    dict
        ``a_to_b_mean``
            Mean distance from the samples of ``a`` to ``b``.
        ``b_to_a_mean``
            Mean distance from the samples of ``b`` to ``a``.
        ``l1``
            ``(a_to_b_mean + b_to_a_mean) / 2``.
        ``l2``
            Mean of the two directed RMS distances,
            ``(rms(d_ab) + rms(d_ba)) / 2`` -- a length, not a squared length.
        ``hausdorff``
            ``max(max(d_ab), max(d_ba))`` over the samples (a lower bound of
            the true Hausdorff distance for meshes).

    Raises
    ------
    ValueError
        Bad point arrays, empty or triangle-less meshes, meshes of zero area,
        ``n_samples < 1`` or a negative ``seed``.

    Notes
    -----
    A distance *to* a mesh is the exact point-to-triangle distance
    (``RaycastingScene``), so a mesh compared with itself gives ~0 and two
    parallel planes ``d`` apart give ``d``; a distance *to* a point set is the
    nearest-neighbour distance (KD-tree).
    """
    dab, dba = _directed(a, b, n_samples, seed)
    rms_ab, rms_ba = np.sqrt(np.mean(dab * dab)), np.sqrt(np.mean(dba * dba))
    return {
        "l1": float(0.5 * (dab.mean() + dba.mean())),
        "l2": float(0.5 * (rms_ab + rms_ba)),
        "a_to_b_mean": float(dab.mean()),
        "b_to_a_mean": float(dba.mean()),
        "hausdorff": float(max(dab.max(), dba.max())),
    }


def f_score(a: Any, b: Any, threshold: float, n_samples: int = 100_000, seed: int = 0) -> dict[str, float]:
    """Precision, recall and F-score at a distance threshold (Knapitsch et al. 2017).

    Parameters
    ----------
    a : open3d.geometry.TriangleMesh or (N, 3) array_like
        The reconstruction.
    b : open3d.geometry.TriangleMesh or (M, 3) array_like
        The reference (ground truth).
    threshold : float
        Distance below which a sample counts as matched; > 0.
    n_samples, seed : int
        As in :func:`chamfer`.

    Returns
    -------
    dict
        ``precision``: fraction of the samples of ``a`` closer than
        ``threshold`` to ``b``; ``recall``: fraction of the samples of ``b``
        closer than ``threshold`` to ``a``; ``f``: their harmonic mean
        (0 when both are 0).

    Raises
    ------
    ValueError
        ``threshold`` not a finite number > 0, and as :func:`chamfer`.
    """
    threshold = check_number("threshold", threshold, low=0.0, low_open=True)
    dab, dba = _directed(a, b, n_samples, seed)
    precision = float(np.mean(dab < threshold))
    recall = float(np.mean(dba < threshold))
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return {"precision": precision, "recall": recall, "f": float(f)}


def normal_consistency(mesh_a: Any, mesh_b: Any, n_samples: int = 100_000, seed: int = 0) -> float:
    """Mean absolute cosine between the normals of two meshes at matched points.

    Points are sampled on ``mesh_a`` (uniformly by area); each takes the
    normal of its triangle and is matched to the closest point on
    ``mesh_b`` and that point's triangle normal; the same is done from
    ``mesh_b`` to ``mesh_a`` and the two means are averaged.

    Parameters
    ----------
    mesh_a, mesh_b : open3d.geometry.TriangleMesh
    n_samples : int, default 100_000
        Points drawn on each mesh.
    seed : int, default 0

    Returns
    -------
    float
        In ``[0, 1]``; 1 for identical surfaces.  The measure is *unsigned*
        (``|n_a . n_b|``): it ignores orientation, so a mesh and a copy with
        flipped normals (reversed triangle winding) also give 1.

    Raises
    ------
    ValueError
        Empty or triangle-less meshes, meshes of zero area, bad
        ``n_samples`` or ``seed``.
    """
    n_samples = check_number("n_samples", n_samples, low=1, integer=True)
    seed = check_number("seed", seed, low=0, integer=True)
    rng = np.random.default_rng(seed)
    sides = []
    for name, mesh in (("mesh_a", mesh_a), ("mesh_b", mesh_b)):
        verts, tris = mesh_arrays(mesh, name)
        cross, _ = _triangle_frames(verts, tris)
        norm = np.linalg.norm(cross, axis=1, keepdims=True)
        normals = np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)
        samples, faces = _sample_surface(verts, tris, n_samples, rng, name)
        sides.append((_Surface(verts, tris), normals, samples, faces))
    means = []
    for (_, n_from, samples, faces), (surface, n_to, _, _) in ((sides[0], sides[1]), (sides[1], sides[0])):
        hit = surface.closest_triangle(samples)
        means.append(np.abs(np.einsum("nd,nd->n", n_from[faces], n_to[hit])).mean())
    return float(np.mean(means))


# --------------------------------------------------------------------------
# mesh report


def _open3d_mesh(mesh: Any, verts: np.ndarray, tris: np.ndarray):
    """``mesh`` itself when it is an Open3D legacy mesh, else one of its arrays."""
    if hasattr(mesh, "is_orientable"):
        return mesh
    return MeshArrays(verts, tris).to_open3d()


def mesh_report(mesh: Any, self_intersections: bool = True) -> dict[str, Any]:
    """Counts, topology and size of a triangle mesh.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh, MeshArrays or (vertices, triangles)
    self_intersections : bool, default True
        Also count self-intersecting triangle pairs, the pairs Open3D's
        ``get_self_intersecting_triangles`` returns, found fast by
        :func:`o3drbf.mesh.intersections.self_intersecting_pairs` (about
        linear in the triangles).  ``False`` skips the count and leaves
        ``watertight`` topological only.

    Returns
    -------
    dict
        ``vertices``, ``triangles``
            Counts as stored.
        ``edge_manifold``
            Every edge is used by at most two triangles (boundary allowed).
        ``vertex_manifold``
            Open3D's ``is_vertex_manifold`` (the triangles around each vertex
            form one fan; :func:`o3drbf.mesh.intersections.nonmanifold_vertices`).
        ``closed``
            Every edge is used by exactly two triangles (no boundary).
        ``watertight``
            ``closed`` and ``vertex_manifold`` and no self-intersections:
            equal to Open3D's ``is_watertight()``.  With
            ``self_intersections=False``, only ``closed`` and
            ``vertex_manifold``.
        ``euler_characteristic``
            ``V - E + F`` with ``V`` the vertices used by a triangle, ``E``
            the distinct undirected edges, ``F`` the triangles.
        ``components``
            Number of connected triangle clusters (triangles joined through
            shared edges, as Open3D's ``cluster_connected_triangles``).
        ``genus``
            For a watertight, orientable mesh, the sum over components of
            ``(2 - chi_c) / 2`` (``chi_c`` the Euler characteristic of
            component ``c``); for one component this is ``(2 - chi) / 2``.
            ``None`` otherwise (open or non-manifold surfaces).
        ``self_intersections``
            Number of intersecting triangle pairs, or ``None`` when
            ``self_intersections=False``.
        ``area``
            Total triangle area.
        ``volume``
            Enclosed volume (absolute value of the divergence-theorem sum)
            when the mesh is watertight and consistently oriented, else ``None``.

    Raises
    ------
    ValueError
        If ``mesh`` is empty, has no triangles or has non-finite vertices.

    Examples
    --------
    >>> import open3d as o3d
    >>> from o3drbf.mesh.metrics import mesh_report
    >>> report = mesh_report(o3d.geometry.TriangleMesh.create_torus(0.6, 0.25, 24, 12))
    >>> report['watertight'], report['euler_characteristic'], report['genus'], report['components']
    (True, 0, 1, 1)
    """
    verts, tris = mesh_arrays(mesh)
    nf = tris.shape[0]
    edges, tri_edges, counts = unique_edges(tris)
    ne = edges.shape[0]
    n_used = int(np.count_nonzero(np.bincount(tris.ravel(), minlength=verts.shape[0])))

    edge_manifold = bool(counts.max() <= 2)
    closed = bool((counts == 2).all())
    vertex_manifold = len(nonmanifold_vertices(tris, verts.shape[0])) == 0
    n_self = None
    watertight = closed and vertex_manifold
    if self_intersections:
        n_self = int(self_intersecting_pairs(verts, tris).shape[0])
        watertight = watertight and n_self == 0

    n_comp, tri_comp = triangle_components(tris, tri_edges)

    # Consistent orientation: on a closed edge-manifold mesh, each directed edge appears once, i.e. on
    # each edge at most one side runs from its lower vertex up and at most one the other way (side k of
    # a triangle runs from its corner k + 1 to its corner k + 2, as unique_edges numbers them).
    oriented = False
    if closed:
        up = (np.roll(tris, -1, axis=1) <= np.roll(tris, -2, axis=1)).ravel()
        sides = tri_edges.ravel()
        oriented = bool(np.bincount(sides[up], minlength=ne).max(initial=0) <= 1
                        and np.bincount(sides[~up], minlength=ne).max(initial=0) <= 1)

    genus = None
    if watertight and (oriented or _open3d_mesh(mesh, verts, tris).is_orientable()):
        # every vertex in one piece (the mesh is vertex-manifold): each piece's vertices counted once
        vertex_comp = np.full(verts.shape[0], -1, dtype=np.int64)
        vertex_comp[tris] = tri_comp[:, None]
        comp_v = np.bincount(vertex_comp[vertex_comp >= 0], minlength=n_comp)
        edge_comp = np.empty(ne, dtype=np.int64)
        edge_comp[tri_edges.ravel()] = np.repeat(tri_comp, 3)
        comp_e = np.bincount(edge_comp, minlength=n_comp)
        comp_f = np.bincount(tri_comp, minlength=n_comp)
        chi_c = comp_v - comp_e + comp_f
        genus = int(np.sum((2 - chi_c) // 2))

    cross, area = _triangle_frames(verts, tris)
    volume = None
    if watertight and oriented:
        a = verts[tris[:, 0]] - verts.mean(axis=0)
        volume = float(abs(np.einsum("fd,fd->", a, cross)) / 6.0)

    return {
        "vertices": int(verts.shape[0]),
        "triangles": int(nf),
        "watertight": bool(watertight),
        "closed": closed,
        "edge_manifold": edge_manifold,
        "vertex_manifold": vertex_manifold,
        "euler_characteristic": n_used - ne + nf,
        "genus": genus,
        "components": n_comp,
        "self_intersections": n_self,
        "area": float(area.sum()),
        "volume": volume,
    }


def drop_specks(mesh, size: float):
    """Remove the mesh's pieces smaller than ``size`` across (their bounding-box diagonal), never all of them.

    Marching cubes turns a zero crossing of f around a single stray
    constraint into a closed speck a grid cell or two across: not a surface
    the grid can resolve, nor one a scan shows (an object that small is
    covered by at most a few points).

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh or MeshArrays
        An Open3D mesh is changed in place.
    size : float
        Data units; pieces whose bounding-box diagonal is below it go.

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh or MeshArrays
        (A new :class:`MeshArrays` when pieces went.)
    removed : int
        Pieces removed.
    """
    size = check_number("size", size, low=0.0)
    if len(mesh.triangles) == 0 or size == 0:
        return mesh, 0
    tris = np.asarray(mesh.triangles)
    n, labels = triangle_components(tris)
    if n < 2:
        return mesh, 0
    corners = np.asarray(mesh.vertices)[tris]  # (F, 3, 3)
    lo = np.full((n, 3), np.inf)
    hi = np.full((n, 3), -np.inf)
    np.minimum.at(lo, labels, corners.min(axis=1))
    np.maximum.at(hi, labels, corners.max(axis=1))
    small = np.linalg.norm(hi - lo, axis=1) < size
    if small.all() or not small.any():
        return mesh, 0
    if isinstance(mesh, MeshArrays):
        return mesh.keep_triangles(~small[labels]), int(small.sum())
    mesh.remove_triangles_by_mask(small[labels])
    mesh.remove_unreferenced_vertices()
    return mesh, int(small.sum())
