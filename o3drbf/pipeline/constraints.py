"""Constraints: surface, exterior and sphere constraints in the normalized box (smoothing set later, by the parameters)."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.constraints.core import EXTERIOR, SPHERE, SURFACE, Constraints, bounding_sphere, exterior_from_normals, surface_constraints
from o3drbf.options import AUTO_SIZES, DENOISE_MIN_NOISE, ConstraintOptions, auto_surface_count
from o3drbf.pipeline.records import ConstraintSet
from o3drbf.pointset import PointSet
from o3drbf.prep.normalize import Normalization
from o3drbf.prep.sampling import mean_spacing

__all__ = ["build_constraints"]

log = logging.getLogger("o3drbf")


def build_constraints(data: PointSet, options: ConstraintOptions = ConstraintOptions(), *, seed: int = 0,
                      normalization: Normalization | None = None, occluder=None) -> ConstraintSet:
    """Surface, exterior and sphere constraints in the normalized box.

    Surface constraints are a Poisson-disc subset of the points; exterior
    constraints go toward the cameras that see each point (method.md
    section 4) or, without cameras, along the normals; a sphere of exterior
    constraints surrounds the data.  Smoothing is left at 0 (see
    :func:`choose_parameters`).

    Parameters
    ----------
    data : PointSet
        Needs normals or cameras (see :func:`ensure_normals`).
    options : ConstraintOptions
    seed : int
    normalization : Normalization, optional
        The data -> box map (default: the points' own, :meth:`Normalization.from_points`);
        a tile of a larger cloud passes the whole cloud's, so that its
        constraints, offsets and noise are in the box of the whole.
    occluder : (K, 3) array_like, optional
        The points (data coordinates) that block the cameras' view when
        exterior constraints are placed (default the data's points; a tile
        adds points of the whole cloud outside it).

    Returns
    -------
    ConstraintSet

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> from o3drbf import build_constraints
    >>> cset = build_constraints(data)
    >>> cset.constraints.counts()
    {'surface': 600, 'exterior': 60, 'interior': 0, 'sphere': 64}
    """
    options.validate()
    if data.normals is None and data.cameras is None:
        raise ValueError("build_constraints needs normals or cameras; call ensure_normals first")
    count = None if options.surface_radius is not None else options.surface_count
    if count is None and options.surface_radius is None:
        log.info("surface_count=None: every point is a surface constraint")
    auto_count = count == "auto"
    if auto_count:
        count = auto_surface_count(len(data))
    pts = data.points
    norm = Normalization.from_points(pts) if normalization is None else normalization
    box = norm.forward(pts)
    idx = surface_constraints(box, count=count, radius=options.surface_radius, seed=seed)
    surf = box[idx]
    noise, constraint_noise, moved = float("nan"), float("nan"), 0
    spacing = mean_spacing(surf) if len(surf) > 1 else float("nan")
    adaptive = options.surface_adaptive is not None and len(surf) > 10 and len(box) > len(surf)
    if adaptive or (options.denoise and len(surf) > 10 and len(box) > len(surf)):
        from o3drbf.constraints.parameters import estimate_noise

        noise = estimate_noise(box, seed=seed)
        constraint_noise = noise
    uniform = len(idx)
    if options.denoise and len(surf) > 10 and len(box) > len(surf):
        from o3drbf.prep.smoothing import neighbourhood_size, project_to_local_surface

        denoise = options.denoise is True or noise > DENOISE_MIN_NOISE * spacing
        if denoise and auto_count and auto_surface_count(len(data), noisy=True) < len(idx):
            idx = surface_constraints(box, count=auto_surface_count(len(data), noisy=True), seed=seed)
            surf = box[idx]
            spacing = mean_spacing(surf)
            log.info("noisy points: %d surface constraints (points / %d up to %d, else points / %d)", len(idx),
                     AUTO_SIZES["points_per_constraint"], AUTO_SIZES["noisy_full_rate_max"], AUTO_SIZES["noisy_points_per_constraint"])
        uniform = len(idx)
        if adaptive:
            idx, surf = _thin_flat(box, idx, options.surface_adaptive, noise, seed)
        if denoise:
            k = neighbourhood_size(len(box), uniform)
            moved_data, offset, gain = project_to_local_surface(pts, norm.inverse(surf), k=k, tree=data.kdtree, noise=noise / norm.scale)
            surf, offset = norm.forward(moved_data), offset * norm.scale
            # what is left of the noise: the fits' own standard deviation (RMS over the constraints)
            constraint_noise = noise * float(np.sqrt(np.mean(gain * gain)))
            moved = len(surf)
            log.info("noise %.3g box units (%.2f spacings): %d surface constraints moved onto local quadric fits of %d points "
                     "(median |offset| %.3g); their noise %.3g", noise, noise / spacing, moved, k, float(np.median(np.abs(offset))),
                     constraint_noise)
    elif adaptive:
        idx, surf = _thin_flat(box, idx, options.surface_adaptive, noise, seed)
    seen = None
    if data.cameras is not None:
        from o3drbf.constraints.visibility import exterior_constraints

        try:
            ext_data, info = exterior_constraints(
                norm.inverse(surf), data.cameras, offset=options.exterior_offset / norm.scale, ratio=max(options.exterior_ratio, 1e-9),
                seed=seed, occluder=pts if occluder is None else occluder,
                point_camera=None if data.point_camera is None else data.point_camera[idx],
            )
        except ValueError as exc:
            if data.camera_source:
                raise ValueError(f"{data.camera_source}: {exc}") from None
            raise
        ext = norm.forward(ext_data) if options.exterior_ratio > 0 else np.zeros((0, 3))
        seen = [int(v) for v in info["seen"]]
    else:
        n_ext = int(round(options.exterior_ratio * len(idx)))
        ext = exterior_from_normals(surf, data.normals[idx], options.exterior_offset, n_ext, seed=seed, reference=box)
    sph = bounding_sphere(box, options.sphere_count)
    constraints = Constraints.concat(
        Constraints.of_kind(surf, SURFACE, 0.0),
        Constraints.of_kind(ext, EXTERIOR, 0.0),
        Constraints.of_kind(sph, SPHERE, 0.0),
    )
    log.info("%d points -> %d surface, %d exterior, %d sphere constraints; mean spacing %.4f (box units)",
             len(pts), len(surf), len(ext), len(sph), spacing)
    lo, hi = data.bounds
    pad = 0.05 * float((hi - lo).max())
    return ConstraintSet(constraints, norm, np.asarray(idx), spacing, seen, np.stack([lo - pad, hi + pad]), options.exterior_offset,
                         bool(data.normals_estimated), noise, constraint_noise, moved)


def _thin_flat(box: np.ndarray, idx: np.ndarray, tolerance: float, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The uniform subset ``idx`` thinned where the surface is flat (:func:`o3drbf.constraints.adaptive.adaptive_subset`)."""
    from o3drbf.constraints.adaptive import MAX_FACTOR, adaptive_subset

    kept = adaptive_subset(box, idx, tolerance, MAX_FACTOR, noise=noise if np.isfinite(noise) else 0.0, seed=seed)
    log.info("surface_adaptive %g: %d of %d surface constraints kept (fewer where the surface is flat)", tolerance, len(kept), len(idx))
    return kept, box[kept]
