"""One table of defaults, and the options of each stage of :func:`o3drbf.reconstruct`.

:data:`DEFAULTS` is the single source of truth: the Python API, the command
line, the viewer and ``o3drbf compare`` all build their :class:`Options`
from it (``tests/test_options.py`` checks that they agree).  Lengths refer
to the data normalized into the 2x2x2 box unless a name says otherwise.

Options are grouped by stage in small frozen dataclasses; :meth:`Options.create`
builds them from flat keyword names (``Options.create(surface_count=5000)``)
and :meth:`Options.validate` checks every value before the first costly step.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

from o3drbf.extract import AUTO_RESOLUTION, auto_resolution
from o3drbf.options.values import auto_or_bool, box_or_rule, count_or_auto, rgb, whole_number
from o3drbf.validation import check_choice, check_number

__all__ = [
    "DEFAULTS",
    "OUTLIER_METHODS",
    "REGISTER_METHODS",
    "PAPER_VALUES",
    "VIEWER_OVERRIDES",
    "VIEWER_DISPLAY",
    "AUTO_SIZES",
    "MAX_RESOLUTION",
    "auto_surface_count",
    "auto_resolution",
    "UNTILED_MEMORY",
    "untiled_memory",
    "check_untiled_fits",
    "untiled_fits",
    "count_or_auto",
    "PARAMETER_RANGES",
    "check_parameter_range",
    "whole_number",
    "auto_or_bool",
    "box_or_rule",
    "rgb",
    "CARVE_DEFAULTS",
    "TILE_DEFAULTS",
    "PHOTO_DEFAULTS",
    "PHOTO_OVERRIDES",
    "PHOTO_OUTLIER_VOXELS",
    "COMPARE_DEFAULTS",
    "COMPARE_OVERRIDES",
    "COMPARE_PEERS",
    "COMPARE_TUTORIAL",
    "VIEW_DEFAULTS",
    "VIEW_UP",
    "VIEW_LAYERS",
    "ENTRY_POINTS",
    "defaults",
    "PhotoOptions",
    "CarveOptions",
    "CompareOptions",
    "ViewOptions",
    "COMPARE_UP",
    "compare_methods",
    "SOLVER_METHODS",
    "Options",
    "RegistrationOptions",
    "OutlierOptions",
    "ConstraintOptions",
    "ParameterOptions",
    "FitOptions",
    "ExtractOptions",
    "CONFIDENCE_DEFAULTS",
    "ConfidenceOptions",
    "TileOptions",
    "API_ONLY",
]

#: Outlier handling: "auto" (free-space consistency with cameras, an
#: isolated-point rule without, and robust reweighting in the fit), "none",
#: "largest" (largest connected components), "statistical" (Open3D).
OUTLIER_METHODS = ("auto", "none", "largest", "statistical")

#: Registration of the scans to each other: "auto" (when the points carry
#: their scan, ``point_camera``, and two or more scans overlap: rigid motions
#: kept only when they make the scans markedly more consistent), "none".
REGISTER_METHODS = ("auto", "none")

#: Solver methods (see :func:`o3drbf.solvers.solve`).
SOLVER_METHODS = ("auto", "dense", "iterative", "fast")

#: Every default of every entry point (normalized box units).
DEFAULTS: dict = {
    # registration of the scans to each other (cameras and point_camera)
    "register": "auto",
    # outliers
    "outliers": "auto",
    "outlier_radius": None,  # data units; None: 3 mean spacings
    "keep_components": 1,
    # constraints
    "surface_count": "auto",  # from the number of points (AUTO_SIZES)
    "surface_radius": None,
    "denoise": "auto",
    "surface_adaptive": None,  # None: the uniform rule; a tolerance (spacings): fewer constraints where flat (o3drbf.constraints.adaptive)
    "exterior_ratio": 0.1,
    "exterior_offset": 0.05,
    "sphere_count": 64,
    # parameters
    "kernel": "multiorder",
    "auto": True,
    "delta": None,  # multiorder; None: automatic (or the paper's 10 with auto=False)
    "tau": None,  # multiorder; None: automatic (or the paper's 0.01)
    "sigma": None,  # gaussian width; None: 0.1
    "lambda_surface": None,  # None: automatic (or the paper's 1e-3)
    "lambda_exterior": 50.0,  # relative to phi(0) of the kernel used
    # fit
    "solver": "auto",
    "robust": True,
    # extract
    "resolution": "auto",  # from the surface constraints' spacing (AUTO_SIZES)
    "voxel_size": None,  # data units
    "bounds": None,  # data units
    # confidence (o3drbf.mesh.confidence): off by default, the default path unchanged
    "confidence": False,  # compute per-vertex confidence (a PLY vertex property "confidence")
    "trim": None,  # remove triangles with a vertex of confidence below this, in [0, 1]
    # tiles (o3drbf.tiles): off by default; read by fit_tiled, reconstruct_tiled and extract_tiled only
    "tiles": None,  # None: untiled; "auto": one tile per points_per_tile points (untiled on the command line when it fits); N tiles
    "scheduler": None,  # None: a Dask LocalCluster of `workers` processes; "synchronous": this process; or a scheduler address
    "workers": 2,  # workers of a LocalCluster started here (one thread each)
    "memory_limit": None,  # per worker of that LocalCluster; None: 80 % of the available memory shared among them
    "points_per_tile": 60_000,  # tiles="auto": target points per tile cell
    "surface_count_per_tile": 3000,  # Poisson-disc surface constraints per tile support (None: all its points)
    "global_count": 2000,  # surface constraints of the global coarse fit f0
    "overlap": 0.25,  # support margin on each side, as a fraction of the cell's half-size ...
    "min_overlap": 0.02,  # ... and at least this (box units)
    "partition_sample": 1_000_000,  # points that decide f0, its outliers and the k-d cuts (a seeded uniform subsample)
    "chunk_points": 1_000_000,  # points read and distributed to the tiles at a time
    "tile_dir": None,  # folder for the per-tile point files (shared storage for remote workers); None: temporary / in memory
}

#: Options read only through the Python API (no command-line flag): ``bounds``,
#: ``surface_adaptive`` (a sweep's option, not a default: docs/data/adaptive-constraints.md)
#: and the tile sizes beyond ``--tiles``, ``--scheduler`` and ``--workers``.
API_ONLY = ("bounds", "surface_adaptive", "memory_limit", "points_per_tile", "surface_count_per_tile", "global_count", "overlap", "min_overlap",
            "partition_sample", "chunk_points", "tile_dir")

#: ``surface_count="auto"`` and ``resolution="auto"``: sparse scans keep the
#: paper's ~3,000 constraints (and the dense solve), dense scans get detail:
#: one surface constraint per ``points_per_constraint`` points between
#: ``min_constraints`` and ``max_constraints``.  Noisy (denoised) scans keep
#: that rate only up to ``noisy_full_rate_max`` constraints, then one per
#: ``noisy_points_per_constraint`` points: noise makes robust refits, and
#: above the dense solve's range (``o3drbf.solvers.DENSE_AUTO_MAX``) each
#: refit is a whole fast solve.  Chosen on the Stanford bunny's scans and the
#: robustness study; the measurements are in docs/data/design-measurements.md ("Automatic sizes").
AUTO_SIZES = {
    "points_per_constraint": 3,  # surface constraints = points / 3 ...
    "min_constraints": 3000,  # ... at least this many (or every point) ...
    "max_constraints": 30000,  # ... at most this many
    "noisy_full_rate_max": 10000,  # noisy (denoised) scans: points / 3 up to this many, ...
    "noisy_points_per_constraint": 6,  # ... else points / 6 (at least the count above)
    **AUTO_RESOLUTION,  # marching-cubes cells per constraint spacing, between a minimum and a maximum (o3drbf.extract)
}


#: ``denoise="auto"`` moves the surface constraints onto local quadric fits
#: when the points' estimated noise exceeds this many constraint spacings
#: (clean scans stay as they are: their sharp edges are not rounded).
#: Measurements: docs/data/design-measurements.md ("Denoising threshold").
DENOISE_MIN_NOISE = 0.05


#: Mesh pieces smaller than this many surface-constraint spacings across are
#: removed after marching cubes (:func:`o3drbf.mesh.metrics.drop_specks`):
#: the zero crossing around one stray constraint (docs/data/design-measurements.md, "Specks").
SPECK_SPACINGS = 2.0


#: The finest marching-cubes grid any entry point accepts (cells along the
#: longest side): ``resolution`` of :class:`ExtractOptions`, ``--resolution``
#: of ``o3drbf reconstruct`` and of the viewer.
MAX_RESOLUTION = 1024


def auto_surface_count(n_points: int, noisy: bool = False) -> int:
    """The surface-constraint count ``surface_count="auto"`` picks for ``n_points`` points (``noisy``: to be denoised)."""
    a = AUTO_SIZES
    count = n_points // a["points_per_constraint"]
    if noisy:
        count = min(count, max(a["noisy_full_rate_max"], n_points // a["noisy_points_per_constraint"]))
    return int(min(max(count, a["min_constraints"]), a["max_constraints"]))


def extraction_memory(resolution: int) -> int:
    """Peak bytes of marching cubes at ``resolution`` cells on the longest side (a cube, the worst case):
    the float64 value grid, its refinement copy and the boolean masks."""
    nodes = (int(resolution) + 1) ** 3
    return int(nodes * (8 * 2 + 4))


#: Memory of the untiled path (read, outlier rules, normals, kd-trees, noise
#: estimate, subsample, fit, marching cubes at 64 cells) per input point and
#: fixed, from the peak resident memory of ``reconstruct(surface_count=3000,
#: resolution=64)`` on a noisy torus at two sizes, with a margin for reading a
#: file (docs/data/design-measurements.md, "Untiled memory").
UNTILED_MEMORY = {"bytes_per_point": 2200, "fixed_bytes": 512 * 2**20, "usable_fraction": 0.8}


def untiled_memory(n_points: int) -> int:
    """Bytes the untiled path needs for ``n_points`` input points (:data:`UNTILED_MEMORY`)."""
    m = UNTILED_MEMORY
    return int(m["fixed_bytes"] + m["bytes_per_point"] * int(n_points))


def untiled_fits(n_points: int, available: int | None = None) -> bool:
    """Whether the untiled path holds ``n_points`` input points: :func:`untiled_memory` within
    ``usable_fraction`` of ``available`` bytes (default :func:`o3drbf.solvers.base.available_memory`)."""
    if available is None:
        from o3drbf.solvers.base import available_memory

        available = available_memory()
    return untiled_memory(n_points) <= UNTILED_MEMORY["usable_fraction"] * available


def check_untiled_fits(n_points: int | None, available: int | None = None) -> None:
    """Refuse an input too large for the untiled path, suggesting ``--tiles auto``.

    Parameters
    ----------
    n_points : int or None
        Input points (None: unknown, nothing checked).
    available : int, optional
        Bytes available; default :func:`o3drbf.solvers.base.available_memory`.
        The input is refused when :func:`untiled_memory` exceeds
        ``usable_fraction`` of it.

    Raises
    ------
    ValueError
        One line: the points, the memory needed and available, and the fix.
    """
    if n_points is None:
        return
    if available is None:
        from o3drbf.solvers.base import available_memory

        available = available_memory()
    need = untiled_memory(n_points)
    if not untiled_fits(n_points, available):
        raise ValueError(f"{int(n_points):,} points need about {need / 2**30:.1f} GiB without tiles but {available / 2**30:.1f} GiB "
                         "are available; pass --tiles auto (tiled reconstruction, points read in chunks)")

#: The viewer's starting values where an interactive refit needs a lighter
#: problem than a final reconstruction (everything else: :data:`DEFAULTS`).
VIEWER_OVERRIDES = {"resolution": 64, "surface_count": 1500}

#: What the viewer draws: at most ``max_points`` of each point layer (a
#: seeded subsample, so the surface stays visible on dense scans), the input
#: points light and small.
VIEWER_DISPLAY = {"max_points": 50_000, "point_size": 1.0, "point_color": "#a9a9a9"}

#: Space carving from photographs (:mod:`o3drbf.photo.carve`, :class:`CarveOptions`).
CARVE_DEFAULTS = {
    "resolution": 128,
    "background": (0.0, 0.0, 0.0),
    "threshold": 0.15,
    "min_area": 64,
    "photo_consistency": 0.12,
    "sweeps": 3,
    "min_views": 2,
    "keep_silhouettes": True,
}

#: ``o3drbf photos``' own options (:class:`PhotoOptions`): the carving box
#: ("auto": a Middlebury README's, else the silhouettes') and the stride of
#: the silhouette check; the carving's are :data:`CARVE_DEFAULTS`.
PHOTO_DEFAULTS = {"bounds": "auto", "iou_stride": 1}

#: ``o3drbf photos``: the fit of a carved shell (dense and nearly noise-free,
#: so fixed parameters; overrides of :data:`DEFAULTS`).  No denoising: the
#: voxel lattice reads as noise (h / sqrt(12)) and moving the constraints
#: off it loses the silhouettes (docs/data/design-measurements.md, "Photos").
#: Carved voxels share one grid (no scans to register) and stray voxels
#: are whole pieces (the largest component is kept).
PHOTO_OVERRIDES = {"delta": 4.0, "tau": 0.01, "lambda_surface": 1e-4, "exterior_ratio": 0.5, "surface_count": 3000, "resolution": 128,
                   "denoise": False, "register": "none", "outliers": "largest"}

#: ``outlier_radius`` None in ``o3drbf photos``: this many carving voxels (stray voxels are pieces of their own).
PHOTO_OUTLIER_VOXELS = 2.5

#: Open3D's reconstructions ``o3drbf compare`` runs beside o3drbf's kernels.
COMPARE_PEERS = ("poisson", "poisson-tutorial", "bpa", "alpha")

#: How ``o3drbf compare``'s ``poisson-tutorial`` runs Poisson: Open3D's statistical outlier
#: removal (neighbours, standard deviations), then density trimming at this quantile.
COMPARE_TUTORIAL = {"nb_neighbors": 20, "std_ratio": 2.0, "density_quantile": 0.05}

#: ``o3drbf compare``'s own options (:class:`CompareOptions`; methods None: all).
COMPARE_DEFAULTS = {"methods": None, "poisson_depth": 8, "density_quantile": 0.0, "n_samples": 100_000, "up": "z"}

#: ``o3drbf compare``: the o3drbf rows' overrides of :data:`DEFAULTS` (the paper's constraint count on every input).
COMPARE_OVERRIDES = {"surface_count": 3000}

#: The viewer's layers and up axes.
VIEW_LAYERS = ("points", "surface", "exterior", "sphere", "cameras", "mesh")
VIEW_UP = ("auto", "x", "y", "z")

#: The viewer's own options (:class:`ViewOptions`); its first fit is
#: :data:`DEFAULTS` with :data:`VIEWER_OVERRIDES`.
VIEW_DEFAULTS = {"level": 0.0, "poisson": True, "poisson_depth": 8, "window_size": (1600, 800), "save_prefix": "o3drbf_view",
                 "show_sphere": False, "hide": (), "max_points": VIEWER_DISPLAY["max_points"], "zoom": 1.0, "up": "auto",
                 "color_by": None, "distance_to": None, "refit": False}

#: Entry point -> (its own defaults, its overrides of :data:`DEFAULTS`): the one table, by entry point.
ENTRY_POINTS = {
    "reconstruct": ({}, {}),
    "photos": (PHOTO_DEFAULTS, PHOTO_OVERRIDES),
    "compare": (COMPARE_DEFAULTS, COMPARE_OVERRIDES),
    "view": (VIEW_DEFAULTS, VIEWER_OVERRIDES),
}


def defaults(entry: str = "reconstruct") -> dict:
    """Every flat option of an entry point (a key of :data:`ENTRY_POINTS`) with its default, read from the tables now.

    Examples
    --------
    >>> defaults("photos")["resolution"], defaults("photos")["voxels"], defaults()["resolution"]
    (128, 128, 'auto')
    """
    check_choice("entry", entry, tuple(ENTRY_POINTS))
    own, overrides = ENTRY_POINTS[entry]
    out = {**DEFAULTS, **overrides, **own}
    if entry == "photos":
        out.update({("voxels" if k == "resolution" else k): v for k, v in CARVE_DEFAULTS.items()})
    return out


#: Tiled reconstruction (:func:`o3drbf.tiles.fit.fit_tiled`): the tile sizes of
#: :data:`DEFAULTS` (:class:`TileOptions`), the root box's padding (a
#: fraction of the data box's longest side), and the points the global fit
#: f0's stages see per surface constraint of it (a subsample of the
#: partition sample: f0 is coarse, the tiles carry the detail).
TILE_DEFAULTS = {
    **{k: DEFAULTS[k] for k in ("points_per_tile", "surface_count_per_tile", "global_count", "overlap", "min_overlap",
                                "partition_sample", "chunk_points")},
    "root_pad": 0.1,
    "base_points_per_constraint": 20,
    # A tile's stages see at most this many of its support's points per surface constraint (a seeded uniform
    # subsample): denser points would not change where its surface_count_per_tile constraints go.
    "support_points_per_constraint": 30,
    # tiles="auto" adds no tiles once the surface constraints would be closer than this many marching-cubes
    # cells: ceil(N / points_per_tile), at most the voxels of that size the surface crosses / surface_count_per_tile.
    "constraint_cells": 0.75,
}

#: Per-vertex confidence (:func:`o3drbf.mesh.confidence.vertex_confidence`):
#: constraints per local Gaussian-process neighbourhood (the posterior
#: variance of the neighbourhood against the exact one: docs/data/design-measurements.md,
#: "Confidence neighbourhoods"), and the distance, in mean spacings, at which
#: the distance factor is exp(-1/2).
CONFIDENCE_DEFAULTS = {"neighbours": 32, "distance_scale": 2.0}

#: Kernel parameter values accepted (box units), with what is usual.  Outside
#: them the arithmetic or the fit breaks down on any data (the kernel's decay
#: rates overflow, the mesh misses the data, or f has no zero crossing:
#: docs/data/design-measurements.md, "Parameter ranges").
PARAMETER_RANGES = {
    "delta": (0.1, 200.0, "the paper uses 5 to 40"),
    "tau": (1e-6, 10.0, "the paper uses 0.005 to 0.025"),
    "sigma": (1e-3, 10.0, "a few surface-constraint spacings"),
}


def check_parameter_range(name: str, value, label: str | None = None) -> float:
    """Refuse a kernel parameter outside :data:`PARAMETER_RANGES`, in one line naming the range and the fix.

    Parameters
    ----------
    name : str
        A key of :data:`PARAMETER_RANGES`.
    value : float
    label : str, optional
        How the message names the parameter (default ``--`` and ``name``, the command line's option).

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Not a finite number, or outside the range.
    """
    import math

    low, high, usual = PARAMETER_RANGES[name]
    label = label or f"--{name}"
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{label} must be a number in [{low:g}, {high:g}], got {value!r}") from None
    if not (math.isfinite(x) and low <= x <= high):
        raise ValueError(f"{label} {x:g} is outside the sensible range [{low:g}, {high:g}] (box units; {usual}); "
                         f"give {label} in that range, or leave it out for the default")
    return x


#: The paper's fixed values, used for parameters left at None with ``auto=False``.
PAPER_VALUES = {"delta": 10.0, "tau": 0.01, "sigma": 0.1, "lambda_surface": 1e-3}


@dataclass(frozen=True)
class RegistrationOptions:
    """Registration of the scans to each other before anything else.

    Attributes
    ----------
    method : {"auto", "none"}
        "auto": each scan (the points of one camera, ``point_camera``) is
        moved rigidly onto the others, with its camera
        (:func:`o3drbf.prep.registration.refine_registration`); the motions
        are kept only when the median distance between overlapping scans
        falls by at least ``min_gain``, so scans registered already stay
        exactly as they are.  "none": never.
    min_gain : float
        The drop in that distance the motions must bring, in [0, 1).
    """

    method: str = DEFAULTS["register"]
    min_gain: float = 0.1

    def validate(self) -> "RegistrationOptions":
        check_choice("register", self.method, REGISTER_METHODS)
        check_number("min_gain", self.min_gain, low=0.0, high=1.0)
        if self.min_gain >= 1.0:
            raise ValueError(f"min_gain must be below 1, got {self.min_gain}")
        return self


@dataclass(frozen=True)
class OutlierOptions:
    """Outlier handling before the constraints are built.

    Attributes
    ----------
    method : {"auto", "none", "largest", "statistical"}
    radius : float or None
        Neighbourhood radius for "largest", data units (None: 3 mean spacings).
    keep_components : int
        Components kept by "largest".
    """

    method: str = DEFAULTS["outliers"]
    radius: float | None = DEFAULTS["outlier_radius"]
    keep_components: int = DEFAULTS["keep_components"]

    def validate(self) -> "OutlierOptions":
        check_choice("outliers", self.method, OUTLIER_METHODS)
        if self.radius is not None:
            check_number("outlier_radius", self.radius, low=0.0, low_open=True)
        check_number("keep_components", self.keep_components, low=1, integer=True)
        return self


@dataclass(frozen=True)
class ConstraintOptions:
    """Which constraints are built (method.md section 4).

    Attributes
    ----------
    surface_count : int, "auto" or None
        Poisson-disc subsample to about this many surface constraints (the
        paper: 2,000-3,000); "auto": :func:`auto_surface_count` (a fraction
        of the points, clipped; the rates and bounds are :data:`AUTO_SIZES`);
        None keeps every point (or uses ``surface_radius``).
    surface_radius : float or None
        Poisson-disc radius (box units) instead of a count.
    exterior_ratio : float
        Exterior constraints per surface constraint, in [0, 1].
    exterior_offset : float
        Distance of exterior constraints from the surface (box units), in (0, 0.5].
    sphere_count : int
        Exterior constraints on a sphere around the data (0: none).
    denoise : "auto" or bool
        Move the surface constraints onto local quadric fits of all the
        points (:func:`o3drbf.prep.smoothing.project_to_local_surface`), so
        the noise of every point is averaged, not only the subsample's;
        "auto": when the estimated noise exceeds ``DENOISE_MIN_NOISE``
        constraint spacings.
    surface_adaptive : float or None
        None: the uniform subset.  A tolerance (> 0, in constraint
        spacings): the subset is thinned where the surface is flat, down to
        ``1 / MAX_FACTOR**2`` of it, where the sag between constraints
        stays under this (:mod:`o3drbf.constraints.adaptive`).
    """

    surface_count: int | str | None = DEFAULTS["surface_count"]
    surface_radius: float | None = DEFAULTS["surface_radius"]
    exterior_ratio: float = DEFAULTS["exterior_ratio"]
    exterior_offset: float = DEFAULTS["exterior_offset"]
    sphere_count: int = DEFAULTS["sphere_count"]
    denoise: str | bool = DEFAULTS["denoise"]
    surface_adaptive: float | None = DEFAULTS["surface_adaptive"]

    def validate(self) -> "ConstraintOptions":
        if self.denoise not in ("auto", True, False):
            raise ValueError(f"denoise must be 'auto', True or False, got {self.denoise!r}")
        if self.surface_count is not None and self.surface_count != "auto":
            check_number("surface_count", self.surface_count, low=10, integer=True)
        if self.surface_radius is not None:
            check_number("surface_radius", self.surface_radius, low=0.0, high=2.0, low_open=True)
        if self.surface_adaptive is not None:
            check_number("surface_adaptive", self.surface_adaptive, low=0.0, high=10.0, low_open=True)
        check_number("exterior_ratio", self.exterior_ratio, low=0.0, high=1.0)
        check_number("exterior_offset", self.exterior_offset, low=0.0, high=0.5, low_open=True)
        check_number("sphere_count", self.sphere_count, low=0, high=100000, integer=True)
        return self


@dataclass(frozen=True)
class ParameterOptions:
    """The kernel and the smoothing.

    Attributes
    ----------
    kernel : str or Kernel
        A name in :data:`o3drbf.rbf.kernels.KERNELS` or a :class:`~o3drbf.rbf.kernels.Kernel`
        instance (its parameters are then used as they are).
    auto : bool
        Choose the multi-order parameters left at None from the data
        (:mod:`o3drbf.constraints.parameters`); else the paper's values.
    delta, tau : float or None
        Multi-order parameters.
    sigma : float or None
        Gaussian width.
    lambda_surface : float, (N,) array_like or None
        Smoothing of surface constraints (absolute, >= 0; per input point if an array).
    lambda_exterior : float
        Smoothing of exterior and sphere constraints relative to phi(0) of
        the kernel used (as the automatic lambda_surface is), >= 0: the
        constraints keep the same weight whatever delta and tau are.
        They are kept weak (50 phi(0)): they orient the function, the
        surface constraints place it; exterior constraints that pull f all
        the way to their target distort the surface (docs/data/design-measurements.md,
        "Exterior smoothing").
    """

    kernel: object = DEFAULTS["kernel"]
    auto: bool = DEFAULTS["auto"]
    delta: float | None = DEFAULTS["delta"]
    tau: float | None = DEFAULTS["tau"]
    sigma: float | None = DEFAULTS["sigma"]
    lambda_surface: object = DEFAULTS["lambda_surface"]
    lambda_exterior: float = DEFAULTS["lambda_exterior"]

    def kernel_params(self) -> dict:
        """The kernel parameters given (None dropped): ``make_kernel(kernel, **these)``."""
        return {k: v for k, v in (("delta", self.delta), ("tau", self.tau), ("sigma", self.sigma)) if v is not None}

    def validate(self) -> "ParameterOptions":
        from o3drbf.rbf.kernels import Kernel, kernel_class, make_kernel

        check_number("lambda_exterior", self.lambda_exterior, low=0.0)
        if isinstance(self.kernel, Kernel):
            if self.kernel_params():
                raise ValueError(f"kernel is a {type(self.kernel).__name__} instance: give its parameters to it, not delta/tau/sigma")
            return self
        cls = kernel_class(self.kernel)
        given = self.kernel_params()
        wrong = sorted(set(given) - set(cls.parameter_names()))
        if wrong:
            raise ValueError(
                f"{', '.join(wrong)} {'does' if len(wrong) == 1 else 'do'} not apply to the {cls.name!r} kernel "
                f"(its parameters: {', '.join(cls.parameter_names()) or 'none'})"
            )
        for name in sorted(set(given) & set(PARAMETER_RANGES)):  # positive, but beyond what fits (the kernel names the rest)
            if isinstance(given[name], (int, float)) and given[name] > 0:
                check_parameter_range(name, given[name])
        make_kernel(cls.name, **{**{k: PAPER_VALUES[k] for k in cls.parameter_names() if k in PAPER_VALUES}, **given})
        return self


@dataclass(frozen=True)
class FitOptions:
    """The solve.

    Attributes
    ----------
    solver : {"auto", "dense", "iterative", "fast"}
    robust : bool
        Iteratively reweighted fitting: surface constraints far from the
        fitted surface relative to the noise are down-weighted (their lambda
        raised) and refitted.
    """

    solver: str = DEFAULTS["solver"]
    robust: bool = DEFAULTS["robust"]

    def validate(self) -> "FitOptions":
        check_choice("solver", self.solver, SOLVER_METHODS)
        return self


@dataclass(frozen=True)
class ExtractOptions:
    """Marching cubes.

    Attributes
    ----------
    resolution : int or "auto"
        Cells along the longest side, at most :data:`MAX_RESOLUTION`; "auto":
        :func:`auto_resolution` (cells per surface-constraint spacing, clipped:
        :data:`AUTO_SIZES`).
    voxel_size : float or None
        Grid spacing in data units (overrides ``resolution``).
    bounds : (2, 3) array_like or None
        Extraction box in data coordinates (default: the data's box, padded).
    """

    resolution: int | str = DEFAULTS["resolution"]
    voxel_size: float | None = DEFAULTS["voxel_size"]
    bounds: object = DEFAULTS["bounds"]

    def validate(self) -> "ExtractOptions":
        if self.resolution != "auto":
            check_number("resolution", self.resolution, low=2, high=MAX_RESOLUTION, integer=True)
            from o3drbf.solvers.base import available_memory, gigabytes

            need = extraction_memory(int(self.resolution))
            limit = int(0.8 * available_memory())
            if need > limit:
                raise ValueError(
                    f"resolution {self.resolution} needs about {gigabytes(need)} for its grids but {gigabytes(limit)} is available; "
                    "use a smaller --resolution (or 'auto')"
                )
        if self.voxel_size is not None:
            check_number("voxel_size", self.voxel_size, low=0.0, low_open=True)
        return self


@dataclass(frozen=True)
class ConfidenceOptions:
    """Per-vertex confidence of the mesh, and trimming by it (:mod:`o3drbf.mesh.confidence`).

    Attributes
    ----------
    confidence : bool
        Compute it (``Reconstruction.confidence``; written as the PLY vertex
        property ``confidence`` by the command line).  Implied by ``trim``.
    trim : float or None
        Remove every triangle with a vertex of confidence below this, in
        [0, 1]: an open surface where nothing was seen.  None: no trimming.
    neighbours : int
        Constraints per local Gaussian-process neighbourhood.
    distance_scale : float
        Mean spacings at which the distance factor is exp(-1/2).
    """

    confidence: bool = DEFAULTS["confidence"]
    trim: float | None = DEFAULTS["trim"]
    neighbours: int = CONFIDENCE_DEFAULTS["neighbours"]
    distance_scale: float = CONFIDENCE_DEFAULTS["distance_scale"]

    @property
    def wanted(self) -> bool:
        """Whether the confidence is computed at all (asked for, or needed by ``trim``)."""
        return bool(self.confidence) or self.trim is not None

    def validate(self) -> "ConfidenceOptions":
        if not isinstance(self.confidence, bool):
            raise ValueError(f"confidence must be True or False, got {self.confidence!r}")
        if self.trim is not None:
            check_number("trim", self.trim, low=0.0, high=1.0)
        check_number("neighbours", self.neighbours, low=1, integer=True)
        check_number("distance_scale", self.distance_scale, low=0.0, low_open=True)
        return self


@dataclass(frozen=True)
class TileOptions:
    """Tiled reconstruction (:mod:`o3drbf.tiles`): f = f0 + sum_t W_t g_t over k-d tiles.

    Read by :func:`o3drbf.tiles.fit.fit_tiled`, :func:`o3drbf.tiles.run.reconstruct_tiled`
    and :func:`o3drbf.tiles.extract.extract_tiled`; the other groups (outliers,
    constraints, parameters, fit, extract) apply to the global fit f0 and to
    every tile as they apply to the untiled path.

    Attributes
    ----------
    tiles : None, "auto" or int
        Number of tiles; "auto": ``ceil(N / points_per_tile)``; None: untiled
        (the tiled entry points read it as "auto").
    scheduler : None, "synchronous", str or distributed.Client
        Where tile tasks run (:func:`o3drbf.tiles.cluster.tile_client`): None a
        LocalCluster of ``workers`` processes, "synchronous" this process, a
        Dask scheduler address (``tcp://HOST:PORT``), or a client (used as given).
    workers : int
        Workers of a LocalCluster started here (one thread each).
    memory_limit : int, str or None
        Per-worker memory limit of that LocalCluster (None: 80 % of the
        available memory shared among the workers).
    points_per_tile : int
        Target points per tile cell for ``tiles="auto"``.
    surface_count_per_tile : int or None
        Poisson-disc surface constraints per tile support (None: all its points).
    global_count : int
        Surface constraints of the global coarse fit f0.
    overlap, min_overlap : float
        Support margin on each side of a cell: ``max(overlap * half-size, min_overlap)``
        (``min_overlap`` in box units).
    partition_sample : int
        At most this many points (a seeded uniform subsample) decide f0 and the k-d cuts.
    chunk_points : int
        Points read and distributed to the tiles at a time.
    tile_dir : path or None
        Folder for the per-tile point files, storage every worker can read
        (None: a temporary folder for a file input, per-tile arrays otherwise).
    """

    tiles: object = DEFAULTS["tiles"]
    scheduler: object = DEFAULTS["scheduler"]
    workers: int = DEFAULTS["workers"]
    memory_limit: object = DEFAULTS["memory_limit"]
    points_per_tile: int = DEFAULTS["points_per_tile"]
    surface_count_per_tile: int | None = DEFAULTS["surface_count_per_tile"]
    global_count: int = DEFAULTS["global_count"]
    overlap: float = DEFAULTS["overlap"]
    min_overlap: float = DEFAULTS["min_overlap"]
    partition_sample: int = DEFAULTS["partition_sample"]
    chunk_points: int = DEFAULTS["chunk_points"]
    tile_dir: object = DEFAULTS["tile_dir"]

    def validate(self) -> "TileOptions":
        if self.tiles is not None and self.tiles != "auto":
            if isinstance(self.tiles, str):
                raise ValueError(f"tiles must be 'auto' or a whole number >= 1, got {self.tiles!r}")
            check_number("tiles", self.tiles, low=1, integer=True)
        if self.scheduler is not None and not isinstance(self.scheduler, str) and not hasattr(self.scheduler, "submit"):
            raise ValueError(f"scheduler must be None, 'synchronous', a Dask scheduler address or a distributed.Client, got {self.scheduler!r}")
        check_number("workers", self.workers, low=1, high=1024, integer=True)
        check_number("points_per_tile", self.points_per_tile, low=100, integer=True)
        if self.surface_count_per_tile is not None:
            check_number("surface_count_per_tile", self.surface_count_per_tile, low=10, integer=True)
        check_number("global_count", self.global_count, low=10, integer=True)
        check_number("overlap", self.overlap, low=0.0)
        check_number("min_overlap", self.min_overlap, low=0.0)
        if self.overlap == 0 and self.min_overlap == 0:
            raise ValueError("overlap and min_overlap are both 0: tile supports must overlap (raise overlap)")
        check_number("partition_sample", self.partition_sample, low=100, integer=True)
        check_number("chunk_points", self.chunk_points, low=1, integer=True)
        return self


#: Flat option name -> (group attribute, field name).
_FLAT = {
    "register": ("registration", "method"),
    "outliers": ("outliers", "method"),
    "outlier_radius": ("outliers", "radius"),
    "keep_components": ("outliers", "keep_components"),
    **{f.name: ("constraints", f.name) for f in fields(ConstraintOptions)},
    **{f.name: ("parameters", f.name) for f in fields(ParameterOptions)},
    **{f.name: ("fit", f.name) for f in fields(FitOptions)},
    **{f.name: ("extract", f.name) for f in fields(ExtractOptions)},
    "confidence": ("confidence", "confidence"),
    "trim": ("confidence", "trim"),
    **{f.name: ("tiles", f.name) for f in fields(TileOptions)},
}
assert set(_FLAT) == set(DEFAULTS), set(_FLAT) ^ set(DEFAULTS)


@dataclass(frozen=True)
class Options:
    """All options of :func:`o3drbf.reconstruct` and of the tiled entry points, one group per stage.

    Examples
    --------
    >>> from o3drbf import Options
    >>> options = Options.create(resolution=64, kernel='thinplate')
    >>> options.extract.resolution, options.parameters.kernel
    (64, 'thinplate')
    >>> Options.create(resolutoin=64)
    Traceback (most recent call last):
    ...
    ValueError: unknown option(s) resolutoin; valid: register, outliers, ...
    """

    registration: RegistrationOptions = field(default_factory=RegistrationOptions)
    outliers: OutlierOptions = field(default_factory=OutlierOptions)
    constraints: ConstraintOptions = field(default_factory=ConstraintOptions)
    parameters: ParameterOptions = field(default_factory=ParameterOptions)
    fit: FitOptions = field(default_factory=FitOptions)
    extract: ExtractOptions = field(default_factory=ExtractOptions)
    confidence: ConfidenceOptions = field(default_factory=ConfidenceOptions)
    tiles: TileOptions = field(default_factory=TileOptions)

    @classmethod
    def create(cls, base: "Options | None" = None, **flat) -> "Options":
        """Options from flat names (the keys of :data:`DEFAULTS`), over ``base``.

        ``basis`` is accepted as another name for ``kernel``.

        Raises
        ------
        ValueError
            An unknown name (the message lists the valid ones).
        """
        if "basis" in flat:
            if "kernel" in flat:
                raise ValueError("give kernel or basis, not both")
            flat["kernel"] = flat.pop("basis")
        unknown = sorted(set(flat) - set(_FLAT))
        if unknown:
            raise ValueError(f"unknown option(s) {', '.join(unknown)}; valid: {', '.join(DEFAULTS)}")
        opts = base or cls()
        groups: dict[str, dict] = {}
        for name, value in flat.items():
            group, attr = _FLAT[name]
            groups.setdefault(group, {})[attr] = value
        return replace(opts, **{g: replace(getattr(opts, g), **v) for g, v in groups.items()})

    def validate(self) -> "Options":
        """Check every value; return self.  Raises ValueError naming the option."""
        for f in fields(self):
            getattr(self, f.name).validate()
        return self

    def flat(self) -> dict:
        """The options as flat names (the keys of :data:`DEFAULTS`)."""
        return {name: getattr(getattr(self, g), a) for name, (g, a) in _FLAT.items()}

    def as_dict(self) -> dict:
        """Nested plain dict (for reports)."""
        return asdict(self)


from o3drbf.options.entry import COMPARE_UP, CarveOptions, CompareOptions, PhotoOptions, ViewOptions, compare_methods  # noqa: E402 - they build on Options
