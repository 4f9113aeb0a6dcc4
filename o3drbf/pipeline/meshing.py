"""Extract, colour, confidence: the mesh of f = 0, its colours from the points, its per-vertex confidence and trimming."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.constraints.core import SURFACE, Constraints
from o3drbf.options import ConfidenceOptions, ExtractOptions, auto_resolution
from o3drbf.pointset import PointSet
from o3drbf.surface import ImplicitSurface

__all__ = ["MIN_VOXEL_CELLS", "check_voxel_size", "extraction_bounds", "mesh_lattice_box", "mesh_surface", "colour", "mesh_confidence"]

log = logging.getLogger("o3drbf")


#: Fewest marching-cubes cells along the extraction box's longest side a ``voxel_size`` may leave.
MIN_VOXEL_CELLS = 8


def check_voxel_size(voxel_size, bounds) -> None:
    """Refuse a ``voxel_size`` that leaves fewer than :data:`MIN_VOXEL_CELLS` cells along the box's longest side.

    Parameters
    ----------
    voxel_size : float or None
        Data units (None: nothing to check).
    bounds : (2, 3) array_like
        The extraction box, data units.

    Raises
    ------
    ValueError
        One line: the cells left, the data's extent, and the largest voxel size that works.
    """
    if voxel_size is None or bounds is None:
        return
    b = np.asarray(bounds, dtype=float)
    extent = float((b[1] - b[0]).max())
    if extent > 0 and extent / float(voxel_size) < MIN_VOXEL_CELLS:
        raise ValueError(f"--voxel-size {float(voxel_size):g} leaves {extent / float(voxel_size):.2g} cells along the longest side of the "
                         f"box meshed ({extent:.4g} data units: the data plus 5 %), too coarse for a surface; give --voxel-size of at most "
                         f"{extent / MIN_VOXEL_CELLS:.3g} ({MIN_VOXEL_CELLS} cells), or --resolution instead")


def extraction_bounds(data: PointSet, options: ExtractOptions) -> np.ndarray:
    """The box marching cubes covers (data units): ``options.bounds``, else the points' box padded by 5 %."""
    if options.bounds is not None:
        return np.asarray(options.bounds, dtype=float)
    lo, hi = data.bounds
    pad = 0.05 * float((hi - lo).max())
    return np.stack([lo - pad, hi + pad])


def mesh_lattice_box(cset, options: ExtractOptions = ExtractOptions()) -> np.ndarray | None:
    """The corners ((2, 3), box coordinates) of the lattice :func:`mesh_surface` will evaluate a fit of
    ``cset`` on with these options, or None when ``cset`` has no bounds (the mesh then covers the centres)."""
    from o3drbf.extract import mesh_lattice

    bounds = options.bounds if options.bounds is not None else cset.bounds
    if bounds is None:
        return None
    resolution = auto_resolution(float(cset.spacing)) if options.resolution == "auto" else options.resolution
    origin, h, shape = mesh_lattice(cset.normalization, bounds, resolution, options.voxel_size)
    return np.array([origin, origin + (np.array(shape) - 1) * h])


def mesh_surface(surface: ImplicitSurface, options: ExtractOptions = ExtractOptions(), *, progress: bool = False, arrays: bool = False):
    """Marching cubes of f = 0 (:func:`o3drbf.extract.extract_mesh`): an Open3D mesh, or with ``arrays`` a
    :class:`o3drbf.mesh.arrays.MeshArrays` (:func:`o3drbf.extract.extract_arrays`, Open3D not imported).

    Raises
    ------
    RuntimeError
        No zero crossing, with the likely cause.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import build_constraints, choose_parameters, fit_surface, mesh_surface
    >>> from o3drbf.options import ExtractOptions
    >>> cset = build_constraints(data)
    >>> surface, _, _ = fit_surface(cset, choose_parameters(data, cset))
    >>> mesh = mesh_surface(surface, ExtractOptions(resolution=20))
    >>> mesh.is_watertight()
    True
    """
    from o3drbf.extract import extract_arrays, extract_mesh

    options.validate()
    resolution = options.resolution
    if resolution == "auto":
        resolution = auto_resolution(float(surface.metadata.get("mean_spacing", float("nan"))))
    check_voxel_size(options.voxel_size, options.bounds if options.bounds is not None else surface.metadata.get("bounds"))
    try:
        return (extract_arrays if arrays else extract_mesh)(surface, resolution=resolution, voxel_size=options.voxel_size,
                                                            bounds=options.bounds, progress=progress)
    except RuntimeError as exc:
        lam = surface.metadata.get("lambda_surface", float("nan"))
        spacing = float(surface.metadata.get("mean_spacing", float("nan")))
        raise RuntimeError(
            f"{exc}. The fit has no zero crossing: the kernel {surface.kernel!r} may not suit the surface constraints' "
            f"spacing {spacing:.3g} (box units; leave --delta, --tau and --sigma out for the defaults), or smoothing may "
            f"swamp the data (lambda_surface {lam:g} vs phi(0) = {surface.kernel.value_at_zero:.3g}; lower lambda_surface, --lambda-surface), "
            "or check the normals/exterior constraints"
        ) from None
    finally:
        if hasattr(surface, "meshing"):
            surface.meshing = None  # the meshing grid (shared with the robust pass) is not kept with the result


def colour(mesh, data: PointSet):
    """Per-vertex colour from the points' colours (nearest points, distance weighted); the mesh unchanged without them.

    Examples
    --------
    >>> import numpy as np, open3d as o3d
    >>> from o3drbf import PointSet, colour
    >>> mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=10)
    >>> points = np.asarray(mesh.vertices) * 1.01
    >>> red = PointSet.create(points, colors=np.tile([1.0, 0.0, 0.0], (len(points), 1)))
    >>> np.asarray(colour(mesh, red).vertex_colors)[0]
    array([1., 0., 0.])
    """
    if mesh is None or data.colors is None:
        return mesh
    from o3drbf.mesh.arrays import MeshArrays
    from o3drbf.mesh.color import color_mesh

    if isinstance(mesh, MeshArrays):
        mesh = mesh.to_open3d()

    return color_mesh(mesh, points=data.points, colors=data.colors)


def mesh_confidence(surface: ImplicitSurface, mesh, constraints: Constraints, spacing: float | None = None,
                    options: ConfidenceOptions = ConfidenceOptions()):
    """Per-vertex confidence of the mesh (:func:`o3drbf.mesh.confidence.vertex_confidence`), and trimming by it.

    Parameters
    ----------
    surface : ImplicitSurface
    mesh : open3d.geometry.TriangleMesh, MeshArrays or None
    constraints : Constraints
        The constraints of the fit, data coordinates (``Reconstruction.constraints``):
        their smoothing is the GP's noise, their surface points what was observed.
    spacing : float, optional
        Mean spacing of the surface constraints, data units (default: measured).
    options : ConfidenceOptions
        Nothing is computed unless ``confidence`` or ``trim`` is set.

    Returns
    -------
    confidence : VertexConfidence or None
        Per vertex of the returned mesh.
    mesh : open3d.geometry.TriangleMesh or None
        Trimmed when ``options.trim`` is set (an open surface where nothing was seen).
    triangles_removed : int

    Examples
    --------
    >>> import o3drbf
    >>> from o3drbf import mesh_confidence
    >>> from o3drbf.options import ConfidenceOptions
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> r = o3drbf.reconstruct(points, normals, surface_count=200, resolution=20)
    >>> confidence, mesh, removed = mesh_confidence(r.surface, r.mesh, r.constraints, options=ConfidenceOptions(confidence=True))
    >>> len(confidence.confidence) == len(r.mesh.vertices), removed
    (True, 0)
    """
    options.validate()
    if mesh is None or not options.wanted:
        return None, mesh, 0
    from o3drbf.mesh.arrays import MeshArrays
    from o3drbf.mesh.confidence import trim_by_confidence, vertex_confidence

    if isinstance(mesh, MeshArrays):
        mesh = mesh.to_open3d()

    if len(constraints) != len(surface.centres):
        raise ValueError(f"{len(constraints)} constraints for a surface with {len(surface.centres)} centres; give the constraints of this fit")
    spacing = spacing if spacing is not None and np.isfinite(spacing) else None
    conf = vertex_confidence(surface, mesh, constraints.smoothing, constraints.select(SURFACE), spacing=spacing,
                             neighbours=options.neighbours, distance_scale=options.distance_scale)
    removed = 0
    if options.trim is not None:
        mesh, kept, removed = trim_by_confidence(mesh, conf.confidence, options.trim)
        conf = conf.subset(kept)
        log.info("trimmed %d triangles with a vertex of confidence below %g", removed, options.trim)
    return conf, mesh, removed
