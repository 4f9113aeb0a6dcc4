"""Tiled fitting: a global coarse fit f0, then one residual fit g_t per tile.

    f(x) = f0(x) + sum_t W_t(x) g_t(x)

f0 is fitted (in this process) to a Poisson-disc subsample of the points (of
a seeded sample of ``partition_sample`` of them when there are more) with the
normal path's constraints (surface, exterior along normals,
bounding sphere).  Tile t then fits g_t to the residual ``y - f0`` at
surface and exterior constraints built, the same way, from the points
inside its support, handed to it by a chunked pass (a per-tile file or
array: no process needs all the points); tiles are independent tasks (Dask
futures, or this process).  Kernel and parameters follow the normal path: the multi-order
basis, with ``auto`` the rule of :mod:`o3drbf.constraints.parameters`
applied to each fit's own constraint spacing (the tiles' are denser than
f0's), else the paper's values.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from o3drbf.options import TILE_DEFAULTS as OPTION_TILE_DEFAULTS
from o3drbf.constraints.core import (
    EXTERIOR,
    SPHERE,
    SURFACE,
    Constraints,
    bounding_sphere,
    exterior_from_normals,
    surface_constraints,
)
from o3drbf.prep.normalize import Normalization
from o3drbf.prep.sampling import mean_spacing
from o3drbf.rbf.kernels import make_kernel
from o3drbf.solvers import solve
from o3drbf.surface import ImplicitSurface
from o3drbf.tiles.cluster import run_tasks, tile_client, worker_summary
from o3drbf.tiles.partition import (
    ArrayPoints,
    Partition,
    kd_split,
    read_tile_points,
    sample_indices,
    scan_bounds,
    spread_to_tiles,
)
from o3drbf.tiles.surface import TiledSurface
from o3drbf.validation import as_points, as_vectors, check_number, shown

__all__ = ["fit_tiled", "fit_tile", "point_source", "tile_count", "TILE_DEFAULTS"]

log = logging.getLogger("o3drbf")

#: Defaults of :func:`fit_tiled` (the table lives in :mod:`o3drbf.options`).
TILE_DEFAULTS = OPTION_TILE_DEFAULTS


def tile_count(n_points: int, tiles="auto", points_per_tile: int = TILE_DEFAULTS["points_per_tile"]) -> int:
    """Number of tiles: ``ceil(n_points / points_per_tile)`` for "auto", else ``tiles``.

    Raises
    ------
    ValueError
        ``tiles`` not "auto" nor an integer in [1, n_points / 10].
    """
    if isinstance(tiles, str):
        if tiles != "auto":
            raise ValueError(f"tiles must be 'auto' or a positive integer, got {shown(tiles)}")
        ppt = check_number("points_per_tile", points_per_tile, low=100, integer=True)
        return max(1, math.ceil(n_points / ppt))
    return check_number("tiles", tiles, low=1, high=max(1, n_points // 10), integer=True)


def _kernel_and_lambda(spacing: float, noise: float | None, scale: float, delta, tau, lambda_surface):
    """The multi-order kernel and surface lambda: given values win, else the auto rule (noise given), else the paper."""
    chosen = None
    if noise is not None and None in (delta, tau, lambda_surface):
        from o3drbf.constraints.parameters import parameters_from

        chosen = parameters_from(spacing, noise, scale)
    d = delta if delta is not None else (chosen.delta if chosen else TILE_DEFAULTS["delta"])
    t = tau if tau is not None else (chosen.tau if chosen else TILE_DEFAULTS["tau"])
    kernel = make_kernel("multiorder", delta=d, tau=t)
    if lambda_surface is not None:
        lam = float(lambda_surface)
    elif chosen is not None:
        lam = chosen.lambda_relative * kernel.value_at_zero
    else:
        lam = TILE_DEFAULTS["lambda_surface"]
    return kernel, lam


def _solve_single_thread(kernel, c: Constraints, solver: str):
    """solve() with one BLAS thread: the same bits in any process or scheduler."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # without it, BLAS threads may change the last bits between schedulers
        return solve(kernel, c.points, c.values, c.smoothing, method=solver)
    with threadpool_limits(limits=1):
        return solve(kernel, c.points, c.values, c.smoothing, method=solver)


def fit_tile(t: int, store=None, base: ImplicitSurface | None = None, partition: Partition | None = None,
             settings: dict | None = None) -> tuple[ImplicitSurface, dict]:
    """Fit tile ``t``'s residual g_t (a Dask task; everything in box coordinates).

    Parameters
    ----------
    t : int
        Tile index.
    store : str or (points (m, 3), normals (m, 3))
        The points in the tile's support and their unit normals, normalized:
        a per-tile file or a pair (:func:`o3drbf.tiles.partition.spread_to_tiles`).
    base : ImplicitSurface
        f0 (identity normalization).
    partition : Partition
    settings : dict
        Constraint and kernel settings from :func:`fit_tiled`.

    Returns
    -------
    g : ImplicitSurface
        The residual fit (zero when the support holds fewer than 10 points).
    info : dict
        Counts, spacing, parameters, solver record and seconds.
    """
    t0 = time.perf_counter()
    s = settings
    sub, nsub = read_tile_points(store)
    info = {"tile": t, "points": int(len(sub))}
    if len(sub) < 10:
        kernel = make_kernel("multiorder", delta=TILE_DEFAULTS["delta"], tau=TILE_DEFAULTS["tau"])
        g = ImplicitSurface(kernel, partition.centre[t][None], np.zeros(1), np.zeros(1), Normalization.identity())
        info.update(constraints=0, seconds=time.perf_counter() - t0, method="none")
        return g, info
    seed = s["seed"] + 1 + t
    sidx = surface_constraints(sub, count=s["surface_count_per_tile"], seed=seed)
    surf = sub[sidx]
    n_ext = int(round(s["exterior_ratio"] * len(sidx)))
    ext = exterior_from_normals(surf, nsub[sidx], s["exterior_offset"], n_ext, seed=seed, reference=sub)
    ext = ext[np.all(np.abs(ext - partition.centre[t]) < partition.rho[t], axis=1)]
    spacing = mean_spacing(surf) if len(surf) > 1 else float("nan")
    kernel, lam = _kernel_and_lambda(spacing, s["noise"], s["scale"], s["delta"], s["tau"], s["lambda_surface"])
    c = Constraints.concat(Constraints.of_kind(surf, SURFACE, lam), Constraints.of_kind(ext, EXTERIOR, s["lambda_exterior"] * kernel.value_at_zero))
    residual = c.values - base.evaluate_box(c.points)
    c = Constraints(c.points, residual, c.smoothing, c.kind)
    sol = _solve_single_thread(kernel, c, s["solver"])
    g = ImplicitSurface(kernel, c.points, sol.weights, sol.poly, Normalization.identity())
    info.update(
        constraints=len(c), surface=len(surf), exterior=len(ext), spacing=spacing, delta=kernel.params["delta"],
        tau=kernel.params["tau"], lambda_surface=lam, method=sol.method, residual=float(sol.residual),
        max_abs_target=float(np.abs(residual).max()), seconds=time.perf_counter() - t0,
    )
    return g, info


def point_source(points, normals=None, seed: int = 0):
    """The points of :func:`fit_tiled` as a chunked source.

    A :class:`o3drbf.io.files.PlyVertices` (a memory-mapped binary PLY with
    normals) is used as it is, never loaded whole; arrays or an Open3D cloud
    are checked and wrapped (normals estimated with Open3D when missing).

    Returns
    -------
    PlyVertices or ArrayPoints
    """
    from o3drbf.io.files import PlyVertices

    if isinstance(points, ArrayPoints) and normals is None and points.has_normals:
        return points
    if isinstance(points, PlyVertices):
        if normals is not None:
            raise ValueError("normals come from the PLY file's nx, ny, nz; pass normals=None with a PlyVertices source")
        if not points.has_normals:
            raise ValueError(f"{points.path} has no normals (nx, ny, nz): the memory-mapped tiled path needs them; "
                             "read the file into memory instead (normals are then estimated) or add normals")
        if points.count < 10:
            raise ValueError(f"{points.path}: {points.count} points, at least 10 needed")
        return points
    cloud_normals = None
    if hasattr(points, "points") and not isinstance(points, np.ndarray):
        if getattr(points, "has_normals", lambda: False)():
            cloud_normals = np.asarray(points.normals)
    pts = as_points(points, min_count=10)
    if normals is None:
        normals = cloud_normals
    if normals is None:
        from o3drbf.pipeline import estimate_normals

        log.info("no normals given: estimating and orienting normals with Open3D (30 neighbours)")
        normals = estimate_normals(pts, seed=seed)
    return ArrayPoints(pts, as_vectors(normals, len(pts), name="normals"))


def fit_tiled(
    points,
    normals=None,
    *,
    tiles="auto",
    client=None,
    workers: int = 2,
    memory_limit=None,
    surface_count_per_tile: int | None = TILE_DEFAULTS["surface_count_per_tile"],
    points_per_tile: int = TILE_DEFAULTS["points_per_tile"],
    global_count: int = TILE_DEFAULTS["global_count"],
    overlap: float = TILE_DEFAULTS["overlap"],
    min_overlap: float = TILE_DEFAULTS["min_overlap"],
    auto: bool = True,
    delta: float | None = None,
    tau: float | None = None,
    lambda_surface: float | None = None,
    lambda_exterior: float = TILE_DEFAULTS["lambda_exterior"],
    exterior_ratio: float = TILE_DEFAULTS["exterior_ratio"],
    exterior_offset: float = TILE_DEFAULTS["exterior_offset"],
    sphere_count: int = TILE_DEFAULTS["sphere_count"],
    solver: str = "auto",
    partition_sample: int = TILE_DEFAULTS["partition_sample"],
    chunk_points: int = TILE_DEFAULTS["chunk_points"],
    tile_dir=None,
    seed: int = 0,
    progress: bool = False,
) -> TiledSurface:
    """Fit f = f0 + sum_t W_t g_t to points with outward normals, tile by tile.

    Parameters
    ----------
    points : (N, 3) array_like, open3d.geometry.PointCloud or o3drbf.io.files.PlyVertices
        Surface samples (data coordinates), N >= 10.  A ``PlyVertices``
        (:func:`o3drbf.io.files.open_ply_vertices`, a memory-mapped binary PLY
        with normals) is read in chunks of ``chunk_points``: this process never
        holds all the points, and each tile's points go to a file in
        ``tile_dir`` that its worker reads.
    normals : (N, 3) array_like, optional
        Outward normals; None: from the cloud or file, else estimated with Open3D
        (o3drbf.pipeline.estimate_normals).
    tiles : "auto" or int
        Number of tiles; "auto": ``ceil(N / points_per_tile)``.
    client : None, "synchronous", scheduler address or distributed.Client
        Where tile fits run (:mod:`o3drbf.tiles.cluster`); None starts a
        LocalCluster of ``workers`` processes when there is more than one tile.
    workers : int
        Workers of a LocalCluster started here.
    memory_limit : int or str, optional
        Per-worker memory limit of a LocalCluster started here.
    surface_count_per_tile : int or None
        Poisson-disc surface constraints per tile support (None: all its points).
    points_per_tile : int
        Target points per tile for ``tiles="auto"``.
    global_count : int
        Surface constraints of the global fit f0.
    overlap, min_overlap : float
        Support margin on each side: ``max(overlap * cell half-size, min_overlap)``
        (box units for ``min_overlap``).
    auto : bool
        Parameters left at None from the automatic rule, applied to each fit's
        own constraint spacing; else the paper's delta 10, tau 0.01, lambda 1e-3.
    delta, tau, lambda_surface, lambda_exterior, exterior_ratio, exterior_offset, sphere_count
        As in :func:`o3drbf.pipeline.reconstruct` (normalized box).
    solver : {"auto", "dense", "iterative", "fast"}
        For f0 and every tile.
    partition_sample : int
        At most this many points (a seeded uniform subsample, all of them when
        N is smaller) decide the global steps: the noise estimate, f0's
        constraints and the k-d cuts (the bounding box uses every point).
    chunk_points : int
        Points read and distributed at a time.
    tile_dir : path, optional
        Folder for the per-tile point files (storage every worker can read;
        removed after the fit if created here).  Default: a temporary folder
        when ``points`` is a file, per-tile arrays sent to each task otherwise.
    seed : int
        Seeds every random choice (tile t uses ``seed + 1 + t``).
    progress : bool
        One bar tick per finished tile.

    The result depends only on the points (not on ``chunk_points``, the
    scheduler or whether they came from a file or an array): bit-identical.

    Returns
    -------
    TiledSurface
        ``metadata`` holds the per-tile records (``tiles``), per-worker task
        time and peak memory (``workers``), the extraction
        ``bounds`` (data box padded by 5 %), parameters and timings.

    Raises
    ------
    ValueError
        Bad points, normals or parameters.
    """
    t_start = time.perf_counter()
    source = point_source(points, normals, seed=seed)
    n = source.count
    count = tile_count(n, tiles, points_per_tile)
    partition_sample = check_number("partition_sample", partition_sample, low=100, integer=True)
    chunk_points = check_number("chunk_points", chunk_points, low=1, integer=True)
    if surface_count_per_tile is not None:
        surface_count_per_tile = check_number("surface_count_per_tile", surface_count_per_tile, low=10, integer=True)
    global_count = check_number("global_count", global_count, low=10, integer=True)
    lambda_exterior = check_number("lambda_exterior", lambda_exterior, low=0.0)
    exterior_ratio = check_number("exterior_ratio", exterior_ratio, low=0.0, high=1.0)
    exterior_offset = check_number("exterior_offset", exterior_offset, low=0.0, high=0.5, low_open=True)
    sphere_count = check_number("sphere_count", sphere_count, low=0, high=100000, integer=True)
    for name, v in (("delta", delta), ("tau", tau), ("lambda_surface", lambda_surface)):
        if v is not None:
            check_number(name, v, low=0.0)
    seed = check_number("seed", seed, low=0, integer=True)

    # One pass for the bounding box, one gather for the sample: never all the points at once.
    data_lo, data_hi = scan_bounds(source, chunk_points)
    norm = Normalization.from_points(np.array([data_lo, data_hi]))
    sample_pts, nrm = source.gather(sample_indices(n, partition_sample, seed))
    box = norm.forward(sample_pts)
    del sample_pts
    noise = None
    if auto and None in (delta, tau, lambda_surface):
        from o3drbf.constraints.parameters import estimate_noise

        noise = estimate_noise(box, seed=seed)

    # f0: the normal path's constraints on a global subsample, fitted here.
    t0 = time.perf_counter()
    idx0 = surface_constraints(box, count=global_count, seed=seed)
    surf0 = box[idx0]
    ext0 = exterior_from_normals(surf0, nrm[idx0], exterior_offset, int(round(exterior_ratio * len(idx0))), seed=seed, reference=box)
    box_lo, box_hi = norm.forward(data_lo), norm.forward(data_hi)  # = the min / max of all points in the box
    sph = bounding_sphere(np.array([box_lo, box_hi]), sphere_count)
    spacing0 = mean_spacing(surf0)
    kernel0, lam0 = _kernel_and_lambda(spacing0, noise, norm.scale, delta, tau, lambda_surface)
    c0 = Constraints.concat(
        Constraints.of_kind(surf0, SURFACE, lam0),
        Constraints.of_kind(ext0, EXTERIOR, lambda_exterior * kernel0.value_at_zero),
        Constraints.of_kind(sph, SPHERE, lambda_exterior * kernel0.value_at_zero),
    )
    sol0 = _solve_single_thread(kernel0, c0, solver)
    base = ImplicitSurface(kernel0, c0.points, sol0.weights, sol0.poly, Normalization.identity())
    t_base = time.perf_counter() - t0
    log.info("tiles: global fit f0 on %d constraints (%s, %r) in %.1f s", len(c0), sol0.method, kernel0, t_base)

    pad = TILE_DEFAULTS["root_pad"] * float((box_hi - box_lo).max())
    root = np.array([box_lo - pad, box_hi + pad])
    cells_lo, cells_hi = kd_split(box, count, root)
    partition = Partition.from_cells(cells_lo, cells_hi, overlap=overlap, min_overlap=min_overlap)
    settings = {
        "seed": seed, "surface_count_per_tile": surface_count_per_tile, "exterior_ratio": exterior_ratio,
        "exterior_offset": exterior_offset, "lambda_exterior": lambda_exterior, "noise": noise, "scale": norm.scale,
        "delta": delta, "tau": tau, "lambda_surface": lambda_surface, "solver": solver,
    }
    del box, nrm
    from o3drbf.io.files import PlyVertices

    made_dir = None
    if tile_dir is None and isinstance(source, PlyVertices):
        import tempfile

        tile_dir = made_dir = tempfile.mkdtemp(prefix="o3drbf-tiles-")
    t0 = time.perf_counter()
    records: list = []
    try:
        stores, _ = spread_to_tiles(source, norm, partition, chunk_points, folder=tile_dir)
        t_spread = time.perf_counter() - t0
        log.info("tiles: %d points spread over %d tiles in %.1f s (%s)", n, count, t_spread,
                 "per-tile arrays" if tile_dir is None else f"files in {tile_dir}")
        with tile_client(client, tasks=count, workers=workers, memory_limit=memory_limit) as c:
            results = run_tasks(c, fit_tile, count, {"base": base, "partition": partition, "settings": settings},
                                per_task=[{"store": st} for st in stores], records=records,
                                progress=progress, desc="fitting tiles")
        del stores
    finally:
        if made_dir is not None:
            import shutil

            shutil.rmtree(made_dir, ignore_errors=True)
    t_tiles = time.perf_counter() - t0
    infos = [info for _, info in results]
    for info in infos:
        log.info("tile %d: %d points, %d constraints, %.1f s", info["tile"], info["points"], info["constraints"], info["seconds"])
    dpad = 0.05 * float((data_hi - data_lo).max())
    metadata = {
        "points": n,
        "tile_count": count,
        "tiles": infos,
        "base": {"constraints": len(c0), "counts": c0.counts(), "spacing": spacing0, "delta": kernel0.params["delta"],
                 "tau": kernel0.params["tau"], "lambda_surface": lam0, "method": sol0.method, "seconds": t_base},
        "noise": noise,
        "lambda_exterior": lambda_exterior,
        "exterior_offset": exterior_offset,
        "seed": seed,
        "bounds": [(data_lo - dpad).tolist(), (data_hi + dpad).tolist()],
        "overlap": overlap,
        "min_overlap": min_overlap,
        "partition_sample": int(min(n, partition_sample)),
        "workers": worker_summary(records),
        "spread_seconds": t_spread,
        "tiles_seconds": t_tiles,
        "total_seconds": time.perf_counter() - t_start,
    }
    return TiledSurface(base, [g for g, _ in results], partition, norm, metadata)
