"""The whole job: :func:`reconstruct` runs the stages in the data's order, timing each, and gathers the :class:`~o3drbf.pipeline.records.Report`."""

from __future__ import annotations

import logging
import time

from o3drbf.constraints.core import Constraints
from o3drbf.mesh.metrics import drop_specks
from o3drbf.options import SPECK_SPACINGS, Options, auto_resolution
from o3drbf.pipeline.constraints import build_constraints
from o3drbf.pipeline.fitting import check_fit_memory, early_fit_check, fit_surface, mesh_cells
from o3drbf.pipeline.meshing import check_voxel_size, colour, extraction_bounds, mesh_confidence, mesh_lattice_box, mesh_surface
from o3drbf.pipeline.normals import check_given_normals, ensure_normals
from o3drbf.pipeline.outliers import remove_outliers
from o3drbf.pipeline.parameters import choose_parameters
from o3drbf.pipeline.read import drop_cameras_within_data, merge_repeated
from o3drbf.pipeline.records import Reconstruction, Report, StageTimer
from o3drbf.pipeline.register import register_scans
from o3drbf.pointset import PointSet
from o3drbf.prep.normalize import check_spans_volume
from o3drbf.startup import ready_numba_in_background

__all__ = ["reconstruct"]

log = logging.getLogger("o3drbf")


def reconstruct(points, normals=None, *, cameras=None, point_camera=None, colors=None, options: Options | None = None,
                extract_mesh: bool = True, seed: int = 0, progress: bool = False, **option_values) -> Reconstruction:
    """Reconstruct a closed surface from points (with normals or cameras).

    Parameters
    ----------
    points : (N, 3) array_like, open3d.geometry.PointCloud, open3d.t.geometry.PointCloud or PointSet
        Surface samples.  A point cloud's normals and colours are used when present.
    normals : (N, 3) array_like, optional
        Outward normals.  Without them (and without cameras) normals are
        estimated and oriented with Open3D, and a log message says so.
    cameras : sequence of Camera, CameraSet, or path, optional
        The cameras (or scanners) that saw the points: exterior constraints
        go toward every camera with an unobstructed view of a point, and
        points in another camera's observed free space are outliers.
    point_camera : (N,) int array_like, optional
        Index of the camera that produced each point (-1 unknown).
    colors : (N, 3) array_like, optional
        Per-point colours: the mesh is coloured from them.
    options : Options, optional
        All options, grouped by stage; default :class:`o3drbf.options.Options`
        (built from :data:`o3drbf.options.DEFAULTS`).
    extract_mesh : bool
        Run marching cubes (else ``mesh`` is None).
    seed : int
        Seed for every random choice: same input, same output.
    progress : bool
        Progress bars on long steps.
    **option_values
        Any key of :data:`o3drbf.options.DEFAULTS` (``surface_count=5000``,
        ``kernel="gaussian"``, ``delta=4``, ``outliers="none"``,
        ``resolution=256``, ...), applied over ``options``.  ``basis`` is
        another name for ``kernel``.

    Returns
    -------
    Reconstruction

    Raises
    ------
    ValueError
        Empty, NaN or too few points, wrong shapes, unknown
        options, parameters out of range or not belonging to the kernel:
        all before any costly step.
    RuntimeError
        No surface found.

    Notes
    -----
    Data are mapped into a 2x2x2 box (delta, tau, lambda and offsets refer
    to it); everything returned is back in the input's coordinates.  The
    fit solves the regularized saddle-point system

        [ Phi + diag(lambda)   Q ] [ w ]   [ y ]
        [ Q^T                  0 ] [ p ] = [ 0 ]

    with y = 0 at surface constraints and -1 at exterior ones, so that
    f(c_i) = y_i - lambda_i w_i.

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import o3drbf
    >>> result = o3drbf.reconstruct(points, normals, surface_count=200, resolution=20)
    >>> result.mesh.is_watertight(), result.report.surface_constraints
    (True, 204)
    >>> bool(abs(result.surface(points)).max() < 0.01)  # f = 0 on the points (data units)
    True
    """
    t_start = time.perf_counter()
    if "extract" in option_values:  # the older keyword
        extract_mesh = bool(option_values.pop("extract"))
    opts = Options.create(options, **option_values).validate()
    stages = StageTimer()
    ready_numba_in_background()  # Numba's set-up beside the stages before its first compiled kernel
    with stages.stage("read"):
        data = points if isinstance(points, PointSet) else PointSet.create(points, normals, cameras=cameras, point_camera=point_camera, colors=colors)
        data, merged = merge_repeated(data)
        check_spans_volume(data.points)
        if extract_mesh:
            check_voxel_size(opts.extract.voxel_size, extraction_bounds(data, opts.extract))
        data, cameras_dropped = drop_cameras_within_data(data)
    n_input = len(data) + merged
    early_fit_check(data.points, opts, extract_mesh, seed=seed)  # seconds: before the costly stages
    registration = None
    if data.point_camera is not None:  # scans known: they may be registered to each other
        with stages.stage("register"):
            data, registration = register_scans(data, opts.registration, seed=seed)
    with stages.stage("outliers"):
        data, outliers = remove_outliers(data, opts.outliers, seed=seed)
    with stages.stage("normals"):
        data, normal_check = check_given_normals(data, seed=seed)
        data, estimated = ensure_normals(data, seed=seed)
    with stages.stage("constraints"):
        cset = build_constraints(data, opts.constraints, seed=seed)
    with stages.stage("parameters"):
        params = choose_parameters(data, cset, opts.parameters, seed=seed, confidence=outliers.confidence)
    plan = check_fit_memory(cset, params, opts.fit, opts.extract if extract_mesh else None)  # seconds, before the fit
    with stages.stage("fit"):
        surface, sol, robust = fit_surface(cset, params, opts.fit, progress=progress, checked=plan is not None,
                                           resolution=mesh_cells(opts.extract, cset) if extract_mesh else None,
                                           lattice=mesh_lattice_box(cset, opts.extract) if extract_mesh else None)
    surface.metadata["seed"] = seed
    mesh, specks = None, 0
    if extract_mesh:
        with stages.stage("extract"):
            mesh = mesh_surface(surface, opts.extract, progress=progress, arrays=True)  # Open3D's mesh made when first asked for
            mesh, specks = drop_specks(mesh, SPECK_SPACINGS * cset.spacing / cset.normalization.scale)
            if specks:
                log.info("removed %d speck(s) under %g constraint spacings across", specks, SPECK_SPACINGS)
        if data.colors is not None:
            with stages.stage("colour"):
                mesh = colour(mesh, data)
    norm = cset.normalization
    fitted = Constraints(cset.constraints.points, cset.constraints.values, params.smoothing, cset.constraints.kind)
    if robust is not None:
        fitted = robust.pop("constraints")
    used = Constraints(norm.inverse(fitted.points), fitted.values, fitted.smoothing, fitted.kind)
    confidence, trimmed = None, 0
    if mesh is not None and opts.confidence.wanted:
        with stages.stage("confidence"):
            confidence, mesh, trimmed = mesh_confidence(surface, mesh, used, cset.spacing / norm.scale, opts.confidence)
    counts = cset.constraints.counts()
    report = Report(
        points=len(data),
        input_points=n_input,
        duplicates_merged=merged,
        registration=None if registration is None else {
            "applied": registration.applied, "scans": registration.scans, "before": registration.before, "after": registration.after,
            "largest_motion": float(registration.motion.max()) if registration.applied else 0.0, "rounds": registration.rounds,
            "reason": registration.reason},
        outliers_removed=outliers.removed,
        outlier_method=outliers.method,
        outlier_reason=outliers.reason,
        normals_estimated=estimated,
        normals_repaired=f"{normal_check.action}: {normal_check.reason}" if normal_check is not None and normal_check.changed else "",
        cameras=0 if data.cameras is None else len(data.cameras),
        cameras_dropped=cameras_dropped,
        points_seen_per_camera=cset.points_seen_per_camera,
        surface_constraints=counts["surface"],
        exterior_constraints=counts["exterior"],
        sphere_constraints=counts["sphere"],
        mean_spacing_box=cset.spacing,
        mean_spacing=cset.spacing / norm.scale,
        noise=cset.noise / norm.scale,
        constraint_noise=cset.constraint_noise / norm.scale,
        denoised=cset.denoised,
        basis=repr(params.kernel),
        parameters={**params.kernel.params, "lambda_surface": params.lambda_surface, "lambda_exterior": params.lambda_exterior},
        parameter_source=params.source,
        auto=params.auto,
        solver=sol.method,
        iterations=sol.iterations,
        residual=sol.residual,
        robust=robust,
        constraints_seconds=stages.seconds("constraints"),
        solve_seconds=sol.seconds,
        extract_seconds=stages.seconds("extract"),
        total_seconds=time.perf_counter() - t_start,
        specks_removed=specks,
        vertices=None if mesh is None else len(mesh.vertices),
        triangles=None if mesh is None else len(mesh.triangles),
        resolution=None if mesh is None or opts.extract.voxel_size is not None else (
            auto_resolution(cset.spacing) if opts.extract.resolution == "auto" else int(opts.extract.resolution)),
        stages=stages.timings,
        confidence=None if confidence is None else {**confidence.summary(), "trim": opts.confidence.trim, "triangles_removed": trimmed},
    )
    return Reconstruction(surface, mesh, used, sol, report, opts, confidence, data.points)
