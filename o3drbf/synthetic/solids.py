"""Solids for the robustness study: signed-distance functions meshed by marching cubes.

Each solid is a signed-distance function (negative inside) built from boxes,
cylinders and tori, with a known genus and a bounding box.  :func:`solid_mesh`
meshes it with scikit-image's marching cubes on a fine grid (the truth mesh;
sharp edges are bevelled by less than one grid cell).

- ``bracket``: an L-shaped CAD part, a base plate and an upright plate, each
  with a round through-hole (sharp edges and corners, genus 2);
- ``double-torus``: two fused tori side by side (smooth, genus 2);
- ``thin-plate``: a slab 3 % as thick as it is wide, edges rounded (thin part,
  genus 0);
- ``pipe``: a tube whose wall is 5 % of its diameter, open at both ends
  (thin walls, genus 1).

Only tests, samples and benchmarks import :mod:`o3drbf.synthetic`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

__all__ = ["SOLIDS", "Solid", "solid", "solid_mesh"]


def _box(p: np.ndarray, center, half) -> np.ndarray:
    q = np.abs(p - np.asarray(center, float)) - np.asarray(half, float)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    return outside + np.minimum(q.max(axis=-1), 0.0)


def _cylinder(p: np.ndarray, center, axis: int, radius: float, half_length: float) -> np.ndarray:
    q = p - np.asarray(center, float)
    other = [i for i in range(3) if i != axis]
    d = np.stack([np.linalg.norm(q[..., other], axis=-1) - radius, np.abs(q[..., axis]) - half_length], axis=-1)
    return np.linalg.norm(np.maximum(d, 0.0), axis=-1) + np.minimum(d.max(axis=-1), 0.0)


def _torus(p: np.ndarray, center, R: float, r: float) -> np.ndarray:
    q = p - np.asarray(center, float)
    return np.hypot(np.hypot(q[..., 0], q[..., 1]) - R, q[..., 2]) - r


def _bracket(p):
    base = _box(p, (0.0, 0.0, -0.4), (0.6, 0.35, 0.1))
    upright = _box(p, (-0.5, 0.0, 0.05), (0.1, 0.35, 0.55))
    body = np.minimum(base, upright)
    hole_base = _cylinder(p, (0.2, 0.0, -0.4), 2, 0.14, 0.3)
    hole_upright = _cylinder(p, (-0.5, 0.0, 0.2), 0, 0.14, 0.3)
    return np.maximum(body, -np.minimum(hole_base, hole_upright))


def _double_torus(p):
    return np.minimum(_torus(p, (-0.42, 0.0, 0.0), 0.5, 0.18), _torus(p, (0.42, 0.0, 0.0), 0.5, 0.18))


def _thin_plate(p):
    rounding = 0.03
    return _box(p, (0.0, 0.0, 0.0), (0.8 - rounding, 0.55 - rounding, 0.0)) - rounding


def _pipe(p):
    outer = _cylinder(p, (0.0, 0.0, 0.0), 2, 0.5, 0.6)
    inner = _cylinder(p, (0.0, 0.0, 0.0), 2, 0.45, 1.0)
    return np.maximum(outer, -inner)


@dataclass(frozen=True)
class Solid:
    """A solid: its signed distance, bounding box and genus."""

    name: str
    signed_distance: Callable[[np.ndarray], np.ndarray]
    lo: tuple
    hi: tuple
    genus: int
    description: str


SOLIDS = {
    "bracket": Solid("bracket", _bracket, (-0.6, -0.35, -0.5), (0.6, 0.35, 0.6), 2, "L-shaped CAD part with two through-holes"),
    "double-torus": Solid("double-torus", _double_torus, (-1.1, -0.68, -0.18), (1.1, 0.68, 0.18), 2, "two fused tori"),
    "thin-plate": Solid("thin-plate", _thin_plate, (-0.8, -0.55, -0.03), (0.8, 0.55, 0.03), 0, "slab 3 % as thick as wide"),
    "pipe": Solid("pipe", _pipe, (-0.5, -0.5, -0.6), (0.5, 0.5, 0.6), 1, "open tube, wall 5 % of its diameter"),
}


def solid(name: str) -> Solid:
    """The solid called ``name`` (one of :data:`SOLIDS`)."""
    if name not in SOLIDS:
        raise ValueError(f"unknown solid {name!r}; valid: {', '.join(SOLIDS)}")
    return SOLIDS[name]


def solid_mesh(name: str, cells: int = 160):
    """The solid meshed by marching cubes: an Open3D TriangleMesh (outward normals).

    Parameters
    ----------
    name : str
        One of :data:`SOLIDS`.
    cells : int
        Grid cells along the longest side of the padded bounding box.
    """
    import open3d as o3d
    from skimage.measure import marching_cubes

    s = solid(name)
    lo, hi = np.asarray(s.lo, float), np.asarray(s.hi, float)
    pad = 0.05 * float((hi - lo).max())
    lo, hi = lo - pad, hi + pad
    h = float((hi - lo).max()) / cells
    axes = [lo[i] + h * np.arange(int(np.ceil((hi[i] - lo[i]) / h)) + 1) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = s.signed_distance(grid)
    verts, faces, _, _ = marching_cubes(values, level=0.0, spacing=(h, h, h))
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts + lo), o3d.utility.Vector3iVector(faces.astype(np.int32)))
    mesh.remove_duplicated_vertices()
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    return mesh
