"""Triangle meshes as arrays: the one place that turns a mesh into ``(V, F)``.

:class:`MeshArrays` is a mesh as NumPy arrays, what the pipeline hands from
one stage to the next (Open3D is imported only when a caller asks for an
Open3D mesh); :func:`mesh_arrays` accepts every mesh form the toolkit takes
(Open3D legacy or tensor ``TriangleMesh``, :class:`MeshArrays`, a mesh file,
or a ``(vertices, triangles)`` pair) and checks it; :func:`raycasting_scene` builds the Open3D ray-casting scene
that visibility, rendering, carving and distance queries share;
:func:`unique_edges` is the undirected edge table of a triangle list.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["MeshArrays", "mesh_arrays", "raycasting_scene", "unique_edges", "triangle_components"]


@dataclass(eq=False)
class MeshArrays:
    """A triangle mesh as arrays, named as on Open3D's ``TriangleMesh``.

    Attributes
    ----------
    vertices : (V, 3) float64 array
    triangles : (F, 3) int32 array
        Vertex indices of each triangle.
    vertex_normals : (V, 3) float64 array or None
    vertex_colors : (V, 3) float64 array in [0, 1] or None

    Examples
    --------
    >>> import numpy as np
    >>> tetra = MeshArrays(np.eye(4, 3), np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    >>> len(tetra.vertices), tetra.has_vertex_normals(), tetra.to_open3d().is_watertight()
    (4, False, True)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_normals: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int32).reshape(-1, 3)
        for name in ("vertex_normals", "vertex_colors"):
            value = getattr(self, name)
            if value is not None:
                value = np.ascontiguousarray(value, dtype=np.float64).reshape(-1, 3)
                if len(value) != len(self.vertices):
                    raise ValueError(f"{name} has {len(value)} rows for {len(self.vertices)} vertices; give one per vertex")
                setattr(self, name, value)

    def has_vertex_normals(self) -> bool:
        return self.vertex_normals is not None and len(self.vertices) > 0

    def has_vertex_colors(self) -> bool:
        return self.vertex_colors is not None and len(self.vertices) > 0

    def has_triangle_normals(self) -> bool:
        return False

    def keep_triangles(self, keep: np.ndarray) -> "MeshArrays":
        """The mesh of the triangles where ``keep`` (a bool mask) holds, without the vertices no kept triangle
        uses: Open3D's ``remove_triangles_by_mask(~keep)`` then ``remove_unreferenced_vertices()`` (the kept
        triangles and vertices in their order)."""
        tris = self.triangles[np.asarray(keep, dtype=bool)]
        used = np.zeros(len(self.vertices), dtype=bool)
        used[tris.ravel()] = True
        if used.all():
            return MeshArrays(self.vertices, tris, self.vertex_normals, self.vertex_colors)
        index = np.cumsum(used) - 1
        pick = lambda a: None if a is None else a[used]  # noqa: E731
        return MeshArrays(self.vertices[used], index[tris], pick(self.vertex_normals), pick(self.vertex_colors))

    def without_degenerate_triangles(self) -> "MeshArrays":
        """Open3D's ``remove_degenerate_triangles()`` (a triangle naming one vertex twice goes) then
        ``remove_unreferenced_vertices()``."""
        t = self.triangles
        return self.keep_triangles((t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 2] != t[:, 0]))

    def to_open3d(self):
        """An ``open3d.geometry.TriangleMesh`` with these vertices, triangles, normals and colours."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices), o3d.utility.Vector3iVector(self.triangles))
        if self.vertex_normals is not None:
            mesh.vertex_normals = o3d.utility.Vector3dVector(self.vertex_normals)
        if self.vertex_colors is not None:
            mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colors)
        return mesh

    @classmethod
    def from_open3d(cls, mesh) -> "MeshArrays":
        """The arrays of an ``open3d.geometry.TriangleMesh`` (copies)."""
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                   np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None,
                   np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None)


def mesh_arrays(mesh: Any, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a mesh, checked.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh, open3d.t.geometry.TriangleMesh, MeshArrays, path or (vertices, triangles)
        A mesh file is read with Open3D.
    name : str
        What to call the mesh in error messages.

    Returns
    -------
    vertices : (V, 3) float64 array
    triangles : (F, 3) int64 array

    Raises
    ------
    FileNotFoundError
        A path that is not a file.
    ValueError
        Anything that is not a mesh, an empty mesh, a mesh without
        triangles, non-finite vertices or triangle indices outside ``[0, V)``.
    """
    if isinstance(mesh, (str, os.PathLike)):
        import open3d as o3d

        path = Path(mesh)
        if not path.is_file():
            raise FileNotFoundError(f"{name} file not found: {path}")
        mesh = o3d.io.read_triangle_mesh(str(path))
    if hasattr(mesh, "vertex") and hasattr(mesh, "triangle"):  # tensor mesh
        verts = mesh.vertex.positions.numpy() if "positions" in mesh.vertex else np.zeros((0, 3))
        tris = mesh.triangle.indices.numpy() if "indices" in mesh.triangle else np.zeros((0, 3), np.int64)
    elif hasattr(mesh, "vertices") and hasattr(mesh, "triangles") and not isinstance(mesh, np.ndarray):
        verts, tris = mesh.vertices, mesh.triangles
    elif isinstance(mesh, tuple) and len(mesh) == 2:
        verts, tris = mesh
    else:
        kind = f"{type(mesh).__module__}.{type(mesh).__qualname__}"
        raise ValueError(
            f"{name} must be an open3d.geometry.TriangleMesh (legacy or tensor), a mesh file or a "
            f"(vertices, triangles) pair, got {kind}"
        )
    verts = np.asarray(verts, dtype=float)
    tris = np.asarray(tris)
    if verts.size == 0:
        raise ValueError(f"{name} is empty (no vertices)")
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"{name} vertices must have shape (V, 3), got {verts.shape}")
    if tris.size == 0:
        raise ValueError(f"{name} has {verts.shape[0]} vertices but no triangles")
    if tris.ndim != 2 or tris.shape[1] != 3 or not np.issubdtype(tris.dtype, np.integer):
        raise ValueError(f"{name} triangles must be integers of shape (F, 3), got {tris.dtype} {tris.shape}")
    tris = tris.astype(np.int64)
    bad = ~np.isfinite(verts).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name} has {int(bad.sum())} vertex(es) with NaN or infinite coordinates (first at index {i})")
    if tris.min() < 0 or tris.max() >= verts.shape[0]:
        raise ValueError(
            f"{name} has triangle indices outside [0, {verts.shape[0]}): min {int(tris.min())}, max {int(tris.max())}"
        )
    return verts, tris


def raycasting_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An Open3D ray-casting scene holding one triangle mesh (single precision).

    Parameters
    ----------
    vertices : (V, 3) array_like
    triangles : (F, 3) int array_like
        May be empty: the scene then holds nothing and every ray misses.

    Returns
    -------
    open3d.t.geometry.RaycastingScene
    """
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    if len(triangles):
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)),
            o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32).reshape(-1, 3)),
        )
    return scene


def unique_edges(triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undirected edges of a triangle list.

    Parameters
    ----------
    triangles : (F, 3) int array_like

    Returns
    -------
    edges : (E, 2) int64 array
        Sorted vertex pairs ``(i < j)``, in increasing order of ``(i, j)``.
    side_edge : (F, 3) int64 array
        The edge of each triangle side; side ``k`` is opposite corner ``k``.
    counts : (E,) int64 array
        How many triangle sides use each edge (2 everywhere on a closed manifold).
    """
    tris = np.ascontiguousarray(np.asarray(triangles, dtype=np.int64).reshape(-1, 3))
    if not len(tris):
        return np.zeros((0, 2), np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    edges, side_edge, counts, n = _edge_table(tris, int(tris.max()) + 1)
    return edges[:n], side_edge.reshape(-1, 3), counts[:n]


def _sort_bucket(order, hi, begin, end):
    """Sort ``order[begin:end]`` by ``hi`` of its entries, keeping the order of equal ones."""
    if end - begin > 32:
        part = order[begin:end].copy()
        order[begin:end] = part[np.argsort(hi[part], kind="mergesort")]
        return
    for p in range(begin + 1, end):  # insertion sort: a vertex has a handful of edges
        s = order[p]
        key = hi[s]
        q = p - 1
        while q >= begin and hi[order[q]] > key:
            order[q + 1] = order[q]
            q -= 1
        order[q + 1] = s


def _edge_table_py(tris, nv):
    """:func:`unique_edges` in linear time: the sides bucketed by their lower vertex (a counting sort),
    each bucket sorted by the higher one.  Returns (edges, side_edge, counts) with room for every side,
    and the number of edges."""
    ns = 3 * tris.shape[0]
    lo = np.empty(ns, np.int64)
    hi = np.empty(ns, np.int64)
    start = np.zeros(nv + 1, np.int64)
    for f in range(tris.shape[0]):
        for k in range(3):
            i, j = tris[f, (k + 1) % 3], tris[f, (k + 2) % 3]
            s = 3 * f + k
            lo[s], hi[s] = min(i, j), max(i, j)
            start[lo[s] + 1] += 1
    for v in range(nv):
        start[v + 1] += start[v]
    fill = start[:-1].copy()
    order = np.empty(ns, np.int64)
    for s in range(ns):
        order[fill[lo[s]]] = s
        fill[lo[s]] += 1
    for v in range(nv):
        if start[v + 1] - start[v] > 1:
            _sort_bucket(order, hi, start[v], start[v + 1])
    edges = np.empty((ns, 2), np.int64)
    side_edge = np.empty(ns, np.int64)
    counts = np.zeros(ns, np.int64)
    n = 0
    for p in range(ns):
        s = order[p]
        if n == 0 or lo[s] != edges[n - 1, 0] or hi[s] != edges[n - 1, 1]:
            edges[n, 0], edges[n, 1] = lo[s], hi[s]
            n += 1
        side_edge[s] = n - 1
        counts[n - 1] += 1
    return edges, side_edge, counts, n


def triangle_components(triangles: np.ndarray, side_edge: np.ndarray | None = None) -> tuple[int, np.ndarray]:
    """Connected pieces of a triangle list: triangles joined through shared edges.

    The same clusters as Open3D's ``cluster_connected_triangles``, found by
    one sparse graph search (linear in the triangles); pieces are numbered
    in the order of their first triangle.

    Parameters
    ----------
    triangles : (F, 3) int array_like
    side_edge : (F, 3) int array, optional
        :func:`unique_edges`' second output, when already computed.

    Returns
    -------
    n : int
        Number of pieces.
    labels : (F,) int64 array
        The piece of each triangle, ``0 .. n - 1``.
    """
    if side_edge is None:
        side_edge = unique_edges(triangles)[1]
    nf = side_edge.shape[0]
    if nf == 0:
        return 0, np.zeros(0, np.int64)
    labels = np.empty(nf, np.int64)
    n = _edge_components(np.ascontiguousarray(side_edge, dtype=np.int64), int(side_edge.max()) + 1, labels)
    return n, labels


def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]  # (path halving)
        i = parent[i]
    return i


def _edge_components_py(side_edge, n_edges, labels):
    """Union-find of the triangles through their edges; ``labels`` numbered by first triangle; returns the count."""
    nf = side_edge.shape[0]
    parent = np.arange(nf)
    first = np.full(n_edges, -1, np.int64)  # the first triangle seen on each edge
    for t in range(nf):
        for k in range(3):
            e = side_edge[t, k]
            if first[e] < 0:
                first[e] = t
            else:
                a, b = _find(parent, t), _find(parent, first[e])
                if a != b:
                    parent[max(a, b)] = min(a, b)
    number = np.full(nf, -1, np.int64)
    n = 0
    for t in range(nf):
        r = _find(parent, t)
        if number[r] < 0:
            number[r] = n
            n += 1
        labels[t] = number[r]
    return n


try:  # compiled where numba is (a dependency); the same code in Python otherwise
    from numba import njit

    _find = njit(cache=True)(_find)
    _edge_components = njit(cache=True)(_edge_components_py)
    _sort_bucket = njit(cache=True)(_sort_bucket)
    _edge_table = njit(cache=True)(_edge_table_py)
except ImportError:  # pragma: no cover
    _edge_components = _edge_components_py
    _edge_table = _edge_table_py
