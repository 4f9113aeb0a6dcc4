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
"""

from __future__ import annotations

import logging
import resource
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np

from o3drbf.constraints.core import EXTERIOR, SPHERE, SURFACE, Constraints, bounding_sphere, exterior_from_normals, surface_constraints
from o3drbf.options import (AUTO_SIZES, DEFAULTS, DENOISE_MIN_NOISE, PAPER_VALUES, SPECK_SPACINGS, auto_resolution, auto_surface_count,
                            ConfidenceOptions, ConstraintOptions, ExtractOptions, FitOptions, Options, OutlierOptions, ParameterOptions,
                            RegistrationOptions)
from o3drbf.mesh.metrics import drop_specks
from o3drbf.pointset import PointSet
from o3drbf.prep.normalize import Normalization, check_spans_volume
from o3drbf.prep.sampling import mean_spacing
from o3drbf.rbf.kernels import Kernel, MultiOrder, kernel_class, make_kernel
from o3drbf.solvers import FAST_EVALUATION_MIN, Refitter, Solution, solve
from o3drbf.surface import ImplicitSurface
from o3drbf.validation import per_point

__all__ = [
    "reconstruct",
    "Reconstruction",
    "Report",
    "StageTiming",
    "OutlierReport",
    "ConstraintSet",
    "Parameters",
    "merge_repeated",
    "drop_cameras_within_data",
    "remove_outliers",
    "ensure_normals",
    "check_given_normals",
    "estimate_normals",
    "build_constraints",
    "choose_parameters",
    "fit",
    "fit_surface",
    "mesh_surface",
    "colour",
    "mesh_confidence",
    "DEFAULTS",
]

log = logging.getLogger("o3drbf")

#: Fewest distinct points a reconstruction takes (``PointSet.create``'s ``min_count``).
MIN_DISTINCT_POINTS = 10

#: Fewest marching-cubes cells along the extraction box's longest side a ``voxel_size`` may leave.
MIN_VOXEL_CELLS = 8


# --------------------------------------------------------------------------
# records


@dataclass
class StageTiming:
    """Seconds and peak memory of one stage.

    Attributes
    ----------
    name : str
        "read", "register" (with ``point_camera``), "outliers", "normals", "constraints", "parameters", "fit", "extract", "colour", "confidence" or "write".
    seconds : float
        Wall time.
    peak_mb : float
        The process's peak resident memory so far (MB), read at the stage's end.
    """

    name: str
    seconds: float
    peak_mb: float


@dataclass
class OutlierReport:
    """What the outlier stage removed, and why.

    Attributes
    ----------
    method : str
        The rule applied ("free-space", "isolated", "largest", "statistical" or "none").
    removed : int
        Points removed.
    reason : str
        One line for the summary.
    confidence : (N,) ndarray or None
        Per kept point, a trust in (0, 1] (lambda is divided by it), when the rule gives one.
    """

    method: str = "none"
    removed: int = 0
    reason: str = ""
    confidence: np.ndarray | None = None


@dataclass
class ConstraintSet:
    """The constraints in the normalized box, and where they came from.

    Attributes
    ----------
    constraints : Constraints
        Surface, exterior and sphere constraints (smoothing not yet set: 0).
    normalization : Normalization
        Data <-> box.
    surface_index : (S,) ndarray of int
        Which points of the PointSet are surface constraints.
    spacing : float
        Mean nearest-neighbour spacing of the surface constraints (box units).
    points_seen_per_camera : list of int or None
    bounds : (2, 3) ndarray
        The extraction box (data coordinates): the points' box padded by 5 %.
    exterior_offset : float
        Box units.
    normals_estimated : bool
    noise : float
        The points' noise across the surface (box units; NaN if not estimated).
    constraint_noise : float
        The surface constraints' noise after denoising (box units; = ``noise``
        when they were not moved).
    denoised : int
        Surface constraints moved onto local quadric fits (0: none).
    """

    constraints: Constraints
    normalization: Normalization
    surface_index: np.ndarray
    spacing: float
    points_seen_per_camera: list | None = None
    bounds: np.ndarray | None = None
    exterior_offset: float = 0.0
    normals_estimated: bool = False
    noise: float = float("nan")
    constraint_noise: float = float("nan")
    denoised: int = 0


@dataclass
class Parameters:
    """The kernel and the per-constraint smoothing chosen for a fit.

    Attributes
    ----------
    kernel : Kernel
    smoothing : (M,) ndarray
        lambda_i per constraint of the ConstraintSet (absolute).
    lambda_surface : float
        Median surface smoothing.
    lambda_exterior : float
        Absolute smoothing of exterior and sphere constraints (the option times phi(0)).
    source : dict
        For delta, tau, lambda_surface: "given", "auto" or "paper".
    auto : dict or None
        The automatic rule's inputs and reason.
    noise : float
        Estimated noise of the points across the surface (box units), or 0.
    """

    kernel: Kernel
    smoothing: np.ndarray
    lambda_surface: float
    lambda_exterior: float
    source: dict
    auto: dict | None = None
    noise: float = 0.0


@dataclass
class Report:
    """What :func:`reconstruct` did: what the command line's summary prints.

    Attributes
    ----------
    points : int
        Points used (after repairs and outlier removal).
    input_points : int
        Points given.
    duplicates_merged : int
        Exactly repeated points merged (their normals and colours averaged).
    registration : dict or None
        With cameras and ``point_camera``: whether the scans were moved
        (``applied``), how many, the median distance between overlapping
        scans ``before`` and ``after`` and the ``largest_motion`` (data
        units), and the ``reason``; None when registration did not run.
    outliers_removed : int
    outlier_method, outlier_reason : str
    normals_estimated : bool
    normals_repaired : str
        Empty when the given normals passed :func:`check_given_normals` (or
        none were given); else one line: what was wrong and what was done.
    cameras : int
        Cameras used.
    cameras_dropped : list of str
        Cameras given but not used: their centre lies within the data
        (:func:`drop_cameras_within_data`).
    points_seen_per_camera : list of int or None
    surface_constraints, exterior_constraints, sphere_constraints : int
    mean_spacing_box, mean_spacing : float
        Mean spacing of the surface constraints, box and data units.
    noise, constraint_noise : float
        Estimated noise across the surface of the points and of the surface
        constraints after denoising (data units; NaN when not estimated).
    denoised : int
        Surface constraints moved onto local quadric fits (``denoise``).
    basis : str
        The kernel, e.g. ``MultiOrder(delta=3.0, tau=0.01)``.
    parameters : dict
        Kernel parameters, lambda_surface, lambda_exterior.
    parameter_source : dict
    auto : dict or None
    solver : str
    iterations : int
    residual : float
    robust : dict or None
        Rounds, down-weighted and dropped constraints, the residual scale.
    constraints_seconds, solve_seconds, extract_seconds, total_seconds : float
    vertices, triangles : int or None
    specks_removed : int
        Mesh pieces under ``SPECK_SPACINGS`` constraint spacings across
        removed (:func:`o3drbf.mesh.metrics.drop_specks`): zero crossings of
        f around a single stray constraint.
    resolution : int or None
        Marching-cubes cells along the longest side (after "auto").
    stages : list of StageTiming
    confidence : dict or None
        With ``confidence`` or ``trim``: the per-vertex confidence's mean,
        min, q25 and median (over the final mesh), ``trim`` (the threshold or
        None) and ``triangles_removed``; None when not asked.
    """

    points: int = 0
    input_points: int = 0
    duplicates_merged: int = 0
    registration: dict | None = None
    outliers_removed: int = 0
    outlier_method: str = "none"
    outlier_reason: str = ""
    normals_estimated: bool = False
    normals_repaired: str = ""
    cameras: int = 0
    cameras_dropped: list = field(default_factory=list)
    points_seen_per_camera: list | None = None
    surface_constraints: int = 0
    exterior_constraints: int = 0
    sphere_constraints: int = 0
    mean_spacing_box: float = float("nan")
    noise: float = float("nan")
    constraint_noise: float = float("nan")
    denoised: int = 0
    mean_spacing: float = float("nan")
    basis: str = ""
    parameters: dict = field(default_factory=dict)
    parameter_source: dict = field(default_factory=dict)
    auto: dict | None = None
    solver: str = ""
    iterations: int = 0
    residual: float = float("nan")
    robust: dict | None = None
    constraints_seconds: float = 0.0
    solve_seconds: float = 0.0
    extract_seconds: float = 0.0
    total_seconds: float = 0.0
    vertices: int | None = None
    triangles: int | None = None
    specks_removed: int = 0
    resolution: int | None = None
    stages: list = field(default_factory=list)
    confidence: dict | None = None

    def as_dict(self) -> dict:
        """The report as a plain dict (JSON-ready apart from NaN)."""
        return asdict(self)

    def __getitem__(self, key: str):
        """``report["points"]``: dict-style access to the fields."""
        try:
            return getattr(self, key)
        except AttributeError:
            raise KeyError(key) from None

    def get(self, key: str, default=None):
        return getattr(self, key, default)


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
    report : Report
        Counts, parameters, timings: what the command line prints.
    options : Options
        The options used.
    confidence : VertexConfidence or None
        Per vertex of ``mesh`` (:func:`mesh_confidence`), when ``confidence``
        or ``trim`` was asked; else None.
    points : (N, 3) ndarray or None
        The points kept (data coordinates): after merging repeats,
        registering the scans and removing outliers; what the fitness error
        is measured over.
    """

    surface: ImplicitSurface
    mesh: object
    constraints: Constraints
    solution: Solution
    report: Report
    options: Options = field(default_factory=Options)
    confidence: object = None
    points: np.ndarray | None = None

    def plot(self, *, constraints: bool = False, compare: dict | None = None, title: str | None = None, **options):
        """Show the mesh with PyVista: inline in Jupyter (static PNG, or interactive with trame), else a window or offscreen.

        Parameters
        ----------
        constraints : bool
            Draw the surface (red) and exterior (blue) constraints over the mesh
            (not the bounding-sphere ones, which would shrink the mesh in the frame).
        compare : dict of str to open3d.geometry.TriangleMesh, optional
            Other reconstructions of the same data, one panel each beside this one (linked cameras).
        title : str, optional
            Default: "o3drbf (<triangles> triangles)".
        **options
            ``show``, ``screenshot`` (a .png also written), ``backend``,
            ``window_size``, ``view``, ``viewup``: see :func:`o3drbf.pictures.plot`.

        Returns
        -------
        pyvista.Plotter or None
            The open plotter with ``show=False``, else None.

        Raises
        ------
        ValueError
            No mesh (``reconstruct(..., extract_mesh=False)``): mesh it first with :func:`mesh_surface`.
        """
        from o3drbf.pictures import plot

        if self.mesh is None:
            raise ValueError("plot: this reconstruction has no mesh (extract_mesh=False); mesh it with o3drbf.mesh_surface first")
        c = self.constraints
        return plot(
            self.mesh,
            points=c.select(SURFACE) if constraints else None,
            exterior=c.select(EXTERIOR) if constraints else None,
            compare=compare,
            title=title if title is not None else f"o3drbf ({len(self.mesh.triangles):,} triangles)",
            **options,
        )

    @property
    def stats(self) -> Report:
        """The report (kept for code written against the older dict: ``stats["points"]`` works)."""
        return self.report


class _Stages:
    """Times each stage and records the peak memory after it."""

    def __init__(self):
        self.timings: list[StageTiming] = []

    @contextmanager
    def stage(self, name: str):
        t0 = time.perf_counter()
        yield
        self.timings.append(StageTiming(name, time.perf_counter() - t0, peak_rss_mb()))

    def seconds(self, name: str) -> float:
        return sum(t.seconds for t in self.timings if t.name == name)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------
# stages


def merge_repeated(data: PointSet) -> tuple[PointSet, int]:
    """Merge exactly repeated points (real pipelines produce them), averaging their normals and colours.

    Returns the PointSet and how many rows were merged (logged when any).
    """
    from o3drbf.prep.duplicates import merge_duplicates

    points, normals, colors, point_camera, merged = merge_duplicates(data.points, data.normals, data.colors, data.point_camera)
    if not merged:
        return data, 0
    if len(points) < MIN_DISTINCT_POINTS:
        n = len(points) + merged
        what = "copies of one point" if len(points) == 1 else f"copies of {len(points)} points"
        raise ValueError(f"all {n:,} points are {what}: {merged:,} repeats removed, {len(points)} distinct left; at least "
                         f"{MIN_DISTINCT_POINTS} distinct points are needed (check how the file was exported)")
    log.warning("%d repeated point(s) merged", merged)
    kept = PointSet.create(points, normals, cameras=data.cameras, point_camera=point_camera, colors=colors, source=data.source)
    return kept, merged


def drop_cameras_within_data(data: PointSet) -> tuple[PointSet, list[str]]:
    """Drop the cameras whose centre lies within the data: at a point, or closer to one than the visibility test can resolve.

    A camera that close (within the ray margin of
    :mod:`o3drbf.constraints.visibility`, ``VOXEL_SPACINGS * MARGIN_VOXELS``
    mean point spacings) would be taken to see every point near it with
    nothing tested in between, and would place exterior (free-space)
    constraints along the surface or inside the object; a camera exactly at
    a point has no direction toward it at all.  Such a camera is a wrong
    pose (or a sensor position that is not a viewpoint): it is dropped, its
    points are kept as points of unknown camera, and a warning names it.

    Parameters
    ----------
    data : PointSet

    Returns
    -------
    PointSet
        Without those cameras (the same object when none is dropped).
    list of str
        The dropped cameras, e.g. ``"camera 3 (img03.png)"``.

    Raises
    ------
    ValueError
        Every camera lies within the data.
    """
    if data.cameras is None:
        return data, []
    from dataclasses import replace

    from o3drbf.constraints.visibility import MARGIN_VOXELS, VOXEL_SPACINGS

    clearance = VOXEL_SPACINGS * MARGIN_VOXELS * data.spacing
    with_centre = [k for k, cam in enumerate(data.cameras) if cam.kind != "direction"]
    if not with_centre:
        return data, []
    distance, _ = data.kdtree.query(np.array([data.cameras[k].center for k in with_centre]))
    inside = {k: float(d) for k, d in zip(with_centre, distance) if d <= clearance}
    if not inside:
        return data, []
    labels = [f"camera {k}" + (f" ({data.cameras[k].name})" if data.cameras[k].name else "") for k in inside]
    spacings = max(inside.values()) / data.spacing
    limit = clearance / data.spacing
    if len(inside) == len(data.cameras):
        raise ValueError(f"every camera lies within the data (at most {spacings:.2g} point spacings from a point, closer than the "
                         f"{limit:.3g} the visibility test resolves): no free space can be proved; check the camera poses "
                         "(x_cam = R X + t, looking along +z), or give normals and leave --cameras out")
    one = len(labels) == 1
    log.warning("%s %s %.2g point spacings from a data point, closer than the %.3g the visibility test resolves (inside the data): "
                "%s free-space constraints dropped, %s points kept; check %s pose", ", ".join(labels), "lies" if one else "lie (at most)",
                spacings, limit, "its" if one else "their", "its" if one else "their", "its" if one else "their")
    kept = [k for k in range(len(data.cameras)) if k not in inside]
    point_camera = None
    if data.point_camera is not None:
        new = np.full(len(data.cameras), -1, dtype=np.int64)
        new[kept] = np.arange(len(kept))
        point_camera = np.where(data.point_camera >= 0, new[np.maximum(data.point_camera, 0)], -1)
        point_camera = None if (point_camera < 0).all() else point_camera
    return replace(data, cameras=[data.cameras[k] for k in kept], point_camera=point_camera, _cache=data._cache), labels


def register_scans(data: PointSet, options: RegistrationOptions = RegistrationOptions(), *, seed: int = 0):
    """Move each scan rigidly onto the others, with its camera, when that makes them consistent.

    Parameters
    ----------
    data : PointSet
        Needs cameras and ``point_camera`` (the scan of each point); without
        them nothing is done.
    options : RegistrationOptions
    seed : int

    Returns
    -------
    PointSet
        The moved points and cameras (the same object when nothing moved).
    Registration or None
        What :func:`o3drbf.prep.registration.refine_registration` found
        (None when it did not run: ``register="none"``, no cameras or no
        ``point_camera``).
    """
    options.validate()
    if options.method == "none" or data.cameras is None or data.point_camera is None:
        return data, None
    from dataclasses import replace

    from o3drbf.prep.registration import apply_transforms, refine_registration

    toward = np.zeros_like(data.points)
    for k, camera in enumerate(data.cameras):
        sel = data.point_camera == k
        if sel.any():
            toward[sel] = camera.toward(data.points[sel])[0]
    reg = refine_registration(data.points, data.point_camera, len(data.cameras), toward=toward, min_gain=options.min_gain, seed=seed)
    log.info("registration: %s", reg.reason)
    if not reg.applied:
        return data, reg
    cameras = [camera.moved(T) for camera, T in zip(data.cameras, reg.transforms)]
    normals = None if data.normals is None else apply_transforms(data.normals, data.point_camera, reg.transforms, vectors=True)
    moved = replace(data, points=apply_transforms(data.points, data.point_camera, reg.transforms), normals=normals,
                    cameras=cameras, _cache={})
    return moved, reg


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
    separate objects are kept).  Measured (docs/robustness-notes.md): 97-100 %
    of free-space spurious returns and about 91 % of uniform outliers caught,
    at most 0.05 % of genuine points removed.
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


def estimate_normals(points, k: int = 30, seed: int = 0) -> np.ndarray:
    """Outward unit normals for a point cloud without them (Open3D).

    Normals are estimated from ``k`` nearest neighbours, oriented
    consistently over a neighbour graph, then flipped as a whole so that most
    point away from the centroid (right for closed, roughly star-shaped
    objects; give normals or cameras when that does not hold).

    Parameters
    ----------
    points : (N, 3) array_like
    k : int
    seed : int
        Unused (Open3D's estimate is deterministic); kept for symmetry.

    Returns
    -------
    (N, 3) ndarray
    """
    import open3d as o3d

    from o3drbf.validation import as_points

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
    # The tangent-plane orientation is consistent within each connected piece
    # of the neighbour graph, not across pieces: flip each piece on its own so
    # that its normals point away from its own centroid (separate objects,
    # e.g. stacked tori, are each oriented outward).
    labels = _neighbour_components(pts, k=min(k, 10))
    for c in np.unique(labels):
        sel = labels == c
        if np.einsum("ij,ij->i", n[sel], pts[sel] - pts[sel].mean(axis=0)).mean() < 0:
            n[sel] = -n[sel]
    return n


def _neighbour_components(points: np.ndarray, k: int) -> np.ndarray:
    """Connected components of the symmetric k-nearest-neighbour graph (labels)."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    _, nb = cKDTree(points).query(points, k=k + 1)
    rows = np.repeat(np.arange(len(points)), k)
    graph = sparse.coo_matrix((np.ones(rows.size), (rows, nb[:, 1:].ravel())), shape=(len(points), len(points)))
    return connected_components(graph, directed=False)[1]


def check_given_normals(data: PointSet, *, seed: int = 0):
    """Check the given normals against the points (and cameras), and repair them when they are wrong.

    See :func:`o3drbf.prep.orientation.check_normals`: normals that point
    opposite ways between neighbours are re-oriented consistently, normals
    that all point inward are flipped, and with ``point_camera`` a normal
    facing away from its camera is flipped.  A repair is logged as a warning.

    Parameters
    ----------
    data : PointSet
    seed : int

    Returns
    -------
    PointSet
        ``data`` itself when there were no given normals or they passed.
    NormalCheck or None
        None without given normals.
    """
    if data.normals is None or data.normals_estimated:
        return data, None
    from o3drbf.prep.orientation import check_normals

    normals, check = check_normals(data.points, data.normals, data.cameras, data.point_camera, seed=seed)
    if not check.changed:
        return data, check
    log.warning("normals repaired (%s): %s", check.action, check.reason)
    return data.with_normals(normals), check


def ensure_normals(data: PointSet, *, seed: int = 0) -> tuple[PointSet, bool]:
    """Estimate normals when there are neither normals nor cameras.

    Returns the PointSet (with normals) and whether they were estimated.
    """
    if data.normals is not None or data.cameras is not None:
        return data, False
    log.info("no normals given: estimating and orienting normals with Open3D (30 neighbours)")
    return data.with_normals(estimate_normals(data.points, seed=seed), estimated=True), True


def build_constraints(data: PointSet, options: ConstraintOptions = ConstraintOptions(), *, seed: int = 0) -> ConstraintSet:
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

    Returns
    -------
    ConstraintSet
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
    norm = Normalization.from_points(pts)
    box = norm.forward(pts)
    idx = surface_constraints(box, count=count, radius=options.surface_radius, seed=seed)
    surf = box[idx]
    noise, constraint_noise, moved = float("nan"), float("nan"), 0
    spacing = mean_spacing(surf) if len(surf) > 1 else float("nan")
    if options.denoise and len(surf) > 10 and len(box) > len(surf):
        from o3drbf.constraints.parameters import estimate_noise
        from o3drbf.prep.smoothing import neighbourhood_size, project_to_local_surface

        noise = estimate_noise(box, seed=seed)
        constraint_noise = noise
        denoise = options.denoise is True or noise > DENOISE_MIN_NOISE * spacing
        if denoise and auto_count and auto_surface_count(len(data), noisy=True) < len(idx):
            idx = surface_constraints(box, count=auto_surface_count(len(data), noisy=True), seed=seed)
            surf = box[idx]
            spacing = mean_spacing(surf)
            log.info("noisy points: %d surface constraints (points / %d up to %d, else points / %d)", len(idx),
                     AUTO_SIZES["points_per_constraint"], AUTO_SIZES["noisy_full_rate_max"], AUTO_SIZES["noisy_points_per_constraint"])
        if denoise:
            k = neighbourhood_size(len(box), len(surf))
            moved_data, offset, gain = project_to_local_surface(pts, norm.inverse(surf), k=k, tree=data.kdtree, noise=noise / norm.scale)
            surf, offset = norm.forward(moved_data), offset * norm.scale
            # what is left of the noise: the fits' own standard deviation (RMS over the constraints)
            constraint_noise = noise * float(np.sqrt(np.mean(gain * gain)))
            moved = len(surf)
            log.info("noise %.3g box units (%.2f spacings): %d surface constraints moved onto local quadric fits of %d points "
                     "(median |offset| %.3g); their noise %.3g", noise, noise / spacing, moved, k, float(np.median(np.abs(offset))),
                     constraint_noise)
    seen = None
    if data.cameras is not None:
        from o3drbf.constraints.visibility import exterior_constraints

        try:
            ext_data, info = exterior_constraints(
                norm.inverse(surf), data.cameras, offset=options.exterior_offset / norm.scale, ratio=max(options.exterior_ratio, 1e-9),
                seed=seed, occluder=pts, point_camera=None if data.point_camera is None else data.point_camera[idx],
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


def choose_parameters(data: PointSet, cset: ConstraintSet, options: ParameterOptions = ParameterOptions(), *, seed: int = 0,
                      confidence=None) -> Parameters:
    """The kernel and per-constraint smoothing.

    Values given explicitly always win.  With ``options.auto`` the
    multi-order parameters left at None come from the surface constraints'
    spacing and the points' noise (:mod:`o3drbf.constraints.parameters`);
    otherwise from the paper (:data:`o3drbf.options.PAPER_VALUES`).

    Parameters
    ----------
    data : PointSet
        The points the constraints were built from.
    cset : ConstraintSet
    options : ParameterOptions
    seed : int
    confidence : (N,) array_like, optional
        Per point of ``data``, a trust in (0, 1]: its surface smoothing is
        divided by it.

    Returns
    -------
    Parameters
    """
    options.validate()
    n = len(data)
    if isinstance(options.kernel, Kernel):
        cls, given = type(options.kernel), dict(options.kernel.params)
    else:
        cls, given = kernel_class(options.kernel), options.kernel_params()
    use_auto = bool(options.auto) and issubclass(cls, MultiOrder)
    names = ("delta", "tau") if issubclass(cls, MultiOrder) else ()
    source = {name: "given" if (name in given) else ("auto" if use_auto else "paper") for name in names}
    source["lambda_surface"] = "given" if options.lambda_surface is not None else ("auto" if use_auto else "paper")
    box = cset.normalization.forward(data.points)
    chosen = None
    noise = 0.0
    if use_auto and "auto" in source.values():
        from o3drbf.constraints.parameters import estimate_noise, parameters_from

        noise = cset.noise if np.isfinite(cset.noise) else estimate_noise(box, seed=seed)
        # The smoothing follows the noise the constraints carry: after denoising, theirs, not the points'.
        chosen = parameters_from(cset.spacing, cset.constraint_noise if cset.denoised else noise, cset.normalization.scale,
                                 denoised=bool(cset.denoised), point_spacing=data.spacing * cset.normalization.scale)
        log.info("automatic parameters: %s", chosen.reason)
        given = {**{"delta": chosen.delta, "tau": chosen.tau}, **given}
    if isinstance(options.kernel, Kernel):
        kernel = options.kernel
    else:
        defaults = {k: PAPER_VALUES[k] for k in cls.parameter_names() if k in PAPER_VALUES}
        kernel = make_kernel(cls.name, **{**defaults, **given})
    _check_width(kernel, options, cset.spacing)
    if source["lambda_surface"] == "auto":
        lam_points = np.full(n, chosen.lambda_relative * kernel.value_at_zero)
    else:
        lam_points = per_point("lambda_surface", PAPER_VALUES["lambda_surface"] if options.lambda_surface is None else options.lambda_surface, n)
    if confidence is not None:
        lam_points = lam_points / np.clip(np.asarray(confidence, dtype=float), 1e-3, 1.0)
    lam_e = float(options.lambda_exterior) * kernel.value_at_zero
    c = cset.constraints
    smoothing = np.where(c.kind == SURFACE, 0.0, lam_e)
    smoothing[c.kind == SURFACE] = lam_points[cset.surface_index]
    return Parameters(kernel, smoothing, float(np.median(lam_points)), lam_e, source,
                      None if chosen is None else chosen.as_dict(), float(noise))


def _check_width(kernel: Kernel, options: ParameterOptions, spacing: float) -> None:
    """Refuse a given Gaussian width under one surface-constraint spacing (box units): the bumps would not overlap."""
    sigma = kernel.params.get("sigma")
    given = options.sigma is not None or isinstance(options.kernel, Kernel)
    if sigma is None or not given or not np.isfinite(spacing) or sigma >= spacing:
        return
    raise ValueError(f"--sigma {sigma:g} is narrower than the surface constraints' spacing {spacing:.3g} (box units): the Gaussians "
                     f"do not overlap and leave no surface between the constraints; give --sigma of at least {spacing:.2g} "
                     f"(about {8 * spacing:.2g}, 8 spacings, suits most data)")


def fit(constraints: Constraints, kernel: Kernel, normalization: Normalization, solver: str = "auto", progress: bool = False,
        **solve_options) -> tuple[ImplicitSurface, Solution]:
    """Fit an implicit surface to constraints given in the normalized box.

    Parameters
    ----------
    constraints : Constraints
        Points, target values and smoothing, in the box.
    kernel : Kernel
    normalization : Normalization
        Data <-> box, kept by the surface.
    solver : {"auto", "dense", "iterative", "fast"}
    progress : bool
    **solve_options
        Passed to :func:`o3drbf.solvers.solve`.

    Returns
    -------
    ImplicitSurface, Solution
    """
    sol = solve(kernel, constraints.points, constraints.values, constraints.smoothing, method=solver, progress=progress, **solve_options)
    return surface_of(sol, constraints.points, kernel, normalization), sol


def surface_of(sol: Solution, centres, kernel: Kernel, normalization: Normalization) -> ImplicitSurface:
    """The implicit surface of a solution at its centres (box units); fast-solved large ones evaluate by fast sums."""
    surf = ImplicitSurface(kernel, centres, sol.weights, sol.poly, normalization)
    if sol.method == "fast" and len(centres) >= FAST_EVALUATION_MIN:
        from o3drbf.solvers.fast import make_evaluator

        surf.evaluator = make_evaluator(kernel, centres, sol.weights)
    return surf


def check_fit_memory(cset: ConstraintSet, params: Parameters, options: FitOptions = FitOptions(),
                     extract: ExtractOptions | None = None) -> dict | None:
    """Refuse, before the fit starts, a fast fit (and its meshing) that would not fit in memory.

    The need is :func:`o3drbf.solvers.fast.memory_plan`'s for these
    centres (products, preconditioner, Krylov basis, then the evaluator and
    marching cubes at the extraction's resolution); the limit 80 % of the
    memory available now.  Dense solves are checked by the solver itself
    (also up front).

    Parameters
    ----------
    cset : ConstraintSet
    params : Parameters
    options : FitOptions
    extract : ExtractOptions, optional
        The meshing to plan for (None: no mesh).

    Returns
    -------
    dict or None
        The plan (None when the solve is not fast).

    Raises
    ------
    MemoryRefusal
        With ``cli_hint`` naming a ``--surface-count`` that would fit (when
        one would) and ``--tiles auto``.
    """
    from o3drbf.options import extraction_memory
    from o3drbf.rbf.sums import polynomial_basis
    from o3drbf.solvers import MemoryRefusal, choose_method, fast

    pts = cset.constraints.points
    n = len(pts)
    m = polynomial_basis(pts[:1], params.kernel.polynomial_degree).shape[1]
    method = options.solver if options.solver != "auto" else choose_method(n + m)[0]
    if method != "fast" or not params.kernel.positive_definite:
        return None
    extraction, box = 0, None
    if extract is not None:
        res = extract.resolution if extract.resolution != "auto" else auto_resolution(cset.spacing)
        extraction = extraction_memory(int(res)) if extract.voxel_size is None else 0
        if cset.bounds is not None:
            b = cset.normalization.forward(np.asarray(cset.bounds, dtype=float))
            box = np.stack([b.min(axis=0), b.max(axis=0)])
    try:
        return fast.check_memory(n, eps=fast.product_tolerance(1e-6), kernel=params.kernel, centres=pts,
                                 evaluation=extract is not None and n >= FAST_EVALUATION_MIN, box=box, extraction_bytes=extraction)
    except MemoryRefusal as exc:
        surface = cset.constraints.counts()["surface"]
        hints = []
        if exc.fraction:
            count = int(exc.fraction * surface)
            digits = max(len(str(count)) - 2, 0)
            hints.append(f"--surface-count {count // 10**digits * 10**digits}")
        hints.append("--tiles auto")
        exc.cli_hint = "pass " + " or ".join(hints)
        exc.what = f"a fast fit of {n:,} constraints ({surface:,} surface)" + (" and its mesh" if extract is not None else "")
        exc.args = (exc.message(),)
        raise


#: From this many expected constraints on, :func:`early_fit_check` estimates the fit's memory right
#: after reading (below it the stages before the fit take seconds anyway).
EARLY_CHECK_MIN = 50_000
#: :func:`early_fit_check` refuses only when its estimate exceeds the limit by this factor (it works
#: on a random subset of the points, not the constraints; :func:`check_fit_memory` decides the rest).
EARLY_CHECK_SLACK = 1.25


def early_fit_check(points, options: Options, extract: bool = True, seed: int = 0) -> None:
    """Refuse, seconds after reading, a fit that clearly would not fit in memory.

    The constraint count is the one the options will give (``surface_count``
    or ``"auto"`` or every point, plus exterior and sphere constraints); the
    memory is :func:`o3drbf.solvers.fast.memory_plan`'s for a seeded random
    subset of the points of that size, in the normalized box, with the
    multi-order kernel of the paper's values.  It refuses only above
    ``EARLY_CHECK_SLACK`` times the limit and only from ``EARLY_CHECK_MIN``
    constraints, for a fast solve of a multi-order kernel; the exact check
    (:func:`check_fit_memory`) comes before the fit.

    Raises
    ------
    MemoryRefusal
        With ``cli_hint`` naming a ``--surface-count`` that would fit (when
        one would) and ``--tiles auto``.
    """
    from o3drbf.solvers import MemoryRefusal, fast
    from o3drbf.solvers.base import memory_limit_or_default

    c, p = options.constraints, options.parameters
    n_points = len(points)
    if c.surface_radius is not None or options.fit.solver == "dense":
        return
    kernel = p.kernel if isinstance(p.kernel, Kernel) else None
    if kernel is None and str(p.kernel) != "multiorder":
        return
    if kernel is not None and not isinstance(kernel, MultiOrder):
        return
    surface = n_points if c.surface_count is None else (
        auto_surface_count(n_points) if c.surface_count == "auto" else min(int(c.surface_count), n_points))
    total = int(round(surface * (1 + c.exterior_ratio))) + int(c.sphere_count)
    if total < EARLY_CHECK_MIN:
        return
    norm = Normalization.from_points(points)
    rng = np.random.default_rng(seed)
    centres = norm.forward(np.asarray(points, dtype=float)[np.sort(rng.choice(n_points, min(total, n_points), replace=False))])
    if total > len(centres):  # exterior constraints beside the surface ones
        extra = centres[rng.choice(len(centres), total - len(centres))] + rng.normal(scale=c.exterior_offset, size=(total - len(centres), 3))
        centres = np.vstack([centres, extra])
    kernel = kernel or MultiOrder(PAPER_VALUES["delta"], PAPER_VALUES["tau"])
    limit = memory_limit_or_default()
    extraction = 0
    if extract and options.extract.voxel_size is None:
        from o3drbf.options import extraction_memory

        res = options.extract.resolution
        extraction = extraction_memory(AUTO_SIZES["max_resolution"] if res == "auto" else int(res))
    try:
        fast.check_memory(total, eps=fast.product_tolerance(1e-6), memory_limit=int(EARLY_CHECK_SLACK * limit), kernel=kernel,
                          centres=centres, evaluation=extract, extraction_bytes=extraction)
    except MemoryRefusal as exc:
        hints = []
        fraction = fast.fitting_fraction(kernel, centres, limit, eps=fast.product_tolerance(1e-6), evaluation=extract,
                                         extraction_bytes=extraction, limit=limit)
        if fraction:
            count = int(fraction * surface)
            digits = max(len(str(count)) - 2, 0)
            hints.append(f"--surface-count {count // 10**digits * 10**digits}")
        hints.append("--tiles auto")
        raise MemoryRefusal(f"a fast fit of about {total:,} constraints ({surface:,} surface)" + (" and its mesh" if extract else ""),
                            exc.need, limit, fraction=fraction, cli_hint="pass " + " or ".join(hints)) from None


def fit_surface(cset: ConstraintSet, params: Parameters, options: FitOptions = FitOptions(), *, progress: bool = False,
                checked: bool = False):
    """Solve for the implicit function; robustly reweighted by default.

    Parameters
    ----------
    cset : ConstraintSet
    params : Parameters
    options : FitOptions
    progress : bool
    checked : bool
        :func:`check_fit_memory` has passed: the solver does not check again.

    Returns
    -------
    surface : ImplicitSurface
    solution : Solution
    robust : dict or None
        Rounds, down-weighted and dropped constraints, scale, seconds, and
        ``constraints`` (those of the final fit); None when not robust.
    """
    options.validate()
    c = cset.constraints
    constraints = Constraints(c.points, c.values, params.smoothing, c.kind)
    # One factorization for the first fit and every robust refit (Woodbury updates of the dense one).
    session = Refitter(params.kernel, constraints.points, constraints.values, constraints.smoothing, method=options.solver,
                       checked=checked, progress=progress)

    def refit(smoothing=None):
        keep, solution = session.solve(smoothing)
        return surface_of(solution, constraints.points[keep], params.kernel, cset.normalization), solution

    surface, sol = refit()
    robust = None
    if options.robust:
        from o3drbf.constraints.robust import robust_reweight

        # The residual scale never falls below half a constraint spacing, so
        # clean data are not reweighted (no refit when no residual reaches
        # Tukey's c times the scale).
        scale = max(params.noise, 0.5 * cset.spacing) if np.isfinite(cset.spacing) else params.noise
        surface, sol, rep = robust_reweight(
            lambda c: fit(c, params.kernel, cset.normalization, solver=options.solver, progress=progress),
            constraints, scale, first=(surface, sol), refit=refit,
        )
        robust = {"rounds": int(rep.rounds), "downweighted": int(rep.downweighted), "dropped": int(rep.dropped),
                  "scale": float(rep.scale), "seconds": float(rep.seconds), "constraints": rep.constraints}
        if rep.downweighted or rep.dropped:
            log.info("robust fit: %d round(s), %d constraints down-weighted, %d dropped (scale %.3g box units)",
                     rep.rounds, rep.downweighted, rep.dropped, rep.scale)
    surface.metadata = {
        "basis": params.kernel.to_dict(),
        "lambda_surface": params.lambda_surface,
        "lambda_exterior": params.lambda_exterior,
        "exterior_offset": cset.exterior_offset,
        "counts": cset.constraints.counts(),
        "mean_spacing": cset.spacing,
        "bounds": None if cset.bounds is None else cset.bounds.tolist(),
        "normals_estimated": cset.normals_estimated,
        "parameter_source": params.source,
    }
    log.info("solved %d constraints (%s) in %.2f s, relative residual %.1e", len(constraints), sol.method, sol.seconds, sol.residual)
    return surface, sol, robust


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


def _extraction_bounds(data: PointSet, options: ExtractOptions) -> np.ndarray:
    """The box marching cubes covers (data units): ``options.bounds``, else the points' box padded by 5 %."""
    if options.bounds is not None:
        return np.asarray(options.bounds, dtype=float)
    lo, hi = data.bounds
    pad = 0.05 * float((hi - lo).max())
    return np.stack([lo - pad, hi + pad])


def mesh_surface(surface: ImplicitSurface, options: ExtractOptions = ExtractOptions(), *, progress: bool = False):
    """Marching cubes of f = 0 (:func:`o3drbf.extract.extract_mesh`).

    Raises
    ------
    RuntimeError
        No zero crossing, with the likely cause.
    """
    from o3drbf.extract import extract_mesh

    options.validate()
    resolution = options.resolution
    if resolution == "auto":
        resolution = auto_resolution(float(surface.metadata.get("mean_spacing", float("nan"))))
    check_voxel_size(options.voxel_size, options.bounds if options.bounds is not None else surface.metadata.get("bounds"))
    try:
        return extract_mesh(surface, resolution=resolution, voxel_size=options.voxel_size, bounds=options.bounds, progress=progress)
    except RuntimeError as exc:
        lam = surface.metadata.get("lambda_surface", float("nan"))
        spacing = float(surface.metadata.get("mean_spacing", float("nan")))
        raise RuntimeError(
            f"{exc}. The fit has no zero crossing: the kernel {surface.kernel!r} may not suit the surface constraints' "
            f"spacing {spacing:.3g} (box units; leave --delta, --tau and --sigma out for the defaults), or smoothing may "
            f"swamp the data (lambda_surface {lam:g} vs phi(0) = {surface.kernel.value_at_zero:.3g}; lower lambda_surface, --lambda-surface), "
            "or check the normals/exterior constraints"
        ) from None


def colour(mesh, data: PointSet):
    """Per-vertex colour from the points' colours (nearest points, distance weighted); the mesh unchanged without them."""
    if mesh is None or data.colors is None:
        return mesh
    from o3drbf.mesh.color import color_mesh

    return color_mesh(mesh, points=data.points, colors=data.colors)


def mesh_confidence(surface: ImplicitSurface, mesh, constraints: Constraints, spacing: float | None = None,
                    options: ConfidenceOptions = ConfidenceOptions()):
    """Per-vertex confidence of the mesh (:func:`o3drbf.mesh.confidence.vertex_confidence`), and trimming by it.

    Parameters
    ----------
    surface : ImplicitSurface
    mesh : open3d.geometry.TriangleMesh or None
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
    """
    options.validate()
    if mesh is None or not options.wanted:
        return None, mesh, 0
    from o3drbf.mesh.confidence import trim_by_confidence, vertex_confidence

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


# --------------------------------------------------------------------------
# the whole job


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
    """
    t_start = time.perf_counter()
    if "extract" in option_values:  # the older keyword
        extract_mesh = bool(option_values.pop("extract"))
    opts = Options.create(options, **option_values).validate()
    stages = _Stages()
    with stages.stage("read"):
        data = points if isinstance(points, PointSet) else PointSet.create(points, normals, cameras=cameras, point_camera=point_camera, colors=colors)
        data, merged = merge_repeated(data)
        check_spans_volume(data.points)
        if extract_mesh:
            check_voxel_size(opts.extract.voxel_size, _extraction_bounds(data, opts.extract))
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
        surface, sol, robust = fit_surface(cset, params, opts.fit, progress=progress, checked=plan is not None)
    surface.metadata["seed"] = seed
    mesh, specks = None, 0
    if extract_mesh:
        with stages.stage("extract"):
            mesh = mesh_surface(surface, opts.extract, progress=progress)
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
