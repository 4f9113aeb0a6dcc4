"""The options of ``o3drbf photos``, ``o3drbf compare`` and ``o3drbf view``.

Each entry point's options hold :class:`~o3drbf.options.Options` (the
reconstruction it runs) and its own group, with the same three ways in as
:func:`o3drbf.reconstruct`: ``Options``-like objects built by ``create``
from flat names over a base, checked once by ``validate``, and read back
by ``flat``.  Their defaults are the tables of :mod:`o3drbf.options`
(:func:`o3drbf.options.defaults` of each entry point).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import numpy as np

from o3drbf.options import (CARVE_DEFAULTS, COMPARE_DEFAULTS, COMPARE_PEERS, COMPARE_OVERRIDES, DEFAULTS, MAX_RESOLUTION, PHOTO_DEFAULTS, PHOTO_OVERRIDES,
                            VIEW_DEFAULTS, VIEW_UP, VIEWER_OVERRIDES, Options)
from o3drbf.validation import check_choice, check_number

__all__ = ["CarveOptions", "PhotoOptions", "CompareOptions", "ViewOptions", "COMPARE_UP", "compare_methods", "PHOTO_NAMES"]

#: The data's up axes ``o3drbf compare --up`` takes (the picture's views).
COMPARE_UP = ("x", "y", "z", "-x", "-y", "-z")


def compare_methods(methods) -> tuple[str, ...]:
    """Method names of ``o3drbf compare`` from a comma-separated string or a sequence: every registered
    kernel (:data:`o3drbf.rbf.kernels.KERNELS`) and :data:`o3drbf.options.COMPARE_PEERS`.

    Raises ``ValueError`` naming the unknown ones and listing the valid ones.

    Examples
    --------
    >>> compare_methods("multiorder, poisson,multiorder")
    ('multiorder', 'poisson')
    """
    from o3drbf.rbf.kernels import KERNELS

    if isinstance(methods, str):
        names = [m.strip().lower() for m in methods.split(",") if m.strip()]
    else:
        names = [str(m).strip().lower() for m in methods]
    valid = (*KERNELS, *COMPARE_PEERS)
    if not names:
        raise ValueError(f"no methods given; valid methods: {', '.join(valid)}")
    unknown = [m for m in names if m not in valid]
    if unknown:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, unknown))}; valid methods: {', '.join(valid)}")
    return tuple(dict.fromkeys(names))  # drop repeats, keep order


def _create(cls, base, own: dict, inner: str, flat: dict):
    """``cls`` over ``base`` from flat names: ``own`` maps a name to (group or None, field); the rest go to ``Options.create``
    of the attribute ``inner``."""
    opts = base or cls()
    valid = set(own) | (set(DEFAULTS) - set(own))
    unknown = sorted(set(flat) - valid - {"basis"})
    if unknown:
        raise ValueError(f"unknown option(s) {', '.join(unknown)}; valid: {', '.join(sorted(valid))}")
    changes: dict = {}
    groups: dict = {}
    for name, value in flat.items():
        if name in own:
            group, attr = own[name]
            if group is None:
                changes[attr] = value
            else:
                groups.setdefault(group, {})[attr] = value
    rest = {k: v for k, v in flat.items() if k not in own}
    if rest:
        changes[inner] = Options.create(getattr(opts, inner), **rest)
    for group, values in groups.items():
        changes[group] = replace(getattr(opts, group), **values)
    return replace(opts, **changes)


def _flat(opts, own: dict, inner: str) -> dict:
    out = {k: v for k, v in getattr(opts, inner).flat().items() if k not in own}
    for name, (group, attr) in own.items():
        out[name] = getattr(opts if group is None else getattr(opts, group), attr)
    return out


@dataclass(frozen=True)
class CarveOptions:
    """Space carving (:func:`o3drbf.photo.carve.carve`).

    Attributes
    ----------
    resolution : int
        Voxels along the box's longest side (``--voxels``).
    background : (3,) floats in [0, 1]
        Background colour of the photographs.
    threshold : float
        Foreground: the largest channel difference from the background above this, in (0, 1).
    min_area : int
        Silhouette specks and holes up to this many pixels are cleaned.
    photo_consistency : float or None
        Carve surface voxels whose colour spread (RMS standard deviation,
        colours in [0, 1]) across the cameras that see them exceeds this;
        None or 0: the visual hull.
    sweeps : int
        Photo-consistency sweeps.
    min_views : int
        Cameras that must see a voxel for its colours to be compared (>= 2).
    keep_silhouettes : bool
        Photo-consistency never carves a voxel on a silhouette's outline.
    """

    resolution: int = CARVE_DEFAULTS["resolution"]
    background: tuple = CARVE_DEFAULTS["background"]
    threshold: float = CARVE_DEFAULTS["threshold"]
    min_area: int = CARVE_DEFAULTS["min_area"]
    photo_consistency: float | None = CARVE_DEFAULTS["photo_consistency"]
    sweeps: int = CARVE_DEFAULTS["sweeps"]
    min_views: int = CARVE_DEFAULTS["min_views"]
    keep_silhouettes: bool = CARVE_DEFAULTS["keep_silhouettes"]

    def validate(self) -> "CarveOptions":
        check_number("resolution", self.resolution, low=8, high=MAX_RESOLUTION, integer=True)
        bg = np.asarray(self.background, dtype=float).reshape(-1)
        if bg.shape != (3,) or not np.isfinite(bg).all() or bg.min() < 0 or bg.max() > 1:
            raise ValueError(f"background must be an RGB colour with components in [0, 1], got {np.asarray(self.background).tolist()}")
        check_number("threshold", self.threshold, low=0.0, high=1.0, low_open=True)
        check_number("min_area", self.min_area, low=0, integer=True)
        if self.photo_consistency is not None:
            check_number("photo_consistency", self.photo_consistency, low=0.0, high=1.0)
        check_number("sweeps", self.sweeps, low=0, integer=True)
        check_number("min_views", self.min_views, low=2, integer=True)
        if not isinstance(self.keep_silhouettes, bool):
            raise ValueError(f"keep_silhouettes must be True or False, got {self.keep_silhouettes!r}")
        return self


#: ``o3drbf photos``' own flat names -> (group, field); the carving box ``bounds`` is the photos' (the reconstruction's
#: box is the carving's), ``voxels`` the carving resolution (``resolution`` is the marching cubes', as for reconstruct).
PHOTO_NAMES = {
    "bounds": (None, "bounds"),
    "iou_stride": (None, "iou_stride"),
    "voxels": ("carving", "resolution"),
    **{f.name: ("carving", f.name) for f in fields(CarveOptions) if f.name != "resolution"},
}


@dataclass(frozen=True)
class PhotoOptions:
    """All options of :func:`o3drbf.photo.pipeline.run_photos` (``o3drbf photos``).

    Attributes
    ----------
    bounds : "auto", "silhouettes" or (2, 3) array_like
        Carving box.  "auto": a box the folder's README gives (Middlebury),
        else "silhouettes": the box of the region inside every silhouette.
    carving : CarveOptions
    surface : Options
        The fit of the carved shell: :data:`o3drbf.options.DEFAULTS` with
        :data:`o3drbf.options.PHOTO_OVERRIDES` (carved shells are dense and
        nearly noise-free).  ``outlier_radius`` None: 2.5 voxels.
    iou_stride : int
        Check the silhouettes at every ``iou_stride``-th pixel.

    Examples
    --------
    >>> opts = PhotoOptions.create(voxels=96, surface_count=2000)
    >>> opts.carving.resolution, opts.surface.constraints.surface_count
    (96, 2000)
    """

    bounds: object = PHOTO_DEFAULTS["bounds"]
    carving: CarveOptions = field(default_factory=CarveOptions)
    surface: Options = field(default_factory=lambda: Options.create(**PHOTO_OVERRIDES))
    iou_stride: int = PHOTO_DEFAULTS["iou_stride"]

    @classmethod
    def create(cls, base: "PhotoOptions | None" = None, **flat) -> "PhotoOptions":
        """From flat names (:data:`PHOTO_NAMES` and the keys of :data:`o3drbf.options.DEFAULTS`), over ``base``.

        Examples
        --------
        >>> PhotoOptions.create(voxels=64, delta=5.0).carving.resolution
        64
        """
        return _create(cls, base, PHOTO_NAMES, "surface", flat)

    def validate(self) -> "PhotoOptions":
        """Check every value; return self.  Raises ValueError naming the option."""
        if isinstance(self.bounds, str):
            check_choice("bounds", self.bounds, ("auto", "silhouettes"))
        else:
            b = np.asarray(self.bounds, dtype=float).reshape(-1)
            if b.shape != (6,) or not np.isfinite(b).all() or (b[3:] <= b[:3]).any():
                raise ValueError(f"bounds must be 'auto', 'silhouettes' or [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, "
                                 f"got {np.asarray(self.bounds).tolist()}")
        self.carving.validate()
        self.surface.validate()
        check_number("iou_stride", self.iou_stride, low=1, integer=True)
        return self

    def flat(self) -> dict:
        """The options as flat names (those :meth:`create` takes)."""
        return _flat(self, PHOTO_NAMES, "surface")


COMPARE_NAMES = {name: (None, name) for name in COMPARE_DEFAULTS}


@dataclass(frozen=True)
class CompareOptions:
    """All options of :func:`o3drbf.evaluation.compare.compare` (``o3drbf compare``).

    Attributes
    ----------
    methods : str, sequence of str or None
        Methods to run (:func:`o3drbf.evaluation.compare.parse_methods`); None: all.
    poisson_depth : int
        Open3D Poisson octree depth, 1..12.
    density_quantile : float
        Poisson (raw points): trim vertices below this density quantile, in
        [0, 1] (0 keeps the closed surface; the tutorial variant always trims).
    n_samples : int
        Points drawn per mesh for the measures against a reference.
    up : str
        The data's up axis for the picture (:data:`COMPARE_UP`).
    o3drbf : Options
        What the o3drbf rows run (each with its own kernel):
        :data:`o3drbf.options.DEFAULTS` with :data:`o3drbf.options.COMPARE_OVERRIDES`.

    Examples
    --------
    >>> opts = CompareOptions.create(methods="multiorder,poisson", poisson_depth=7, surface_count=800)
    >>> opts.methods, opts.poisson_depth, opts.o3drbf.constraints.surface_count
    ('multiorder,poisson', 7, 800)
    """

    methods: object = COMPARE_DEFAULTS["methods"]
    poisson_depth: int = COMPARE_DEFAULTS["poisson_depth"]
    density_quantile: float = COMPARE_DEFAULTS["density_quantile"]
    n_samples: int = COMPARE_DEFAULTS["n_samples"]
    up: str = COMPARE_DEFAULTS["up"]
    o3drbf: Options = field(default_factory=lambda: Options.create(**COMPARE_OVERRIDES))

    @classmethod
    def create(cls, base: "CompareOptions | None" = None, **flat) -> "CompareOptions":
        """From flat names (:data:`o3drbf.options.COMPARE_DEFAULTS` and the keys of :data:`o3drbf.options.DEFAULTS`), over ``base``.

        Examples
        --------
        >>> CompareOptions.create(poisson_depth=6, surface_count=800).o3drbf.constraints.surface_count
        800
        """
        return _create(cls, base, COMPARE_NAMES, "o3drbf", flat)

    def validate(self) -> "CompareOptions":
        """Check every value; return self.  Raises ValueError naming the option."""
        if self.methods is not None:
            compare_methods(self.methods)
        check_number("poisson_depth", self.poisson_depth, low=1, high=12, integer=True)
        check_number("density_quantile", self.density_quantile, low=0.0, high=1.0)
        check_number("n_samples", self.n_samples, low=100, integer=True)
        check_choice("up", self.up, COMPARE_UP)
        self.o3drbf.validate()
        return self

    def flat(self) -> dict:
        """The options as flat names (those :meth:`create` takes)."""
        return _flat(self, COMPARE_NAMES, "o3drbf")


VIEW_NAMES = {name: (None, name) for name in VIEW_DEFAULTS}


@dataclass(frozen=True)
class ViewOptions:
    """All options of the viewer (``o3drbf view``, :mod:`o3drbf.viewers.app`).

    Attributes
    ----------
    fit : Options
        The first fit (the sliders start from it): :data:`o3drbf.options.DEFAULTS`
        with :data:`o3drbf.options.VIEWER_OVERRIDES`; ``resolution`` a whole
        number, at most :data:`o3drbf.options.MAX_RESOLUTION`.
    level : float
        Iso-level of the shown surface.
    poisson : bool
        Show Open3D Poisson beside it.
    poisson_depth : int
        Its octree depth, 1..12.
    window_size : (int, int)
        Pixels, at least 200 x 150.
    save_prefix : str
        Keys m / k write ``PREFIX_mesh.ply`` / ``PREFIX.png``.
    show_sphere : bool
        Show the sphere constraints at start.
    hide : tuple of str
        Layers hidden at start.
    max_points : int
        Points drawn per point layer (a seeded subsample).
    zoom : float
        Start view: 1 fits the data, in 0.01..100.
    up : str
        The data's up axis (:data:`o3drbf.options.VIEW_UP`); "auto": the cameras' up, else z.
    color_by : str or None
        A finished mesh: colour it by this per-vertex field.
    distance_to : path or None
        A finished mesh: colour it by its distance to this mesh.
    refit : bool
        A finished mesh: fit its vertices instead of showing it.

    Examples
    --------
    >>> opts = ViewOptions.create(zoom=0.5, resolution=48)
    >>> opts.zoom, opts.fit.extract.resolution
    (0.5, 48)
    """

    fit: Options = field(default_factory=lambda: Options.create(**VIEWER_OVERRIDES))
    level: float = VIEW_DEFAULTS["level"]
    poisson: bool = VIEW_DEFAULTS["poisson"]
    poisson_depth: int = VIEW_DEFAULTS["poisson_depth"]
    window_size: tuple = VIEW_DEFAULTS["window_size"]
    save_prefix: str = VIEW_DEFAULTS["save_prefix"]
    show_sphere: bool = VIEW_DEFAULTS["show_sphere"]
    hide: tuple = VIEW_DEFAULTS["hide"]
    max_points: int = VIEW_DEFAULTS["max_points"]
    zoom: float = VIEW_DEFAULTS["zoom"]
    up: str = VIEW_DEFAULTS["up"]
    color_by: str | None = VIEW_DEFAULTS["color_by"]
    distance_to: object = VIEW_DEFAULTS["distance_to"]
    refit: bool = VIEW_DEFAULTS["refit"]

    @classmethod
    def create(cls, base: "ViewOptions | None" = None, **flat) -> "ViewOptions":
        """From flat names (:data:`o3drbf.options.VIEW_DEFAULTS` and the keys of :data:`o3drbf.options.DEFAULTS`), over ``base``.

        Examples
        --------
        >>> ViewOptions.create(zoom=0.5, resolution=96).fit.extract.resolution
        96
        """
        return _create(cls, base, VIEW_NAMES, "fit", flat)

    def validate(self) -> "ViewOptions":
        """Check every value; return self.  Raises ValueError naming the option."""
        self.fit.validate()
        check_number("resolution", self.fit.extract.resolution, low=2, high=MAX_RESOLUTION, integer=True)
        check_number("surface_count", self.fit.constraints.surface_count, low=10, integer=True)
        check_number("level", self.level)
        check_number("poisson_depth", self.poisson_depth, low=1, high=12, integer=True)
        w, h = self.window_size
        if int(w) < 200 or int(h) < 150:
            raise ValueError(f"window_size must be at least 200 150, got {w} {h}")
        check_number("max_points", self.max_points, low=1, integer=True)
        check_number("zoom", self.zoom, low=0.01, high=100.0)
        check_choice("up", self.up, VIEW_UP)
        from o3drbf.options import VIEW_LAYERS

        for layer in self.hide:
            check_choice("hide", layer, VIEW_LAYERS)
        return self

    def flat(self) -> dict:
        """The options as flat names (those :meth:`create` takes)."""
        return _flat(self, VIEW_NAMES, "fit")
