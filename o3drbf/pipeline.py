"""One entry point for the whole job: points in, implicit surface and mesh out."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from o3drbf.validation import as_points, as_vectors, check_number, per_point
from o3drbf.constraints.core import (
    EXTERIOR,
    SPHERE,
    SURFACE,
    Constraints,
    bounding_sphere,
    exterior_from_normals,
    surface_constraints,
)
from o3drbf.rbf.kernels import Kernel, make_kernel
from o3drbf.prep.normalize import Normalization
from o3drbf.prep.sampling import mean_spacing
from o3drbf.solvers import Solution, solve
from o3drbf.surface import ImplicitSurface

__all__ = ["reconstruct", "fit", "Reconstruction", "estimate_normals", "DEFAULTS"]

log = logging.getLogger("o3drbf")

#: Default parameters (the paper's, in the normalized 2x2x2 box).
DEFAULTS = {
    "basis": "multiorder",
    "delta": 10.0,
    "tau": 0.01,
    "sigma": 0.1,
    "lambda_surface": 1e-3,
    "lambda_exterior": 2.0,
    "surface_count": 3000,
    "exterior_ratio": 0.1,
    "exterior_offset": 0.05,
    "sphere_count": 64,
    "resolution": 128,
}


@dataclass
class Reconstruction:
    """What :func:`reconstruct` returns.

    Attributes
    ----------
    surface : ImplicitSurface
        Evaluate f and grad f anywhere (data coordinates); save/load.
    mesh : open3d.geometry.TriangleMesh or None
        The extracted iso-surface (data coordinates), None if ``extract=False``.
    constraints : Constraints
        The constraints used, in data coordinates.
    solution : Solution
        Solver record (method, residual, iterations, seconds).
    stats : dict
        Counts, spacing, timings: what the command line prints.
    """

    surface: ImplicitSurface
    mesh: object
    constraints: Constraints
    solution: Solution
    stats: dict = field(default_factory=dict)


def estimate_normals(points, k: int = 30, seed: int = 0) -> np.ndarray:
    """Outward unit normals for a point cloud without them (Open3D).

    Normals are estimated from ``k`` nearest neighbours, oriented
    consistently over a neighbour graph, then flipped as a whole so that most
    point away from the centroid (right for closed, roughly star-shaped
    objects; give normals or cameras when that does not hold).
    """
    import open3d as o3d

    pts = as_points(points, min_count=4)
    k = min(int(k), len(pts) - 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    try:
        pcd.orient_normals_consistent_tangent_plane(min(k, 15))
    except RuntimeError:  # degenerate neighbour graphs
        pcd.orient_normals_towards_camera_location(pts.mean(axis=0))
        return -np.asarray(pcd.normals)
    n = np.asarray(pcd.normals).copy()
    if np.einsum("ij,ij->i", n, pts - pts.mean(axis=0)).mean() < 0:
        n = -n
    return n


def fit(constraints: Constraints, kernel: Kernel, normalization: Normalization, solver: str = "auto", progress: bool = False, **solve_options) -> tuple[ImplicitSurface, Solution]:
    """Fit an implicit surface to constraints given in the normalized box."""
    sol = solve(kernel, constraints.points, constraints.values, constraints.smoothing, method=solver, progress=progress, **solve_options)
    surf = ImplicitSurface(kernel, constraints.points, sol.weights, sol.poly, normalization)
    from o3drbf.solvers import FAST_EVALUATION_MIN

    if sol.method == "fast" and len(constraints) >= FAST_EVALUATION_MIN:
        from o3drbf.solvers.fast import make_evaluator

        surf.evaluator = make_evaluator(kernel, constraints.points, sol.weights)
    return surf, sol


def reconstruct(
    points,
    normals=None,
    *,
    cameras=None,
    point_camera=None,
    outliers: str = "none",
    outlier_radius: float | None = None,
    keep_components: int = 1,
    basis: str = DEFAULTS["basis"],
    delta: float | None = None,
    tau: float | None = None,
    sigma: float = DEFAULTS["sigma"],
    lambda_surface=None,
    auto: bool = False,
    lambda_exterior: float = DEFAULTS["lambda_exterior"],
    surface_count: int | None = DEFAULTS["surface_count"],
    surface_radius: float | None = None,
    exterior_ratio: float = DEFAULTS["exterior_ratio"],
    exterior_offset: float = DEFAULTS["exterior_offset"],
    sphere_count: int = DEFAULTS["sphere_count"],
    solver: str = "auto",
    resolution: int = DEFAULTS["resolution"],
    voxel_size: float | None = None,
    bounds=None,
    extract: bool = True,
    seed: int = 0,
    progress: bool = False,
) -> Reconstruction:
    """Reconstruct a closed surface from points with normals.

    Parameters
    ----------
    points : (N, 3) array_like or open3d.geometry.PointCloud
        Surface samples.  A point cloud's normals are used when present.
    normals : (N, 3) array_like, optional
        Outward normals.  Without them (and without cameras, or a point cloud
        that has normals) normals are estimated and oriented with Open3D, and
        a log message says so.
    cameras : sequence of Camera, CameraSet, or path, optional
        The cameras (or scanners) that saw the points.  Exterior constraints
        are then placed toward every camera with an unobstructed view of a
        point (method.md section 4) instead of along normals.
    point_camera : (N,) int array_like, optional
        Index of the camera that produced each point (-1 unknown): such
        points are visible from it by definition.
    outliers : {"none", "largest", "statistical"}
        Keep the ``keep_components`` largest connected components under
        ``outlier_radius`` (default three mean spacings), or Open3D's
        statistical outlier removal.
    outlier_radius : float, optional
        Neighbourhood radius for ``outliers="largest"``, in data units.
    keep_components : int
        How many components ``outliers="largest"`` keeps.
    basis : {"multiorder", "thinplate", "gaussian"}
    delta, tau : float, optional
        Multi-order basis parameters (normalized box): delta in (0, 1e4],
        tau in (0, 10].  The paper: delta 5..40, tau 0.005..0.025.  None:
        chosen from the data when ``auto``, else the paper's 10 and 0.01.
    sigma : float
        Gaussian width (box units), for ``basis="gaussian"``.
    lambda_surface : float or (N,) array_like, optional
        Smoothing of surface constraints, >= 0 (0 interpolates); per input
        point if an array.  None: chosen from the data when ``auto``
        (multi-order basis), else the paper's 1e-3.
    auto : bool
        Choose the parameters left at None from the surface constraints'
        spacing and the points' noise (:mod:`o3drbf.constraints.parameters`).  Values given
        explicitly always win.  ``stats["parameters"]`` records the values
        used, ``stats["parameter_source"]`` where each came from ("given",
        "auto" or "paper") and ``stats["auto"]`` the rule's inputs and reason.
    lambda_exterior : float
        Smoothing of exterior constraints, >= 0.
    surface_count : int or None
        Poisson-disc subsample to about this many surface constraints (the
        paper: 2,000-3,000); None keeps every point (or uses ``surface_radius``).
    surface_radius : float, optional
        Poisson-disc radius (box units) instead of a count.
    exterior_ratio : float
        Exterior constraints per surface constraint, in [0, 1] (paper: 0.1).
    exterior_offset : float
        Distance of exterior constraints from the surface along the normal
        (box units), in (0, 0.5].
    sphere_count : int
        Exterior constraints on a sphere around the bounding box (0: none).
    solver : {"auto", "dense", "iterative", "fast"}
    resolution : int
        Marching-cubes cells along the longest side.
    voxel_size : float, optional
        Grid spacing in data units (overrides ``resolution``).
    bounds : (2, 3) array_like, optional
        Extraction box in data coordinates (default: the data's box, padded).
    extract : bool
        Run marching cubes (else ``mesh`` is None).
    seed : int
        Seed for every random choice: same input, same output.
    progress : bool
        Progress bars on long steps.

    Returns
    -------
    Reconstruction

    Raises
    ------
    ValueError
        Empty, NaN, too few or duplicated points, wrong shapes, parameters
        out of range.

    Notes
    -----
    Data are mapped into a 2x2x2 box (delta, tau, lambda and offsets refer
    to it); everything returned is back in the input's coordinates.
    """
    t_start = time.perf_counter()
    cloud_normals = None
    if hasattr(points, "points") and not isinstance(points, np.ndarray):
        if getattr(points, "has_normals", lambda: False)():
            cloud_normals = np.asarray(points.normals)
    pts = as_points(points, min_count=10, allow_duplicates=False)
    n = len(pts)
    if normals is None:
        normals = cloud_normals
    auto = bool(auto)
    use_auto = auto and str(basis).lower() == "multiorder"
    source = {
        name: "given" if value is not None else ("auto" if use_auto else "paper")
        for name, value in (("delta", delta), ("tau", tau), ("lambda_surface", lambda_surface))
    }
    # Validate the given values now (before any costly step); fill the rest later.
    make_kernel(basis, **_kernel_params(basis, DEFAULTS["delta"] if delta is None else delta, DEFAULTS["tau"] if tau is None else tau, sigma))
    lam_s = per_point("lambda_surface", DEFAULTS["lambda_surface"] if lambda_surface is None else lambda_surface, n)
    lam_e = check_number("lambda_exterior", lambda_exterior, low=0.0)
    exterior_ratio = check_number("exterior_ratio", exterior_ratio, low=0.0, high=1.0)
    exterior_offset = check_number("exterior_offset", exterior_offset, low=0.0, high=0.5, low_open=True)
    sphere_count = check_number("sphere_count", sphere_count, low=0, high=100000, integer=True)
    if surface_count is not None:
        surface_count = check_number("surface_count", surface_count, low=10, integer=True)
    if surface_radius is not None:
        surface_radius = check_number("surface_radius", surface_radius, low=0.0, high=2.0, low_open=True)
        surface_count = None
    elif surface_count is None:
        log.info("surface_count=None: every point is a surface constraint")

    cams, camera_source = _cameras(cameras)
    if point_camera is not None:
        point_camera = np.asarray(point_camera)
        if point_camera.shape != (n,) or not np.issubdtype(point_camera.dtype, np.integer):
            raise ValueError(f"point_camera must be an ({n},) integer array, got {point_camera.dtype} {point_camera.shape}")
        if cams is None:
            raise ValueError("point_camera needs cameras")
        if point_camera.max() >= len(cams) or point_camera.min() < -1:
            raise ValueError(f"point_camera values must be -1 or camera indices 0..{len(cams) - 1}")
    removed = 0
    if outliers != "none":
        keep = _remove_outliers(pts, outliers, outlier_radius, keep_components)
        removed = n - len(keep)
        pts = pts[keep]
        normals = None if normals is None else np.asarray(normals, dtype=float)[keep]
        lam_s = lam_s[keep]
        point_camera = None if point_camera is None else point_camera[keep]
        log.info("outliers (%s): removed %d of %d points", outliers, removed, n)
        n = len(pts)
        if n < 10:
            raise ValueError(f"outlier removal left {n} points; at least 10 needed (raise outlier_radius)")

    normals_estimated = normals is None and cams is None
    if normals_estimated:
        log.info("no normals given: estimating and orienting normals with Open3D (30 neighbours)")
        normals = estimate_normals(pts, seed=seed)
    nrm = None if normals is None else as_vectors(normals, n, name="normals")

    norm = Normalization.from_points(pts)
    box = norm.forward(pts)
    t0 = time.perf_counter()
    idx = surface_constraints(box, count=surface_count, radius=surface_radius, seed=seed)
    surf_pts = box[idx]
    camera_info = None
    if cams is not None:
        from o3drbf.constraints.visibility import exterior_constraints

        try:
            ext_data, camera_info = exterior_constraints(
                pts[idx],
                cams,
                offset=exterior_offset / norm.scale,
                ratio=max(exterior_ratio, 1e-9),
                seed=seed,
                occluder=pts,
                point_camera=None if point_camera is None else point_camera[idx],
            )
        except ValueError as exc:
            if camera_source:
                raise ValueError(f"{camera_source}: {exc}") from None
            raise
        ext = norm.forward(ext_data) if exterior_ratio > 0 else np.zeros((0, 3))
    else:
        n_ext = int(round(exterior_ratio * len(idx)))
        ext = exterior_from_normals(surf_pts, nrm[idx], exterior_offset, n_ext, seed=seed, reference=box)
    sph = bounding_sphere(box, sphere_count)
    spacing = mean_spacing(surf_pts) if len(surf_pts) > 1 else float("nan")
    chosen = None
    if use_auto and "auto" in source.values():
        from o3drbf.constraints.parameters import estimate_noise, parameters_from

        chosen = parameters_from(spacing, estimate_noise(box, seed=seed), norm.scale)
        log.info("automatic parameters: %s", chosen.reason)
        delta = chosen.delta if delta is None else delta
        tau = chosen.tau if tau is None else tau
    delta = DEFAULTS["delta"] if delta is None else delta
    tau = DEFAULTS["tau"] if tau is None else tau
    kernel = make_kernel(basis, **_kernel_params(basis, delta, tau, sigma))
    if source["lambda_surface"] == "auto":
        # The rule's lambda is relative to phi(0) of the kernel actually used.
        lam_s = np.full(n, chosen.lambda_relative * kernel.value_at_zero)
    constraints = Constraints.concat(
        Constraints.of_kind(surf_pts, SURFACE, lam_s[idx]),
        Constraints.of_kind(ext, EXTERIOR, lam_e),
        Constraints.of_kind(sph, SPHERE, lam_e),
    )
    t_constraints = time.perf_counter() - t0
    log.info(
        "%d points -> %d surface, %d exterior, %d sphere constraints; mean spacing %.4f (box units)",
        n, len(surf_pts), len(ext), len(sph), spacing,
    )

    surface, sol = fit(constraints, kernel, norm, solver=solver, progress=progress)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * float((hi - lo).max())
    surface.metadata = {
        "basis": kernel.to_dict(),
        "lambda_surface": float(np.median(lam_s)),
        "lambda_exterior": lam_e,
        "exterior_offset": exterior_offset,
        "counts": constraints.counts(),
        "mean_spacing": spacing,
        "seed": seed,
        "bounds": [(lo - pad).tolist(), (hi + pad).tolist()],
        "normals_estimated": normals_estimated,
        "parameter_source": source,
    }
    log.info("solved %d constraints (%s) in %.2f s, relative residual %.1e", len(constraints), sol.method, sol.seconds, sol.residual)

    mesh = None
    t_extract = 0.0
    if extract:
        from o3drbf.extract import extract_mesh

        t0 = time.perf_counter()
        try:
            mesh = extract_mesh(surface, resolution=resolution, voxel_size=voxel_size, bounds=bounds, progress=progress)
        except RuntimeError as exc:
            raise RuntimeError(
                f"{exc}. The fit has no zero crossing: smoothing may swamp the data "
                f"(lambda_surface {np.median(lam_s):g} vs phi(0) = {kernel.value_at_zero:.3g}); "
                "lower lambda_surface, or check the normals/exterior constraints"
            ) from None
        t_extract = time.perf_counter() - t0
    data_constraints = Constraints(norm.inverse(constraints.points), constraints.values, constraints.smoothing, constraints.kind)
    stats = {
        "points": n,
        "outliers_removed": removed,
        "normals_estimated": normals_estimated,
        "cameras": 0 if cams is None else len(cams),
        "points_seen_per_camera": None if camera_info is None else [int(v) for v in camera_info["seen"]],
        **{f"{k}_constraints": v for k, v in constraints.counts().items()},
        "mean_spacing_box": spacing,
        "mean_spacing": spacing / norm.scale,
        "basis": repr(kernel),
        "parameters": {**kernel.params, "lambda_surface": float(np.median(lam_s)), "lambda_exterior": lam_e},
        "parameter_source": source,
        "auto": None if chosen is None else chosen.as_dict(),
        "solver": sol.method,
        "iterations": sol.iterations,
        "residual": sol.residual,
        "constraints_seconds": t_constraints,
        "solve_seconds": sol.seconds,
        "extract_seconds": t_extract,
        "total_seconds": time.perf_counter() - t_start,
    }
    if mesh is not None:
        stats["vertices"] = len(mesh.vertices)
        stats["triangles"] = len(mesh.triangles)
    return Reconstruction(surface, mesh, data_constraints, sol, stats)


def _cameras(cameras):
    """(list of Camera or None, the file they came from or "") from None, a
    sequence of Camera, a CameraSet, or a camera file path."""
    if cameras is None:
        return None, ""
    if isinstance(cameras, (str, bytes)) or hasattr(cameras, "__fspath__"):
        from o3drbf.cameras.model import load_cameras

        cameras = load_cameras(cameras)
    source = str(getattr(cameras, "source", "") or "")
    cams = list(cameras)
    if not cams:
        raise ValueError(f"{source + ': ' if source else ''}cameras is empty; give at least one camera (or None to use normals)")
    return cams, source


def _remove_outliers(points, method: str, radius, keep_components: int) -> np.ndarray:
    from o3drbf.prep.outliers import largest_components, statistical_outliers

    if method == "largest":
        if radius is None:
            radius = 3.0 * mean_spacing(points)
        kept, _ = largest_components(points, radius, keep=keep_components)
        return kept
    if method == "statistical":
        kept, _ = statistical_outliers(points)
        return kept
    raise ValueError(f"outliers must be 'none', 'largest' or 'statistical', got {method!r}")


def _kernel_params(basis, delta, tau, sigma) -> dict:
    key = str(basis).lower()
    if key == "multiorder":
        return {"delta": delta, "tau": tau}
    if key == "gaussian":
        return {"sigma": sigma}
    return {}
