"""Per-vertex confidence of a reconstructed mesh, from the fit itself, and trimming by it.

Two measures of how much the data say about the surface at each vertex:

- ``distance``: distance from the vertex to the nearest observed point (the
  surface constraints by default), in units of their mean spacing;
- ``variance``: the Gaussian-process posterior variance the kernel defines
  (:mod:`o3drbf.rbf.variance`), relative to phi(0): the fit with smoothing
  lambda is the posterior mean of a GP with covariance phi and noise lambda,
  so ``variance`` is ~lambda / phi(0) on densely sampled surface and tends
  to 1 where no constraint is near.

They combine into one ``confidence`` in [0, 1]::

    confidence = (1 - variance) * exp(-distance^2 / (2 * scale^2))

(``scale`` = :data:`o3drbf.options.CONFIDENCE_DEFAULTS` ``["distance_scale"]``
spacings).  The first factor is what the kernel knows; the second is the
plain geometric test, so a vertex is trusted only when both agree.

Both dip between the observed points, most where a random sample leaves a
gap of two or three spacings: trimming there would punch holes into what
was seen.  The combined value is therefore closed (a morphological closing
over the vertices: the largest value within ``closing`` spacings, then the
smallest of those within the same radius, :func:`close_confidence`), which
fills dips narrower than about twice that radius and leaves the edge of the
seen region where it was.  For a
kernel that is not positive definite (thin-plate) there is no variance:
``variance`` is NaN and ``confidence`` is the distance factor alone.

:func:`trim_by_confidence` removes the triangles with a vertex below a
threshold: what is left is the part of the surface the data support, an
open surface where nothing was seen.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from o3drbf.mesh.arrays import mesh_arrays
from o3drbf.prep.sampling import mean_spacing
from o3drbf.rbf.variance import local_posterior_variance
from o3drbf.validation import as_points, check_number, per_point

__all__ = ["VertexConfidence", "vertex_confidence", "combine_confidence", "close_confidence", "trim_by_confidence", "CLOSING_SPACINGS"]

log = logging.getLogger("o3drbf")

#: Radius of the closing of the combined confidence, in mean spacings.
CLOSING_SPACINGS = 2.0

@dataclass
class VertexConfidence:
    """Per-vertex confidence of a mesh.

    Attributes
    ----------
    confidence : (V,) ndarray
        In [0, 1]: ``(1 - variance) * exp(-distance^2 / (2 scale^2))``
        (the distance factor alone when ``variance`` is NaN), closed over
        ``closing`` spacings (:func:`close_confidence`).
    distance : (V,) ndarray
        Distance to the nearest observed point, in mean spacings.
    variance : (V,) ndarray
        GP posterior variance relative to phi(0), in [0, 1]; NaN for a kernel
        that is not positive definite.
    spacing : float
        The mean spacing used as the distance unit (data units).
    neighbours : int
        Constraints per local GP neighbourhood.
    distance_scale : float
        ``scale`` above, in spacings.
    closing : float
        Radius of the closing, in spacings (0: none).
    """

    confidence: np.ndarray
    distance: np.ndarray
    variance: np.ndarray
    spacing: float
    neighbours: int
    distance_scale: float
    closing: float = 0.0

    def subset(self, keep) -> "VertexConfidence":
        """The values of the vertices selected by ``keep`` ((V,) bool or indices), e.g. after trimming."""
        return VertexConfidence(self.confidence[keep], self.distance[keep], self.variance[keep], self.spacing,
                                self.neighbours, self.distance_scale, self.closing)

    def summary(self) -> dict:
        """Mean, min and quartiles of ``confidence`` (plain floats, for reports)."""
        c = self.confidence
        if not len(c):
            return {"mean": float("nan"), "min": float("nan"), "q25": float("nan"), "median": float("nan")}
        return {"mean": float(c.mean()), "min": float(c.min()), "q25": float(np.quantile(c, 0.25)), "median": float(np.median(c))}


def combine_confidence(distance, variance, distance_scale: float) -> np.ndarray:
    """``(1 - variance) * exp(-distance^2 / (2 scale^2))``, the distance factor alone where variance is NaN.

    Parameters
    ----------
    distance : (V,) array_like
        In mean spacings, >= 0.
    variance : (V,) array_like
        Relative to phi(0), in [0, 1] (or NaN).
    distance_scale : float
        > 0, in spacings.

    Returns
    -------
    (V,) ndarray in [0, 1]
    """
    scale = check_number("distance_scale", distance_scale, low=0.0, low_open=True)
    d = np.asarray(distance, dtype=float)
    v = np.asarray(variance, dtype=float)
    near = np.exp(-0.5 * (d / scale) ** 2)
    known = np.where(np.isnan(v), 1.0, 1.0 - np.clip(v, 0.0, 1.0))
    return np.clip(known * near, 0.0, 1.0)


def close_confidence(vertices, confidence, radius: float, max_neighbours: int = 96, chunk: int = 20000) -> np.ndarray:
    """Morphological closing of per-vertex values: the largest within ``radius``, then the smallest of those.

    Dips narrower than about ``2 radius`` are filled; a broad low region
    keeps its edge where it was (up to the vertex spacing).

    Parameters
    ----------
    vertices : (V, 3) array_like
    confidence : (V,) array_like
    radius : float
        Data units, >= 0 (0: the values unchanged).
    max_neighbours : int
        At most this many nearest vertices within ``radius`` are looked at
        (on very fine meshes the ball shrinks to them).
    chunk : int
        Vertices per KD-tree query (bounds the memory).

    Returns
    -------
    (V,) ndarray
    """
    v = as_points(vertices, "vertices", min_count=0)
    c = np.asarray(confidence, dtype=float).ravel()
    radius = check_number("closing radius", radius, low=0.0)
    if radius == 0 or len(v) < 2:
        return c.copy()
    tree = cKDTree(v)
    k = min(int(max_neighbours), len(v))

    def extreme(values, pick):
        padded = np.append(values, np.nan)  # index len(v): no neighbour
        out = np.empty(len(v))
        for start in range(0, len(v), chunk):
            _, nb = tree.query(v[start:start + chunk], k=k, distance_upper_bound=radius)
            out[start:start + chunk] = pick(padded[nb.reshape(-1, k)], axis=1)
        return out

    return extreme(extreme(c, np.nanmax), np.nanmin)


def vertex_confidence(surface, mesh, smoothing, observed=None, *, spacing: float | None = None,
                      neighbours: int, distance_scale: float, closing: float = CLOSING_SPACINGS) -> VertexConfidence:
    """Per-vertex confidence of ``mesh`` from the fit ``surface``.

    Parameters
    ----------
    surface : ImplicitSurface
        The fit: its kernel, its centres (the constraints, box coordinates)
        and its normalization.
    mesh : open3d.geometry.TriangleMesh or (V, 3) ndarray
        The mesh (or its vertices), data coordinates.
    smoothing : float or (M,) array_like
        lambda_i of each centre of ``surface`` (absolute, as fitted; e.g.
        ``Reconstruction.constraints.smoothing``).
    observed : (S, 3) array_like, optional
        The observed points the distance is measured to, data coordinates
        (e.g. the surface constraints); default every centre.
    spacing : float, optional
        Distance unit, data units; default the mean nearest-neighbour
        spacing of ``observed``.
    neighbours : int
        Constraints per local GP neighbourhood (:func:`o3drbf.rbf.variance.local_posterior_variance`);
        at least the number of centres gives the exact variance.  The
        pipeline's default: :data:`o3drbf.options.CONFIDENCE_DEFAULTS`.
    distance_scale : float
        Spacings at which the distance factor is exp(-1/2) (default: the same table).
    closing : float
        Radius of the closing of the combined value (:func:`close_confidence`),
        in spacings; 0 leaves it as combined (default :data:`CLOSING_SPACINGS`).

    Returns
    -------
    VertexConfidence

    Raises
    ------
    ValueError
        ``smoothing`` of the wrong length, no observed points, bad numbers.
    """
    vertices = as_points(mesh, "vertices", min_count=0) if isinstance(mesh, np.ndarray) else mesh_arrays(mesh)[0]
    centres = np.asarray(surface.centres, dtype=float)
    lam = per_point("smoothing", smoothing, len(centres))
    neighbours = int(check_number("neighbours", neighbours, low=1, integer=True))
    scale = check_number("distance_scale", distance_scale, low=0.0, low_open=True)
    norm = surface.normalization
    seen = norm.inverse(centres) if observed is None else as_points(observed, "observed")
    if spacing is None:
        spacing = mean_spacing(seen) if len(seen) > 1 else float("nan")
    spacing = check_number("spacing", spacing, low=0.0, low_open=True)
    distance = cKDTree(seen).query(vertices)[0] / spacing if len(vertices) else np.zeros(0)
    if getattr(surface.kernel, "positive_definite", False):
        variance = local_posterior_variance(surface.kernel, centres, lam, norm.forward(vertices), neighbours=neighbours)
        variance = variance / surface.kernel.value_at_zero
    else:
        log.info("the %s kernel is not positive definite: confidence from the distance alone", surface.kernel.name)
        variance = np.full(len(vertices), np.nan)
    conf = combine_confidence(distance, variance, scale)
    closing = check_number("closing", closing, low=0.0)
    conf = close_confidence(vertices, conf, closing * spacing)
    return VertexConfidence(conf, distance, variance, float(spacing), min(neighbours, len(centres)), float(scale), float(closing))


def trim_by_confidence(mesh, confidence, threshold: float):
    """Remove every triangle with a vertex whose confidence is below ``threshold``.

    Vertices no longer used are dropped; normals and colours are kept.

    Parameters
    ----------
    mesh : open3d.geometry.TriangleMesh
    confidence : (V,) array_like
        Per vertex of ``mesh``.
    threshold : float
        In [0, 1]; 0 keeps everything.

    Returns
    -------
    trimmed : open3d.geometry.TriangleMesh
        A new mesh (``mesh`` is not changed).
    kept : (V,) ndarray of bool
        Which vertices of ``mesh`` are in ``trimmed`` (in order).
    removed : int
        Triangles removed.
    """
    import open3d as o3d

    threshold = check_number("trim", threshold, low=0.0, high=1.0)
    v, t = mesh_arrays(mesh)
    conf = np.asarray(confidence, dtype=float).ravel()
    if len(conf) != len(v):
        raise ValueError(f"confidence has {len(conf)} values for {len(v)} vertices; compute it for this mesh")
    keep_tri = (conf[t] >= threshold).all(axis=1) if len(t) else np.zeros(0, dtype=bool)
    t = t[keep_tri]
    used = np.zeros(len(v), dtype=bool)
    used[t.ravel()] = True
    new_index = np.cumsum(used) - 1
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v[used]), o3d.utility.Vector3iVector(new_index[t].astype(np.int32)))
    if mesh.has_vertex_normals():
        out.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals)[used])
    if mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[used])
    return out, used, int((~keep_tri).sum())
