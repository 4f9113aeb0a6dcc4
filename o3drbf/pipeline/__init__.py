"""Points in, implicit surface and mesh out: :func:`reconstruct` as named stages.

The data's path, each stage a public function that can be called alone::

    data = PointSet.create(points, normals, cameras=...)        # read (validated once)
    data, registration = register_scans(data, options.registration)  # scans registered to each other (with cameras)
    data, outliers = remove_outliers(data, options.outliers)    # outliers
    data, check = check_given_normals(data)                     # given normals checked, repaired when wrong
    data, estimated = ensure_normals(data)                      # normals, when neither normals nor cameras
    cset = build_constraints(data, options.constraints)         # constraints (normalized box)
    params = choose_parameters(data, cset, options.parameters)  # kernel and smoothing
    surface, solution, robust = fit_surface(cset, params, options.fit)   # fit
    mesh = mesh_surface(surface, options.extract)               # extract
    mesh = colour(mesh, data)                                   # colour
    conf, mesh, removed = mesh_confidence(surface, mesh, constraints, spacing, options.confidence)  # confidence, trim (when asked)

:func:`reconstruct` runs them in that order and returns a
:class:`Reconstruction` with a typed :class:`Report` (counts, parameters and
where they came from, seconds and peak memory per stage).

One module per stage, in the data's order: :mod:`~o3drbf.pipeline.read`
(repeats merged, cameras inside the data dropped),
:mod:`~o3drbf.pipeline.register`, :mod:`~o3drbf.pipeline.outliers`,
:mod:`~o3drbf.pipeline.normals`, :mod:`~o3drbf.pipeline.constraints`,
:mod:`~o3drbf.pipeline.parameters`, :mod:`~o3drbf.pipeline.fitting` (with
the memory checks before it), :mod:`~o3drbf.pipeline.meshing` (extract,
colour, confidence); :mod:`~o3drbf.pipeline.records` holds what they hand
each other and the report, :mod:`~o3drbf.pipeline.run` the whole job.  Every
public name is importable from ``o3drbf.pipeline``.
"""

from __future__ import annotations

from o3drbf.options import DEFAULTS
from o3drbf.pipeline.constraints import build_constraints
from o3drbf.pipeline.fitting import (EARLY_CHECK_MIN, EARLY_CHECK_SLACK, check_fit_memory, early_fit_check, fit, fit_surface,
                                     surface_of)
from o3drbf.pipeline.meshing import MIN_VOXEL_CELLS, check_voxel_size, colour, extraction_bounds, mesh_confidence, mesh_surface
from o3drbf.pipeline.normals import check_given_normals, ensure_normals, estimate_normals
from o3drbf.pipeline.outliers import remove_outliers
from o3drbf.pipeline.parameters import choose_parameters
from o3drbf.pipeline.read import MIN_DISTINCT_POINTS, drop_cameras_within_data, merge_repeated
from o3drbf.pipeline.records import (ConstraintSet, OutlierReport, Parameters, Reconstruction, Report, StageTimer, StageTiming,
                                     peak_rss_mb)
from o3drbf.pipeline.register import register_scans
from o3drbf.pipeline.run import reconstruct

__all__ = [
    "reconstruct",
    "Reconstruction",
    "Report",
    "StageTiming",
    "StageTimer",
    "OutlierReport",
    "ConstraintSet",
    "Parameters",
    "merge_repeated",
    "drop_cameras_within_data",
    "register_scans",
    "remove_outliers",
    "ensure_normals",
    "check_given_normals",
    "estimate_normals",
    "build_constraints",
    "choose_parameters",
    "fit",
    "surface_of",
    "check_fit_memory",
    "early_fit_check",
    "fit_surface",
    "check_voxel_size",
    "extraction_bounds",
    "mesh_surface",
    "colour",
    "mesh_confidence",
    "peak_rss_mb",
    "DEFAULTS",
    "EARLY_CHECK_MIN",
    "EARLY_CHECK_SLACK",
    "MIN_DISTINCT_POINTS",
    "MIN_VOXEL_CELLS",
]
