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

import argparse
import csv
import io as _io
import json
import math
import threading
import time
import tracemalloc
from pathlib import Path

import numpy as np

from o3drbf.options import DEFAULTS
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
    "main_compare",
    "add_compare_arguments",
    "parse_methods",
    "COLUMNS",
    "TUTORIAL",
]

#: Open3D's reconstructions run beside o3drbf's kernels.
PEERS = ("poisson", "poisson-tutorial", "bpa", "alpha")

#: How ``poisson-tutorial`` runs Poisson: Open3D's statistical outlier
#: removal (neighbours, standard deviations), then density trimming at this quantile.
TUTORIAL = {"nb_neighbors": 20, "std_ratio": 2.0, "density_quantile": 0.05}


def available_methods() -> tuple[str, ...]:
    """Every registered o3drbf kernel (:data:`o3drbf.rbf.kernels.KERNELS`), then the peers."""
    from o3drbf.rbf.kernels import KERNELS

    return (*KERNELS, *PEERS)


#: The methods at import time (kernels registered later are found by :func:`available_methods`).
METHODS = available_methods()

#: Table columns, in order (every row has every key; missing values are None).
COLUMNS = (
    "method",
    "seconds",
    "peak_mb",
    "rss_peak_mb",
    "triangles",
    "vertices",
    "watertight",
    "components",
    "euler_characteristic",
    "genus",
    "fitness_mean",
    "fitness_rms",
    "average_curvature",
    "chamfer_l1",
    "chamfer_l2",
    "hausdorff",
    "f_score",
    "precision",
    "recall",
    "f_threshold",
    "normal_consistency",
    "error",
)

_BPA_RADII = (1.0, 2.0, 4.0)
_UP = {f"{sign}{axis}": tuple(float(s * (i == k)) for k in range(3)) for i, axis in enumerate("xyz") for sign, s in (("", 1), ("-", -1))}
_ALPHA_FACTOR = 3.0
_NORMAL_K = 30


# --------------------------------------------------------------------------
# inputs


def parse_methods(methods) -> tuple[str, ...]:
    """Method names from a comma-separated string or a sequence.

    Raises ``ValueError`` naming the unknown ones and listing the valid ones.
    """
    if isinstance(methods, str):
        names = [m.strip().lower() for m in methods.split(",") if m.strip()]
    else:
        names = [str(m).strip().lower() for m in methods]
    valid = available_methods()
    if not names:
        raise ValueError(f"no methods given; valid methods: {', '.join(valid)}")
    unknown = [m for m in names if m not in valid]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, unknown))}; valid methods: {', '.join(valid)}")
    return tuple(dict.fromkeys(names))  # drop repeats, keep order


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


def _run(name, points, normals, cameras, options):
    import open3d as o3d

    seed = int(options.get("seed", 0))
    if name not in PEERS:
        # Exactly what `o3drbf reconstruct` runs: the one table of defaults, the
        # kernel named, and only the options given here.
        from o3drbf.options import DEFAULTS
        from o3drbf.pipeline import reconstruct

        kw = {k: options[k] for k in DEFAULTS if k in options and k != "kernel"}
        result = reconstruct(points, normals, cameras=cameras, point_camera=options.get("point_camera") if cameras is not None else None,
                             kernel=name, seed=seed, **kw)
        return result.mesh
    if name == "poisson-tutorial":
        return _poisson_tutorial(points, normals, cameras, options)
    if normals is None:
        normals = open3d_normals(points, cameras, options.get("point_camera"))
    spacing = options.get("spacing") or mean_spacing(points)
    if name == "poisson":
        from o3drbf.evaluation.peers import poisson

        return poisson(points, normals, depth=options.get("poisson_depth", 8), density_quantile=options.get("density_quantile", 0.0))
    pcd = _open3d_cloud(points, normals)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if name == "bpa":
            radii = o3d.utility.DoubleVector([r * spacing for r in options.get("bpa_radii", _BPA_RADII)])
            mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pcd, radii)
        elif name == "alpha":
            alpha = options.get("alpha") or _ALPHA_FACTOR * spacing
            mesh = o3d.geometry.TriangleMesh.create_from_point_cloud_alpha_shape(pcd, alpha)
        else:  # pragma: no cover - names are checked before
            raise ValueError(f"unknown method {name!r}; valid methods: {', '.join(METHODS)}")
    mesh.compute_vertex_normals()
    return mesh


def _poisson_tutorial(points, normals, cameras, options):
    """Poisson as Open3D's tutorial runs it: outliers removed, normals (given or estimated on what is left), density trim."""
    from o3drbf.evaluation.peers import poisson
    from o3drbf.prep.outliers import statistical_outliers

    keep, _ = statistical_outliers(points, TUTORIAL["nb_neighbors"], TUTORIAL["std_ratio"])
    pts = points[keep]
    if normals is not None:
        nrm = np.asarray(normals, dtype=float)[keep]
    else:
        pc = options.get("point_camera")
        pc = None if pc is None else np.asarray(pc).reshape(-1)[keep]
        nrm = open3d_normals(pts, cameras, pc)
    return poisson(pts, nrm, depth=options.get("poisson_depth", 8), density_quantile=TUTORIAL["density_quantile"])


def run_method(name: str, points, normals=None, cameras=None, **options):
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
    **options
        ``resolution``, ``surface_count``, ``seed`` (o3drbf);
        ``poisson_depth`` (8), ``density_quantile`` (0, raw Poisson only); ``spacing`` (the
        mean nearest-neighbour spacing, computed when absent),
        ``bpa_radii`` (multiples of the spacing, ``(1, 2, 4)``), ``alpha``
        (data units, default ``3 x spacing``); ``point_camera``.

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
    pts = as_points(points, min_count=4)
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base, _ = tracemalloc.get_traced_memory()
    t0 = time.perf_counter()
    try:
        mesh = _run(name, pts, normals, cameras, options)
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


def compare_with_meshes(
    points,
    normals=None,
    cameras=None,
    truth=None,
    methods=METHODS,
    seed: int = 0,
    resolution: int | str = DEFAULTS["resolution"],
    poisson_depth: int = 8,
    density_quantile: float = 0.0,
    *,
    point_camera=None,
    surface_count: int = 3000,
    n_samples: int = 100_000,
):
    """As :func:`compare`, and also the meshes: ``(rows, {name: mesh or None})``."""
    names = parse_methods(methods)
    pts = as_points(points, min_count=4)
    if normals is not None:
        normals = np.asarray(normals, dtype=float)
        if normals.shape != pts.shape or not np.isfinite(normals).all():
            raise ValueError(f"normals must be a finite {pts.shape} array like the points, got {normals.shape}")
    seed = check_number("seed", seed, low=0, integer=True)
    if resolution != "auto":
        resolution = check_number("resolution", resolution, low=2, integer=True)
    poisson_depth = check_number("poisson_depth", poisson_depth, low=1, high=12, integer=True)
    density_quantile = check_number("density_quantile", density_quantile, low=0.0, high=1.0)
    cams = _camera_list(cameras)
    threshold = None
    if truth is not None:
        tv = _check_truth(truth)
        threshold = 0.01 * float(np.linalg.norm(tv.max(axis=0) - tv.min(axis=0)))
    options = dict(
        seed=seed,
        resolution=resolution,
        surface_count=surface_count,
        poisson_depth=poisson_depth,
        density_quantile=density_quantile,
        spacing=mean_spacing(pts),
        point_camera=point_camera,
    )
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
                mesh, seconds, peak = run_method(name, pts, nrm, cams, **options)
            seconds += normal_seconds
            row.update(seconds=round(seconds, 4), peak_mb=round(peak / 2**20, 2), rss_peak_mb=None if rss.peak_bytes is None else round(rss.peak_bytes / 2**20, 2))
            _measure(row, mesh, pts, truth, threshold, n_samples, seed)
        except Exception as exc:  # one failing method must not stop the others
            row["error"] = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
        rows.append(row)
        meshes[name] = mesh
    return rows, meshes


def compare(points, normals=None, cameras=None, truth=None, methods=METHODS, seed=0, resolution=DEFAULTS["resolution"], poisson_depth=8, density_quantile=0.0, **kw) -> list[dict]:
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
    methods : sequence of str or comma-separated str
    seed, resolution : int
        o3drbf sampling seed (also the metrics' sampling seed) and
        marching-cubes resolution.
    poisson_depth : int
    density_quantile : float
        Poisson density trimming (0: none).
    **kw
        ``point_camera``, ``surface_count`` (3000), ``n_samples`` (points
        drawn per mesh for the truth measures, 100,000).

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
    >>> from o3drbf.evaluation.compare import compare
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> rows = compare(points, normals, methods='multiorder,poisson', resolution=20, poisson_depth=5, surface_count=200)
    >>> [(row['method'], row['watertight']) for row in rows]
    [('multiorder', True), ('poisson', True)]
    """
    rows, _ = compare_with_meshes(points, normals, cameras, truth, methods, seed, resolution, poisson_depth, density_quantile, **kw)
    return rows


# --------------------------------------------------------------------------
# output


#: Human names of the methods (kernels registered later: ``o3drbf <name>``).
LABELS = {
    "multiorder": "o3drbf multi-order",
    "thinplate": "o3drbf thin-plate",
    "gaussian": "o3drbf Gaussian",
    "poisson": "Open3D Poisson (raw points)",
    "poisson-tutorial": "Open3D Poisson (tutorial: outlier removal + density trim)",
    "bpa": "Open3D ball pivoting",
    "alpha": "Open3D alpha shape",
}

#: ``comparison.md``'s columns: raw key -> header (with units).  Left out of
#: it (kept in the CSV/JSON): ``peak_mb`` (tracemalloc, Python only),
#: ``vertices``, ``fitness_rms``, ``chamfer_l2`` and ``f_threshold`` (one
#: value, in the line above the table).
HUMAN_COLUMNS = {
    "method": "Method",
    "seconds": "Time (s)",
    "rss_peak_mb": "Peak memory (MB)",
    "triangles": "Triangles",
    "watertight": "Watertight",
    "components": "Pieces",
    "euler_characteristic": "Euler characteristic",
    "genus": "Genus",
    "fitness_mean": "Fitness mean (data units)",
    "average_curvature": "Mean curvature (1/data units)",
    "chamfer_l1": "Chamfer L1 (data units)",
    "hausdorff": "Hausdorff (data units)",
    "f_score": "F-score @ τ",
    "precision": "Precision @ τ",
    "recall": "Recall @ τ",
    "normal_consistency": "Normal consistency",
    "error": "Error",
}

#: The notes printed under the table.
TABLE_NOTES = (
    "Peak memory: growth of the process's resident memory while the method ran (psutil, sampled every 5 ms), "
    "Open3D's and Numba's compiled allocations included; methods run one after another, so memory an earlier "
    "method freed but the allocator kept is not counted again. (The Python-only tracemalloc peak is `peak_mb` "
    "in comparison.csv/json.)",
    "Chamfer L1: mean of the two mean surface-to-surface distances (the RMS version is `chamfer_l2` in the CSV); "
    "Hausdorff: the largest sampled distance. F-score, precision, recall: fractions of points sampled on the "
    "two surfaces within τ of the other. Normal consistency: mean |cos| between matched normals (1 is best).",
    "Watertight: Open3D's is_watertight (closed, vertex-manifold, no self-intersections). Pieces: connected "
    "triangle clusters. Fitness: distance from the input points to the mesh.",
)

#: Views of :func:`picture`, left to right.
VIEWS = ("front", "side", "top", "below")


def method_label(name: str) -> str:
    """The human name of a method, ``(default)`` after the default kernel's."""
    label = LABELS.get(name, f"o3drbf {name}")
    return f"{label} (default)" if name == DEFAULTS["kernel"] else label


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _threshold(rows):
    values = {r.get("f_threshold") for r in rows} - {None}
    return values.pop() if len(values) == 1 else None


def settings_line(rows, points: int | None = None, reference: str | None = None, threshold: float | None = None) -> str:
    """The one line of settings shared by every row (above the table, on the picture).

    ``threshold`` defaults to the rows' ``f_threshold`` (the F-score's τ).
    """
    threshold = _threshold(rows) if threshold is None else threshold
    parts = []
    if points is not None:
        parts.append(f"{int(points):,} input points")
    if reference is not None:
        parts.append(f"reference: {reference}")
    if threshold is not None:
        parts.append(f"τ = {_fmt(float(threshold))} data units (1% of the reference's bounding-box diagonal)")
    elif reference is None:
        parts.append("no reference mesh: no Chamfer/F-score")
    return " · ".join(parts)


def markdown_table(rows, points: int | None = None, reference: str | None = None) -> str:
    """``comparison.md``: a line of shared settings, the table, notes.

    Columns are :data:`HUMAN_COLUMNS` (those with no value in any row are
    left out); methods by :func:`method_label`; numbers to 4 significant
    digits.
    """
    cols = [c for c in HUMAN_COLUMNS if c == "method" or any(r.get(c) is not None for r in rows)]
    lines = [settings_line(rows, points, reference), "", "| " + " | ".join(HUMAN_COLUMNS[c] for c in cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        cells = [method_label(r["method"]) if c == "method" else _fmt(r.get(c)) for c in cols]
        lines.append("| " + " | ".join(cell.replace("|", "/") for cell in cells) + " |")
    for note in (note for c, note in zip(("rss_peak_mb", "chamfer_l1", "watertight"), TABLE_NOTES) if c in cols):
        lines.extend(("", note))
    return "\n".join(lines) + "\n"


def write_tables(rows, out_dir, stem: str = "comparison", points: int | None = None, reference: str | None = None) -> dict:
    """Write ``comparison.md``, ``comparison.csv`` and ``comparison.json``.

    Each file is written atomically.  The markdown is
    :func:`markdown_table` (human headers, ``points`` and ``reference``
    named in its first line); the JSON holds the rows exactly (a list of
    objects with the raw keys :data:`COLUMNS`, ``null`` for missing values);
    the CSV has a header with :data:`COLUMNS` and empty cells for missing
    values.

    Returns
    -------
    dict
        ``{"markdown": Path, "csv": Path, "json": Path}``.
    """
    from o3drbf.io.files import atomic_path

    out = Path(out_dir)
    if not out.is_dir():
        raise FileNotFoundError(f"output folder does not exist: {out}")
    rows = [{c: r.get(c) for c in COLUMNS} for r in rows]
    paths = {"markdown": out / f"{stem}.md", "csv": out / f"{stem}.csv", "json": out / f"{stem}.json"}
    buf = _io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({c: "" if v is None else v for c, v in r.items()})
    texts = {"markdown": markdown_table(rows, points, reference), "csv": buf.getvalue(), "json": json.dumps(rows, indent=2, allow_nan=False) + "\n"}
    for key, path in paths.items():
        with atomic_path(path) as tmp:
            Path(tmp).write_text(texts[key], encoding="utf-8")
    return paths


def _wrap(text: str, width: int = 40) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width)[:3])


def row_title(row: dict) -> str:
    """The title of a method's row in :func:`picture`: its name (wrapped at
    36 characters), then the table's Chamfer L1, F-score, watertight and
    pieces (as in the table)."""
    lines = [_wrap(method_label(row["method"]), 36)]  # long labels on two lines: a panel is narrow
    if row.get("error"):
        return lines[0] + "\n" + _wrap("FAILED: " + row["error"])
    if row.get("chamfer_l1") is not None:
        lines.append(f"Chamfer L1 {_fmt(row['chamfer_l1'])}, F-score {_fmt(row.get('f_score'))}")
    pieces = row.get("components")
    if row.get("watertight") is not None and pieces is not None:
        lines.append(f"watertight {_fmt(row['watertight'])}, {pieces} piece{'' if pieces == 1 else 's'}")
    if row.get("seconds") is not None:
        lines.append(f"{_fmt(row['seconds'])} s, {_fmt(row.get('triangles'))} triangles")
    return "\n".join(lines)


def colour_range(rows) -> tuple[float, float] | None:
    """The shared range of the distance colours: ``(0, 2 τ)`` (τ the F-score
    threshold: the bar's middle), or None without a reference."""
    threshold = _threshold(rows)
    return None if threshold is None else (0.0, 2.0 * float(threshold))


def picture_panels(rows, meshes: dict, points=None, truth=None, reference: str | None = None, max_points: int = 200_000):
    """The panels of :func:`picture`: ``(rows of Panel, header text, colour range, bounds)``.

    One row for the input points, one for the reference (``truth``, when
    given), then one per method in ``rows``' order; one column per view of
    :data:`VIEWS`.  The first panel of each row carries the title
    (:func:`row_title` for methods).  With a reference, method meshes are
    coloured by each vertex's distance to it on :func:`colour_range`.
    Every panel frames ``bounds`` ``(6,)``: the reference's box, else the
    input points' 1st to 99th percentiles (stray outliers and a method's
    far-off pieces fall outside; the titles still count them), padded by 5%;
    None (everything drawn) without either.
    """
    from o3drbf.mesh.metrics import point_distances
    from o3drbf.pictures import Panel

    def line(title, **kw):
        return [Panel(title if j == 0 else "", view=v, **kw) for j, v in enumerate(VIEWS)]

    clim = colour_range(rows) if truth is not None else None
    grid_rows = []
    if points is not None:
        pts = np.asarray(points, dtype=float)
        shown = pts[:: max(1, -(-len(pts) // max_points))]
        title = f"input: {len(pts):,} points" + ("" if len(shown) == len(pts) else f" ({len(shown):,} drawn)")
        grid_rows.append(line(title, points=shown))
    if truth is not None:
        grid_rows.append(line(f"reference{'' if reference is None else ': ' + reference}\n{len(truth.triangles):,} triangles", mesh=truth))
    for row in rows:
        mesh = meshes.get(row["method"])
        ok = mesh is not None and len(mesh.triangles) > 0
        if not ok and not row.get("error"):
            row = {**row, "error": "no mesh"}
        scalars = point_distances(np.asarray(mesh.vertices), truth) if ok and clim is not None else None
        grid_rows.append(line(row_title(row), mesh=mesh if ok else None, scalars=scalars))
    head = ["o3drbf compare" + ("" if points is None else f": {len(points):,} input points") + ("" if reference is None else f", reference {reference}")]
    if clim is not None:
        head.append(f"F-score threshold tau = {_fmt(clim[1] / 2)} data units (1% of the reference's diagonal)")
        head.append("colour: distance to the reference, one scale for every method;")
        head.append("yellow: 2 tau or more")
    else:
        head.append("no reference: red = pieces besides the largest,")
        head.append("orange = back faces (insides seen through holes)")
    head.append("red under a see-through piece: pieces hidden inside it")
    header = "\n".join(head)
    bounds = None
    if truth is not None:
        tv = np.asarray(truth.vertices)
        lo, hi = tv.min(axis=0), tv.max(axis=0)
    elif points is not None:
        lo, hi = np.percentile(np.asarray(points, dtype=float), [1, 99], axis=0)
    if truth is not None or points is not None:
        pad = 0.05 * (hi - lo).max()
        bounds = tuple(float(b) for b in np.column_stack([lo - pad, hi + pad]).ravel())
    return grid_rows, header, clim, bounds


def picture(meshes: dict, path, points=None, rows=None, truth=None, reference: str | None = None, viewup=(0.0, 0.0, 1.0), panel_size: int = 300) -> Path:
    """The comparison picture: one row per method, one column per view.

    Rows (:func:`picture_panels`): the input points, the reference when
    given, then each method, titled with its table numbers; columns:
    :data:`VIEWS` (front, side, top, below).  The PNG is
    ``(len(VIEWS) * panel_size, HEADER_HEIGHT + n_rows * panel_size)``
    pixels (:data:`o3drbf.pictures.HEADER_HEIGHT`).

    Parameters
    ----------
    meshes : dict
        ``{method: mesh or None}`` (None: failed, an empty row).
    path : str or Path
        A ``.png``.
    points : (N, 3) array, optional
    rows : list of dict, optional
        :func:`compare`'s rows for the titles (default: names only).
    truth : open3d.geometry.TriangleMesh, optional
    reference : str, optional
        The reference's name, for the header.
    viewup : 3-tuple
        The data's up axis.
    """
    from o3drbf.pictures import grid

    if not meshes:
        raise ValueError("no meshes to draw")
    if rows is None:
        rows = [{"method": name, "error": None if m is not None and len(m.triangles) else "no mesh"} for name, m in meshes.items()]
    panels, header, clim, bounds = picture_panels(rows, meshes, points, truth, reference)
    return grid(panels, path, panel_size=panel_size, header=header, clim=clim, colour_label="distance to reference (data units)", viewup=viewup, bounds=bounds)


# --------------------------------------------------------------------------
# command line


def add_compare_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``compare`` arguments to a (sub)parser; returns it."""
    parser.description = parser.description or (
        "Run several reconstruction methods on the same points and compare them: "
        "a table (markdown, CSV, JSON) of time, memory, triangles, watertightness and "
        "quality measures, and a picture: one row per method seen from four sides, coloured by distance to the truth."
    )
    parser.add_argument(
        "input",
        help="point cloud file (normals used when present), or a file that holds points and cameras "
        "(Stanford .conf, COLMAP text folder, Bundler bundle.out, o3drbf scan .json)",
    )
    parser.add_argument("--cameras", metavar="FILE", default=None, help="cameras that saw the points: Open3D normals are oriented toward them, o3drbf uses them for exterior constraints")
    parser.add_argument("--truth", metavar="MESH", default=None, help="ground-truth mesh: adds Chamfer, Hausdorff, F-score (1%% of its diagonal) and normal consistency")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated, from: " + ", ".join(METHODS) + " (default: all)")
    parser.add_argument("-o", "--out", metavar="OUT_DIR", default="comparison", help="output folder for comparison.{md,csv,json,png} (created; default %(default)s)")
    from o3drbf.options import count_or_auto

    parser.add_argument("--resolution", type=count_or_auto, default=DEFAULTS["resolution"], help="o3drbf marching-cubes resolution, auto or N (default %(default)s)")
    parser.add_argument("--poisson-depth", type=int, default=8, help="Open3D Poisson octree depth (default %(default)s)")
    parser.add_argument("--density-quantile", type=float, default=0.0, help="Poisson (raw points): trim vertices below this density quantile (default %(default)s: closed surface; "
                        "the tutorial variant always trims at 0.05)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed (default %(default)s)")
    parser.add_argument("--up", choices=sorted(_UP), default="z", help="the data's up axis, for the picture's views (default %(default)s; the Stanford bunny: y)")
    return parser


def _read_truth(path):
    import open3d as o3d

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"cannot read truth mesh {p}: file not found")
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) == 0:
        raise ValueError(f"cannot read truth mesh {p}: no triangles (not a mesh file Open3D reads: PLY, OBJ, STL, OFF, glTF)")
    return mesh


def main_compare(args: argparse.Namespace) -> int:
    """``o3drbf compare``: run, write the tables and the picture, print the table.

    Raises ``ValueError`` / ``FileNotFoundError`` on bad input (the CLI turns
    them into ``o3drbf: error: ...`` and exit status 2).
    """
    from o3drbf.pointset import read_input

    methods = parse_methods(getattr(args, "methods", None) or ",".join(available_methods()))
    truth = _read_truth(args.truth) if getattr(args, "truth", None) else None
    data = read_input(args.input, cameras=getattr(args, "cameras", None))
    points, normals, cameras, point_camera = data.points, data.normals, data.cameras, data.point_camera
    out = Path(getattr(args, "out", None) or "comparison")
    from o3drbf.io.files import check_outputs

    if out.exists() and not out.is_dir():
        raise ValueError(f"-o {out} is a file; give a folder for comparison.md/.csv/.json/.png")
    inputs = [args.input, getattr(args, "truth", None), getattr(args, "cameras", None)]
    outputs = [out / f"comparison.{ext}" for ext in ("md", "csv", "json", "png")]
    if out.is_dir():
        check_outputs(outputs, inputs)  # before any method runs: never an input, never read-only
    out.mkdir(parents=True, exist_ok=True)
    check_outputs(outputs, inputs)
    rows, meshes = compare_with_meshes(
        points,
        normals,
        cameras,
        truth,
        methods,
        seed=getattr(args, "seed", 0),
        resolution=getattr(args, "resolution", DEFAULTS["resolution"]),
        poisson_depth=getattr(args, "poisson_depth", 8),
        density_quantile=getattr(args, "density_quantile", 0.0),
        point_camera=point_camera,
    )
    reference = Path(args.truth).name if getattr(args, "truth", None) else None
    paths = write_tables(rows, out, points=len(points), reference=reference)
    png = picture(meshes, out / "comparison.png", points=points, rows=rows, truth=truth, reference=reference, viewup=_UP[getattr(args, "up", "z")])
    print(f"o3drbf compare: {args.input} ({len(points):,} points) -> {out}/")
    print(markdown_table(rows, len(points), reference), end="")
    for row in rows:
        if row["error"]:
            print(f"  {row['method']} failed: {row['error']}")
    print("  wrote " + ", ".join(str(p) for p in (*paths.values(), png)))
    return 0
