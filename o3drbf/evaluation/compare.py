"""Run several reconstruction methods on the same points and compare them.

    o3drbf compare INPUT [--cameras F] [--truth MESH] [--methods ...] [-o OUT_DIR]

Methods (:data:`METHODS`): the three o3drbf bases (``multiorder``,
``thinplate``, ``gaussian``) and Open3D's reconstructions run the way a
user would run them (``poisson`` on the raw points, ``poisson-tutorial`` as
Open3D's tutorial runs it, ``bpa`` ball pivoting, ``alpha`` shapes):

- normals: the given ones; otherwise Open3D estimates them (30 nearest
  neighbours) and orients them -- toward the camera that saw each point (or
  the nearest camera) when cameras are given, otherwise consistently over
  the neighbour graph and then outward (:func:`o3drbf.pipeline.estimate_normals`);
- Poisson (raw points): octree depth ``poisson_depth`` (8) and optional
  density trimming (``density_quantile``, 0 keeps the closed surface);
- Poisson (tutorial): Open3D's statistical outlier removal first
  (:data:`TUTORIAL`: 20 neighbours, 2 standard deviations), normals as above
  on the points kept (the cloud's own normals when it has them), the same
  depth, then the vertices below the 5 % density quantile removed (never
  closed), as ``benchmarks/paper/robustness.py`` runs it;
- ball pivoting: radii ``[1, 2, 4] x`` the mean nearest-neighbour spacing;
- alpha shapes: ``alpha = 3 x`` the mean spacing.

A method that fails (Open3D raises, or returns an empty mesh) gives a row
with an ``error`` and no measures, instead of stopping the comparison.

Memory: ``peak_bytes`` is the peak of Python-level allocations during the
method, as :mod:`tracemalloc` traces them.  NumPy arrays are counted (NumPy
reports its buffers to tracemalloc); memory allocated inside Open3D's or
Numba's compiled code is *not*, so for the Open3D methods it is a lower
bound.  ``rss_peak_mb`` (``comparison.md``'s one memory column, "Peak
memory (MB)") sees every allocation, Open3D's too:
the peak of the process's resident set above its level when the method
started, sampled with psutil by a background thread at the sampler's ``interval``
(None where psutil cannot read it; allocations shorter than one interval can be missed, and
pages freed earlier but kept by the allocator are not counted again).
Times are wall-clock seconds with tracemalloc on.

Outputs (:func:`write_tables`, :func:`picture`): ``comparison.md`` for people
(human column names with units, one line of shared settings above the table,
notes under it), ``comparison.csv``/``.json`` with the raw :data:`COLUMNS`,
and ``comparison.png``: one row per method and one column per view
(:data:`VIEWS`, one from below), the input points and the reference in
their own rows, titles with the table's numbers, meshes coloured by their
distance to the reference on one shared range.
"""

from __future__ import annotations

import math
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np

from o3drbf.evaluation.tables import (COLUMNS, HUMAN_COLUMNS, LABELS, TABLE_NOTES, VIEWS, colour_range, markdown_table, method_label,
                                      picture, picture_panels, row_title, settings_line, write_tables)
from o3drbf.options import COMPARE_PEERS, COMPARE_TUTORIAL, CompareOptions, compare_methods
from o3drbf.prep.sampling import mean_spacing
from o3drbf.validation import as_points, check_number

__all__ = [
    "METHODS",
    "PEERS",
    "available_methods",
    "run_method",
    "compare",
    "compare_with_meshes",
    "write_tables",
    "picture",
    "picture_panels",
    "row_title",
    "markdown_table",
    "settings_line",
    "method_label",
    "colour_range",
    "LABELS",
    "HUMAN_COLUMNS",
    "VIEWS",
    "TABLE_NOTES",
    "parse_methods",
    "COLUMNS",
    "TUTORIAL",
    "UP_AXES",
    "CompareOptions",
]

#: Open3D's reconstructions run beside o3drbf's kernels (:data:`o3drbf.options.COMPARE_PEERS`).
PEERS = COMPARE_PEERS

#: How ``poisson-tutorial`` runs Poisson (:data:`o3drbf.options.COMPARE_TUTORIAL`).
TUTORIAL = COMPARE_TUTORIAL


def available_methods() -> tuple[str, ...]:
    """Every registered o3drbf kernel (:data:`o3drbf.rbf.kernels.KERNELS`), then the peers."""
    from o3drbf.rbf.kernels import KERNELS

    return (*KERNELS, *PEERS)


#: The methods at import time (kernels registered later are found by :func:`available_methods`).
METHODS = available_methods()

_BPA_RADII = (1.0, 2.0, 4.0)
#: ``up`` of :class:`~o3drbf.options.CompareOptions` -> the axis (the picture's ``viewup``).
UP_AXES = {f"{sign}{axis}": tuple(float(s * (i == k)) for k in range(3)) for i, axis in enumerate("xyz") for sign, s in (("", 1), ("-", -1))}
_ALPHA_FACTOR = 3.0
_NORMAL_K = 30


# --------------------------------------------------------------------------
# inputs


def parse_methods(methods) -> tuple[str, ...]:
    """Method names from a comma-separated string or a sequence (:func:`o3drbf.options.compare_methods`).

    Raises ``ValueError`` naming the unknown ones and listing the valid ones.
    """
    return compare_methods(methods)


def _camera_list(cameras):
    if cameras is None:
        return None
    if isinstance(cameras, (str, Path)):
        from o3drbf.cameras.model import load_cameras

        cameras = load_cameras(cameras)
    cams = list(cameras)
    return cams or None


def open3d_normals(points, cameras=None, point_camera=None, k: int = _NORMAL_K) -> np.ndarray:
    """Normals the way an Open3D user gets them.

    Open3D estimate (``k`` nearest neighbours) and consistent tangent-plane
    orientation, then:

    - without cameras, flipped outward as a whole
      (:func:`o3drbf.pipeline.estimate_normals`);
    - with cameras, flipped as a whole so that most normals face their
      nearest camera (the centre; against the viewing direction for direction
      sensors); and where ``point_camera`` says which camera saw a point, that
      normal is flipped to face that camera.  (Flipping every normal toward
      its nearest camera alone goes wrong where the nearest camera does not
      see the point, e.g. inside a torus's hole.)
    """
    cams = _camera_list(cameras)
    pts = as_points(points, min_count=4)
    if cams is None:
        from o3drbf.pipeline import estimate_normals

        return estimate_normals(pts, k=k)
    import open3d as o3d

    k = min(int(k), len(pts) - 1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
    consistent = True
    try:
        pcd.orient_normals_consistent_tangent_plane(min(k, 15))
    except RuntimeError:  # degenerate neighbour graphs: per point only
        consistent = False
    n = np.asarray(pcd.normals).copy()
    dirs = np.empty((len(cams), len(pts), 3))
    dist = np.empty((len(cams), len(pts)))
    for c, cam in enumerate(cams):
        dirs[c], dist[c] = cam.toward(pts)
    idx = np.arange(len(pts))
    facing = np.einsum("ij,ij->i", n, dirs[np.argmin(dist, axis=0), idx])
    if consistent:
        if facing.mean() < 0:
            n = -n
    else:
        n[facing < 0] *= -1
    if point_camera is not None:
        pc = np.asarray(point_camera).reshape(-1)
        if pc.shape == (len(pts),):
            seen = pc >= 0
            flip = seen.copy()
            flip[seen] = np.einsum("ij,ij->i", n[seen], dirs[pc[seen], idx[seen]]) < 0
            n[flip] *= -1
    return n


# --------------------------------------------------------------------------
# running one method


def _open3d_cloud(points, normals):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=float)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=float))
    return pcd


def _run(name, points, normals, cameras, options: CompareOptions, seed: int, point_camera, spacing):
    import open3d as o3d

    if name not in PEERS:
        # Exactly what `o3drbf reconstruct` runs: the o3drbf rows' Options, with the kernel named.
        from o3drbf.pipeline import reconstruct

        result = reconstruct(points, normals, cameras=cameras, point_camera=point_camera if cameras is not None else None,
                             options=options.o3drbf, kernel=name, seed=seed)
        return result.mesh
    if name == "poisson-tutorial":
        return _poisson_tutorial(points, normals, cameras, options, point_camera)
    if normals is None:
        normals = open3d_normals(points, cameras, point_camera)
    spacing = spacing or mean_spacing(points)
    if name == "poisson":
        from o3drbf.evaluation.peers import poisson

        return poisson(points, normals, depth=options.poisson_depth, density_quantile=options.density_quantile)
    pcd = _open3d_cloud(points, normals)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if name == "bpa":
            radii = o3d.utility.DoubleVector([r * spacing for r in _BPA_RADII])
            mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
        elif name == "alpha":
            mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pcd, _ALPHA_FACTOR * spacing)
        else:  # pragma: no cover - names are checked before
            raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(available_methods())}")
    mesh.compute_vertex_normals()
    return mesh


def _poisson_tutorial(points, normals, cameras, options: CompareOptions, point_camera):
    """Poisson as Open3D's tutorial runs it: outliers removed, normals (given or estimated on what is left), density trim."""
    from o3drbf.evaluation.peers import poisson
    from o3drbf.prep.outliers import statistical_outliers

    keep, _ = statistical_outliers(points, TUTORIAL["nb_neighbors"], TUTORIAL["std_ratio"])
    pts = points[keep]
    if normals is not None:
        nrm = np.asarray(normals, dtype=float)[keep]
    else:
        pc = None if point_camera is None else np.asarray(point_camera).reshape(-1)[keep]
        nrm = open3d_normals(pts, cameras, pc)
    return poisson(pts, nrm, depth=options.poisson_depth, density_quantile=TUTORIAL["density_quantile"])


def run_method(name: str, points, normals=None, cameras=None, *, options: CompareOptions | None = None, seed: int = 0, point_camera=None,
               spacing: float | None = None, **overrides):
    """Run one method on the points.

    Parameters
    ----------
    name : str
        One of :data:`METHODS`.
    points : (N, 3) array_like
    normals : (N, 3) array_like, optional
        Outward normals.  Without them the o3drbf bases estimate their own
        (or use the cameras); the Open3D methods use :func:`open3d_normals`.
    cameras : sequence of Camera, CameraSet or camera file, optional
    options : CompareOptions, optional
        ``poisson_depth`` and ``density_quantile`` (raw Poisson), and the
        o3drbf rows' :class:`~o3drbf.options.Options` (``options.o3drbf``).
    seed : int
        o3drbf's sampling seed.
    point_camera : (N,) int array, optional
        The camera that saw each point (-1: unknown).
    spacing : float, optional
        The mean nearest-neighbour spacing (computed when absent): ball
        pivoting's radii are ``(1, 2, 4) x`` it, the alpha shape's alpha ``3 x`` it.
    **overrides
        Flat option names over ``options`` (:meth:`CompareOptions.create`).

    Returns
    -------
    mesh : open3d.geometry.TriangleMesh
    seconds : float
        Wall-clock time of the method (normal estimation included).
    peak_bytes : int
        Peak Python/NumPy allocation during the method (tracemalloc; memory
        allocated inside Open3D's C++ code is not seen).

    Raises
    ------
    ValueError
        Unknown method name; whatever the method raises (Open3D failures
        come through as ``RuntimeError``), and ``RuntimeError`` when it
        returns a mesh without triangles.
    """
    (name,) = parse_methods([name])
    opts = CompareOptions.create(options, **overrides) if overrides or options is None else options
    pts = as_points(points, min_count=4)
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base, _ = tracemalloc.get_traced_memory()
    t0 = time.perf_counter()
    try:
        mesh = _run(name, pts, normals, cameras, opts, seed, point_camera, spacing)
        seconds = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        if not was_tracing:
            tracemalloc.stop()
    if mesh is None or len(mesh.triangles) == 0:
        raise RuntimeError(f"{name} produced no triangles")
    return mesh, float(seconds), int(max(peak - base, 0))


# --------------------------------------------------------------------------
# comparing


class _RssPeak:
    """Peak resident-set growth while the ``with`` block runs (psutil's RSS,
    sampled every ``interval`` s); ``None`` where psutil cannot read it."""

    def __init__(self, interval: float = 0.005):
        import psutil

        self.interval = interval
        self.peak_bytes = None
        self._stop = threading.Event()
        self._process = psutil.Process()
        self._errors = (psutil.Error, OSError)

    def _rss(self):
        try:
            return int(self._process.memory_info().rss)
        except self._errors:
            return None

    def _poll(self):
        while not self._stop.wait(self.interval):
            self._high = max(self._high, self._rss() or 0)

    def __enter__(self):
        self._base = self._rss()
        if self._base is not None:
            self._high = self._base
            self._thread = threading.Thread(target=self._poll, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._base is not None:
            self._stop.set()
            self._thread.join()
            self._high = max(self._high, self._rss() or 0)
            self.peak_bytes = self._high - self._base
        return False


def _finite(x):
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def _measure(row, mesh, points, truth, threshold, n_samples, seed):
    from o3drbf.mesh import metrics

    rep = metrics.mesh_report(mesh)
    row.update(
        triangles=rep["triangles"],
        vertices=rep["vertices"],
        watertight=rep["watertight"],
        components=rep["components"],
        euler_characteristic=int(rep["euler_characteristic"]),
        genus=rep["genus"],
    )
    fit = metrics.fitness_error(points, mesh)
    row.update(fitness_mean=_finite(fit["mean"]), fitness_rms=_finite(fit["rms"]))
    try:
        row["average_curvature"] = _finite(metrics.average_curvature(mesh))
    except ValueError:
        row["average_curvature"] = None
    if truth is not None:
        ch = metrics.chamfer(mesh, truth, n_samples=n_samples, seed=seed)
        fs = metrics.f_score(mesh, truth, threshold, n_samples=n_samples, seed=seed)
        row.update(
            chamfer_l1=_finite(ch["l1"]),
            chamfer_l2=_finite(ch["l2"]),
            hausdorff=_finite(ch["hausdorff"]),
            f_score=_finite(fs["f"]),
            precision=_finite(fs["precision"]),
            recall=_finite(fs["recall"]),
            f_threshold=float(threshold),
            normal_consistency=_finite(metrics.normal_consistency(mesh, truth, n_samples=n_samples, seed=seed)),
        )


def _check_truth(truth):
    from o3drbf.mesh.arrays import mesh_arrays

    verts, _ = mesh_arrays(truth, "truth")
    return verts


def compare_with_meshes(points, normals=None, cameras=None, truth=None, *, options: CompareOptions | None = None, seed: int = 0,
                        point_camera=None, **overrides):
    """As :func:`compare`, and also the meshes: ``(rows, {name: mesh or None})``."""
    opts = CompareOptions.create(options, **overrides).validate()
    names = parse_methods(opts.methods) if opts.methods is not None else available_methods()
    pts = as_points(points, min_count=4)
    if normals is not None:
        normals = np.asarray(normals, dtype=float)
        if normals.shape != pts.shape or not np.isfinite(normals).all():
            raise ValueError(f"normals must be a finite {pts.shape} array like the points, got {normals.shape}")
    seed = check_number("seed", seed, low=0, integer=True)
    cams = _camera_list(cameras)
    threshold = None
    if truth is not None:
        tv = _check_truth(truth)
        threshold = 0.01 * float(np.linalg.norm(tv.max(axis=0) - tv.min(axis=0)))
    run = dict(options=opts, seed=seed, point_camera=point_camera, spacing=mean_spacing(pts))
    open3d_nrm = normals
    rows, meshes = [], {}
    for name in names:
        row = dict.fromkeys(COLUMNS)
        row["method"] = name
        mesh = None
        try:
            nrm, normal_seconds = normals, 0.0
            if name in ("poisson", "bpa", "alpha"):
                if open3d_nrm is None:  # estimated once, shared by the Open3D methods; timed in the first
                    t0 = time.perf_counter()
                    open3d_nrm = open3d_normals(pts, cams, point_camera)
                    normal_seconds = time.perf_counter() - t0
                nrm = open3d_nrm
            with _RssPeak() as rss:
                mesh, seconds, peak = run_method(name, pts, nrm, cams, **run)
            seconds += normal_seconds
            row.update(seconds=round(seconds, 4), peak_mb=round(peak / 2**20, 2), rss_peak_mb=None if rss.peak_bytes is None else round(rss.peak_bytes / 2**20, 2))
            _measure(row, mesh, pts, truth, threshold, opts.n_samples, seed)
        except Exception as exc:  # one failing method must not stop the others
            row["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
        rows.append(row)
        meshes[name] = mesh
    return rows, meshes


def compare(points, normals=None, cameras=None, truth=None, *, options: CompareOptions | None = None, seed: int = 0, point_camera=None,
            **overrides) -> list[dict]:
    """Run each method on the same points and measure the results.

    Parameters
    ----------
    points : (N, 3) array_like
    normals : (N, 3) array_like, optional
        Given to every method; without them each estimates its own
        (o3drbf: see :func:`o3drbf.reconstruct`; Open3D: :func:`open3d_normals`).
    cameras : sequence of Camera, CameraSet or camera file, optional
    truth : open3d.geometry.TriangleMesh, optional
        Ground truth: adds Chamfer L1/L2, Hausdorff, F-score at 1% of its
        bounding-box diagonal, and normal consistency.
    options : CompareOptions, optional
        The methods, Poisson's depth and trimming, the samples of the truth
        measures, and what the o3drbf rows run (``options.o3drbf``, an
        :class:`~o3drbf.options.Options`: reconstruct's defaults with
        :data:`o3drbf.options.COMPARE_OVERRIDES`).
    seed : int
        o3drbf's sampling seed, also the metrics' sampling seed.
    point_camera : (N,) int array, optional
        The camera that saw each point (-1: unknown).
    **overrides
        Flat option names over ``options`` (:meth:`CompareOptions.create`):
        ``methods``, ``poisson_depth``, ``n_samples``, ..., and any option
        of :func:`o3drbf.reconstruct` (``resolution``, ``surface_count``, ...).

    Returns
    -------
    list of dict
        One row per method with the keys :data:`COLUMNS` (``None`` where a
        value does not apply or the method failed; ``error`` says why).
        Watertight is :func:`o3drbf.mesh.metrics.mesh_report`'s (equal to
        Open3D's is_watertight(): closed, vertex-manifold, no self-intersections).

    Raises
    ------
    ValueError
        Unknown method names (the message lists the valid ones), bad points,
        normals or parameters, a truth mesh without triangles.

    Examples
    --------
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, seed=0)
    >>> rows = compare(points, normals, methods="multiorder,poisson", surface_count=300, resolution=24)
    >>> [r["method"] for r in rows]
    ['multiorder', 'poisson']
    """
    rows, _ = compare_with_meshes(points, normals, cameras, truth, options=options, seed=seed, point_camera=point_camera, **overrides)
    return rows
