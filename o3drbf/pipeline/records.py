"""What the stages hand each other and what :func:`~o3drbf.pipeline.reconstruct` returns: the records, the report, the stage timer."""

from __future__ import annotations

import resource
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np

from o3drbf.constraints.core import EXTERIOR, SURFACE, Constraints
from o3drbf.mesh.arrays import MeshArrays
from o3drbf.options import Options
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import Kernel
from o3drbf.solvers import Solution
from o3drbf.surface import ImplicitSurface

__all__ = ["StageTiming", "OutlierReport", "ConstraintSet", "Parameters", "Report", "Reconstruction", "StageTimer", "peak_rss_mb"]


@dataclass
class StageTiming:
    """Seconds and peak memory of one stage.

    Attributes
    ----------
    name : str
        "read", "register" (with ``point_camera``), "outliers", "normals", "constraints", "parameters", "fit", "extract", "colour", "confidence", "write" or (the command line's closing summary) "checks".
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
        Mean nearest-neighbour spacing of the surface constraints (box units;
        with ``surface_adaptive``, of the uniform subset before it was thinned).
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

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import o3drbf
    >>> report = o3drbf.reconstruct(points, normals, surface_count=200, resolution=20).report
    >>> report.points, report.surface_constraints, report.sphere_constraints, report.parameter_source['delta']
    (600, 204, 64, 'auto')
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
        Made from :attr:`mesh_arrays` when first asked for (the command line
        never asks, so it does not import Open3D).
    mesh_arrays : MeshArrays or None
        The same mesh as NumPy arrays (read-only view of the result; no Open3D).
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

    Examples
    --------
    >>> import numpy as np
    >>> from o3drbf.synthetic.shapes import Sphere
    >>> points, normals = Sphere(1.0).sample(600, noise=0.002, seed=0)
    >>> import o3drbf
    >>> result = o3drbf.reconstruct(points, normals, surface_count=200, resolution=20)
    >>> type(result).__name__, len(result.mesh.triangles) > 1000, result.solution.method
    ('Reconstruction', True, 'dense')
    """

    surface: ImplicitSurface
    mesh: object = field(repr=False)  # an Open3D mesh, or a MeshArrays turned into one when first read (below)
    constraints: Constraints
    solution: Solution
    report: Report
    options: Options = field(default_factory=Options)
    confidence: object = None
    points: np.ndarray | None = None

    @property
    def mesh_arrays(self) -> MeshArrays | None:
        mesh = self.__dict__.get("_mesh")
        return mesh if mesh is None or isinstance(mesh, MeshArrays) else MeshArrays.from_open3d(mesh)

    def plot(self, *, constraints: bool = False, compare: dict | None = None, title: str | None = None, **options):
        """Show the mesh with PyVista: inline in Jupyter (static PNG, or interactive with trame), else a window or offscreen.

        Parameters
        ----------
        constraints : bool
            Draw the surface (blue) and exterior (green) constraints over the mesh, in the colours of ``o3drbf view``
            (not the bounding-sphere ones, which would shrink the mesh in the frame).
        compare : dict of str to open3d.geometry.TriangleMesh, optional
            Other reconstructions of the same data, one panel each beside this one (linked cameras).
        title : str, optional
            Default: "o3drbf (<triangles> triangles)".
        **options
            ``show``, ``screenshot`` (a .png also written), ``backend``,
            ``window_size``, ``view``: see :func:`o3drbf.pictures.plot`.

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


def _get_mesh(self):
    mesh = self.__dict__.get("_mesh")
    if isinstance(mesh, MeshArrays):  # first read: the Open3D mesh made once, and kept in its place
        mesh = self.__dict__["_mesh"] = mesh.to_open3d()
    return mesh


def _set_mesh(self, mesh):
    self.__dict__["_mesh"] = mesh


# A property over the dataclass field (its __init__ assigns through it): ``mesh`` may be given as MeshArrays.
Reconstruction.mesh = property(_get_mesh, _set_mesh, doc="The mesh as an open3d.geometry.TriangleMesh (None without extraction).")


class StageTimer:
    """Times each stage and records the peak memory after it (the :class:`StageTiming` list of a :class:`Report`).

    Examples
    --------
    >>> timer = StageTimer()
    >>> with timer.stage("read"):
    ...     pass
    >>> [t.name for t in timer.timings], timer.seconds("read") >= 0
    (['read'], True)
    """

    def __init__(self):
        self.timings: list[StageTiming] = []

    @contextmanager
    def stage(self, name: str):
        """Time the ``with`` block as stage ``name`` (appended to :attr:`timings` when it ends)."""
        t0 = time.perf_counter()
        yield
        self.timings.append(StageTiming(name, time.perf_counter() - t0, peak_rss_mb()))

    def seconds(self, name: str) -> float:
        """Total seconds of the stages called ``name`` (0 when none ran)."""
        return sum(t.seconds for t in self.timings if t.name == name)


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
