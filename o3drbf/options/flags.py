"""What each option says on the command line: the help table the flags are generated from.

:data:`FLAGS` gives every option of the tables of :mod:`o3drbf.options` its
help text, kind of value and flag; :data:`ENTRY_FLAGS` says which options
each command offers, in which group.  :mod:`o3drbf.cli.arguments` turns
them into argparse arguments, the defaults read from
:func:`o3drbf.options.defaults` when the parser is built.  A help text
names no number of its own: ``{name}`` fields are filled from
:func:`help_values` (the code's constants) and the default clause is
written from the entry point's default, so neither can drift from the code.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Flag", "FLAGS", "ENTRY_FLAGS", "GROUPS", "flag_for", "help_values", "help_text"]


@dataclass(frozen=True)
class Flag:
    """One option on the command line.

    Attributes
    ----------
    help : str
        The help text without its default clause; ``{name}`` fields come from :func:`help_values`.
    kind : str
        The value: "float", "int" (>= ``low``), "count" (auto or N), "auto_bool" (auto, on or off),
        "bool" (``--x`` / ``--no-x``), "store_true", "store_false", "choice", "text", "box", "rgb",
        "size" (two whole numbers), "layers" (one or more of :data:`o3drbf.options.VIEW_LAYERS`).
    choices : str or None
        A key of :func:`help_values` holding the valid values ("choice", "layers").
    none : str or None
        The default clause when the default is None ("default: ..."); None: no clause.
    flags : tuple of str
        The flag strings (default ``--`` and the name with dashes).
    metavar : str or None
    low : int or None
        Smallest whole number ("int") the flag takes; None: any (the range is the options' ``validate``, one line).
    """

    help: str
    kind: str = "text"
    choices: str | None = None
    none: str | None = None
    flags: tuple = ()
    metavar: str | None = None
    low: int | None = None


_PARAM = "kernel and parameters (lengths in the 2x2x2 box the data are normalized into)"

#: Group titles of ``--help``.
GROUPS = {
    "parameters": _PARAM,
    "scans": "scans and outliers",
    "constraints": "constraints",
    "solve": "solve and mesh",
    "confidence": "confidence (off by default)",
    "tiles": "tiles (beyond one machine; needs pip install 'o3drbf[tiles]')",
    "carving": "carving",
    "surface": "surface (lengths in the 2x2x2 box the data are normalized into)",
    "methods": "methods",
    "o3drbf": "the o3drbf rows (as o3drbf reconstruct; lengths in the 2x2x2 box)",
    "mesh": "a finished mesh (INPUT with faces: shown as it is, no refit)",
    "poisson": "Open3D Poisson",
    "sliders": "starting values of the sliders",
    "fit": "fit",
    "check": "check",
    "window": "window",
}

#: Every option's flag (``"entry.name"`` keys: where one entry point's flag differs from the shared one).
FLAGS = {
    # reconstruct: kernel and parameters
    "kernel": Flag("radial basis function", "choice", choices="kernels", flags=("--kernel", "--basis")),
    "auto": Flag("choose delta, tau and lambda-surface from the data's spacing and noise; --no-auto: the paper's values delta {paper_delta:g}, "
                 "tau {paper_tau:g}, lambda-surface {paper_lambda_surface:g}. An explicit --delta, --tau or --lambda-surface overrides only that one",
                 "bool"),
    "delta": Flag("multiorder: first-order weight", "float", none="--auto, or {paper_delta:g}"),
    "tau": Flag("multiorder: third-order weight", "float", none="--auto, or {paper_tau:g}"),
    "sigma": Flag("gaussian: width", "float", none="{paper_sigma:g}"),
    "lambda_surface": Flag("smoothing of surface constraints, >= 0", "float", none="--auto, or {paper_lambda_surface:g}"),
    "lambda_exterior": Flag("smoothing of exterior constraints, relative to phi(0) of the kernel", "float"),
    # scans and outliers
    "register": Flag("auto: with cameras and the scan of each point, move each scan rigidly onto the others when that makes them markedly "
                     "more consistent (small pose errors); none: never", "choice", choices="register"),
    "outliers": Flag("auto: free-space consistency with cameras, an isolated-point rule without, and a robust fit; largest: keep the "
                     "largest connected components; statistical: Open3D's filter", "choice", choices="outliers"),
    "outlier_radius": Flag("neighbourhood radius for --outliers largest, in data units", "float", none="3 mean spacings"),
    "keep_components": Flag("components kept by --outliers largest", "int"),
    "robust": Flag("iteratively reweighted fit: down-weight surface constraints far from the surface", "bool"),
    # constraints
    "surface_count": Flag("Poisson-disc subsample to about N surface constraints; auto: points / {points_per_constraint}, between "
                          "{min_constraints:,} and {max_constraints:,}", "count", metavar="auto|N"),
    "surface_radius": Flag("Poisson-disc radius (box units) instead of --surface-count", "float"),
    "exterior_ratio": Flag("exterior constraints per surface constraint", "float"),
    "exterior_offset": Flag("distance of exterior constraints from the surface, box units", "float"),
    "sphere_count": Flag("exterior constraints on a sphere around the data", "int"),
    "denoise": Flag("move the surface constraints onto local quadric fits of all the points; auto: when the noise exceeds "
                    "{denoise_min_noise:g} constraint spacings", "auto_bool", metavar="auto|on|off"),
    # solve and mesh
    "solver": Flag("auto: dense up to {dense_auto_max:,} constraints (when it fits in memory), fast above", "choice", choices="solvers"),
    "resolution": Flag("marching-cubes cells along the longest side, at most {max_resolution}; auto: {cells_per_spacing:g} per constraint "
                       "spacing, {min_resolution} to {max_resolution_auto}", "count", metavar="auto|N"),
    "voxel_size": Flag("grid spacing in data units (overrides --resolution)", "float"),
    # confidence
    "confidence": Flag("per-vertex confidence in [0, 1] from the fit (GP posterior variance of the kernel and distance to the surface "
                       "constraints), written as the float PLY vertex property 'confidence' (needs a .ply output)", "store_true"),
    "trim": Flag("remove triangles with a vertex of confidence below CONFIDENCE (0..1): an open surface where nothing was seen", "float",
                 none="no trimming", metavar="CONFIDENCE"),
    # tiles
    "tiles": Flag("tiled reconstruction over N k-d tiles blended by a partition of unity (auto: untiled when the input fits in memory, "
                  "said in one line; else one tile per {points_per_tile:,} points)", "count", metavar="auto|N", none="untiled"),
    "scheduler": Flag("Dask scheduler address for --tiles, tcp://HOST:PORT (a binary PLY's tile files go to the temporary folder: on other "
                      "machines point TMPDIR at storage they share; 'synchronous': in this process)", metavar="ADDR",
                      none="a local cluster of --workers processes"),
    "workers": Flag("worker processes of the local Dask cluster with --tiles, one thread each", "int"),
    # photos
    "photos.outlier_radius": Flag("neighbourhood radius for --outliers largest, in data units", "float",
                                  none="{photo_outlier_voxels:g} carving voxels"),
    "bounds": Flag("carving box 'xmin ymin zmin xmax ymax zmax', 'silhouettes' (the box of the region inside every silhouette) or 'auto' "
                   "(a Middlebury README's box if the folder has one, else silhouettes)", "box"),
    "voxels": Flag("carving voxels along the box's longest side, 8..{max_resolution}", "int"),
    "background": Flag("background colour r,g,b in [0, 1]", "rgb"),
    "threshold": Flag("foreground: largest channel difference from the background above this", "float"),
    "min_area": Flag("silhouette specks and holes up to this many pixels are cleaned", "int"),
    "photo_consistency": Flag("carve surface voxels whose colour spread (RMS std, colours in [0, 1]) across the cameras that see them "
                              "exceeds this; 0 keeps the visual hull", "float"),
    "sweeps": Flag("photo-consistency sweeps", "int"),
    "min_views": Flag("cameras that must see a voxel before its colours are compared", "int"),
    "keep_silhouettes": Flag("let photo-consistency carve voxels on the silhouettes' outline too (shrinks the silhouettes)", "store_false",
                             flags=("--carve-outline",)),
    "iou_stride": Flag("check the silhouettes at every N-th pixel", "int", metavar="N"),
    # compare
    "methods": Flag("comma-separated, from: {methods}", none="all"),
    "poisson_depth": Flag("Open3D Poisson octree depth, 1..12", "int"),
    "density_quantile": Flag("Poisson (raw points): trim vertices below this density quantile (0: the closed surface; the tutorial "
                             "variant always trims at {tutorial_quantile:g})", "float"),
    "n_samples": Flag("points drawn per mesh for the measures against --truth", "int"),
    "up": Flag("the data's up axis, for the picture's views (the Stanford bunny: y)", "choice", choices="compare_up"),
    # view
    "view.up": Flag("the data's up axis; auto: the cameras' up, else z", "choice", choices="view_up"),
    "view.resolution": Flag("marching-cubes cells along the longest side, 2..{max_resolution}", "int"),
    "view.surface_count": Flag("about this many surface constraints", "int"),
    "level": Flag("iso-level of the shown surface", "float"),
    "poisson": Flag("no Open3D Poisson panel", "store_false", flags=("--no-poisson",)),
    "window_size": Flag("pixels", "size", metavar=("W", "H")),
    "save_prefix": Flag("keys m / k write PREFIX_mesh.ply / PREFIX.png", metavar="PREFIX"),
    "show_sphere": Flag("show the sphere constraints at start (key 4)", "store_true"),
    "hide": Flag("layers hidden at start: {layers}", "layers", metavar="LAYER"),
    "max_points": Flag("draw at most this many points per point layer (a seeded subsample)", "int"),
    "zoom": Flag("start view: 1 fits the data, 0.3 also shows cameras further out", "float"),
    "color_by": Flag("colour the mesh by a per-vertex field: a PLY vertex property (e.g. confidence, distance) or x, y, z", metavar="FIELD"),
    "distance_to": Flag("colour the mesh by its distance to the mesh OTHER, shown beside it coloured by its distance to the mesh (same "
                        "camera, same colour range)", metavar="OTHER"),
    "refit": Flag("take a mesh's vertices as points and fit them (instead of showing the mesh)", "store_true"),
}

_RECONSTRUCT = [
    ("parameters", ["kernel", "auto", "delta", "tau", "sigma", "lambda_surface", "lambda_exterior"]),
    ("scans", ["register", "outliers", "outlier_radius", "keep_components", "robust"]),
    ("constraints", ["surface_count", "surface_radius", "exterior_ratio", "exterior_offset", "sphere_count", "denoise"]),
    ("solve", ["solver", "resolution", "voxel_size"]),
]

#: Entry point -> its groups of options on the command line, in ``--help`` order.
ENTRY_FLAGS = {
    "reconstruct": [*_RECONSTRUCT, ("confidence", ["confidence", "trim"]), ("tiles", ["tiles", "scheduler", "workers"])],
    "photos": [("carving", ["bounds", "voxels", "background", "threshold", "min_area", "photo_consistency", "sweeps", "min_views",
                            "keep_silhouettes"]),
               *_RECONSTRUCT, ("check", ["iou_stride"])],
    "compare": [("methods", ["methods", "poisson_depth", "density_quantile", "n_samples", "up"]),
                *[("o3drbf" if g == "parameters" else g, [n for n in names if n != "kernel"]) for g, names in _RECONSTRUCT]],
    "view": [("mesh", ["color_by", "distance_to", "refit"]), ("poisson", ["poisson", "poisson_depth"]),
             ("sliders", ["auto", "lambda_surface", "delta", "tau", "level", "resolution"]), ("fit", ["surface_count", "outliers"]),
             ("window", ["window_size", "save_prefix", "show_sphere", "hide", "max_points", "zoom", "up"])],
}


def flag_for(entry: str, name: str) -> Flag:
    """The :class:`Flag` of option ``name`` in ``entry`` (its own, ``"entry.name"``, else the shared one)."""
    return FLAGS.get(f"{entry}.{name}") or FLAGS[name]


def help_values() -> dict:
    """The constants help texts name (the code's own: the solver switch, the resolution limit, the automatic sizes, ...)."""
    from o3drbf.options import (AUTO_SIZES, COMPARE_PEERS, COMPARE_TUTORIAL, DENOISE_MIN_NOISE, MAX_RESOLUTION, OUTLIER_METHODS, PAPER_VALUES, PHOTO_OUTLIER_VOXELS,
                                REGISTER_METHODS, SOLVER_METHODS, TILE_DEFAULTS, VIEW_LAYERS, VIEW_UP)
    from o3drbf.options.entry import COMPARE_UP
    from o3drbf.rbf.kernels import KERNELS
    from o3drbf.solvers import DENSE_AUTO_MAX

    a = AUTO_SIZES
    return {
        **{f"paper_{k}": v for k, v in PAPER_VALUES.items()},
        "points_per_constraint": a["points_per_constraint"], "min_constraints": a["min_constraints"], "max_constraints": a["max_constraints"],
        "cells_per_spacing": a["cells_per_spacing"], "min_resolution": a["min_resolution"], "max_resolution_auto": a["max_resolution"],
        "max_resolution": MAX_RESOLUTION, "denoise_min_noise": DENOISE_MIN_NOISE, "dense_auto_max": DENSE_AUTO_MAX,
        "points_per_tile": TILE_DEFAULTS["points_per_tile"], "tutorial_quantile": COMPARE_TUTORIAL["density_quantile"],
        "photo_outlier_voxels": PHOTO_OUTLIER_VOXELS,
        "kernels": tuple(KERNELS), "register": REGISTER_METHODS, "outliers": OUTLIER_METHODS, "solvers": SOLVER_METHODS,
        "compare_up": COMPARE_UP, "view_up": VIEW_UP, "layers": ", ".join(VIEW_LAYERS),
        "methods": ", ".join((*KERNELS, *COMPARE_PEERS)),
    }


def help_text(entry: str, name: str, default, values: dict | None = None) -> str:
    """The help of option ``name`` of ``entry`` whose default is ``default``: the table's text and its default clause.

    The clause says the entry point's default (argparse's ``%(default)s``, ``on``/``off`` for switches),
    or the flag's ``none`` text when the default is None.
    """
    flag = flag_for(entry, name)
    values = help_values() if values is None else values
    text = flag.help.format(**values).replace("%", "%%")
    if flag.kind in ("store_true", "store_false"):
        return text
    if flag.kind == "bool":
        return f"{text} (default: {'on' if default else 'off'})"
    if default is None or default == ():
        return text + (f" (default: {flag.none.format(**values)})" if flag.none else "")
    if flag.kind == "auto_bool" and isinstance(default, bool):
        return f"{text} (default {'on' if default else 'off'})"
    if isinstance(default, (tuple, list)):
        return f"{text} (default {' '.join(format(v, 'g') if isinstance(v, float) else str(v) for v in default)})"
    return f"{text} (default %(default)s)"
