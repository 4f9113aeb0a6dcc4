"""Outliers: points that cannot be on the surface dropped (free-space consistency with cameras, isolated points always)."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.options import OutlierOptions
from o3drbf.pipeline.records import OutlierReport
from o3drbf.pointset import PointSet

__all__ = ["remove_outliers"]

log = logging.getLogger("o3drbf")


def remove_outliers(data: PointSet, options: OutlierOptions = OutlierOptions(), *, seed: int = 0) -> tuple[PointSet, OutlierReport]:
    """Drop points that cannot be on the surface.

    Parameters
    ----------
    data : PointSet
    options : OutlierOptions
        ``method="auto"``: with cameras, free-space consistency (a point in
        space another camera saw through is removed; points confirmed by
        several cameras get more weight); without, an isolated-point rule
        that keeps separate objects.  "largest", "statistical", "none" as named.
    seed : int

    Returns
    -------
    PointSet, OutlierReport

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> from o3drbf import PointSet
    >>> data = PointSet.create(points, normals)
    >>> import numpy as np
    >>> from o3drbf import remove_outliers
    >>> noisy = PointSet.create(np.vstack([points, [[3.0, 3.0, 3.0]]]), np.vstack([normals, [[0.0, 0.0, 1.0]]]))
    >>> kept, report = remove_outliers(noisy)
    >>> len(kept.points), report.removed
    (600, 1)
    """
    options.validate()
    method = options.method
    n = len(data)
    if method == "none":
        return data, OutlierReport("none", 0, "none requested")
    if method == "auto":
        return _auto_outliers(data, seed=seed)
    from o3drbf.prep.outliers import largest_components, statistical_outliers

    if method == "largest":
        radius = options.radius if options.radius is not None else 3.0 * data.spacing
        keep, _ = largest_components(data.points, radius, keep=options.keep_components)
        reason = f"kept the {options.keep_components} largest component(s) under radius {radius:.3g}"
    else:
        keep, _ = statistical_outliers(data.points)
        reason = "Open3D statistical outlier removal"
    kept = data.subset(keep)
    removed = n - len(kept)
    if len(kept) < 10:
        raise ValueError(f"outlier removal ({method}) left {len(kept)} points; at least 10 needed (raise outlier_radius, or outliers='none')")
    log.info("outliers (%s): removed %d of %d points", method, removed, n)
    return kept, OutlierReport(method, removed, reason)


def _auto_outliers(data: PointSet, *, seed: int) -> tuple[PointSet, OutlierReport]:
    """The default rule (see :func:`remove_outliers`).

    With cameras: free-space consistency (:func:`o3drbf.constraints.freespace.free_space_check`:
    a point in front of what another camera observed along that ray, by more
    than the tolerance, is removed).  Always: the isolated-point rule
    (:func:`o3drbf.prep.outliers.isolated_points`: tiny groups and points
    hovering off their neighbours' plane; it never compares group sizes, so
    separate objects are kept).  How many outliers it catches and genuine
    points it removes: docs/data/design-measurements.md ("Outliers").
    """
    from o3drbf.prep.outliers import isolated_points

    n = len(data)
    remove = np.zeros(n, dtype=bool)
    parts, methods = [], []
    if data.cameras is not None:
        from o3drbf.constraints.freespace import free_space_check

        fs = free_space_check(data.points, data.cameras, data.point_camera)
        remove |= fs.outlier
        parts.append(f"{int(fs.outlier.sum()):,} in a camera's observed free space")
        methods.append("free-space")
    iso = isolated_points(data.points) & ~remove
    remove |= iso
    parts.append(f"{int(iso.sum()):,} isolated")
    methods.append("isolated")
    removed = int(remove.sum())
    if n - removed < 10:
        raise ValueError(f"outlier handling left {n - removed} points; at least 10 needed (use outliers='none' to keep every point)")
    log.info("outliers (auto): removed %d of %d points (%s)", removed, n, ", ".join(parts))
    kept = data.subset(~remove) if removed else data
    return kept, OutlierReport("+".join(methods), removed, ", ".join(parts))
