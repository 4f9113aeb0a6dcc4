"""Tiled fitting: a global coarse fit f0, then one residual fit g_t per tile.

    f(x) = f0(x) + sum_t W_t(x) g_t(x)

Both run the untiled path's stages (:mod:`o3drbf.pipeline`) on their own
points, in the box of the whole cloud:

- f0, in this process, on a seeded uniform sample of the points
  (``partition_sample`` of them, all when there are fewer, decide the k-d
  cuts and which cameras lie inside the data and are dropped; a seeded
  subsample of ``base_points_per_constraint`` points per constraint of f0,
  :data:`o3drbf.options.TILE_DEFAULTS`, runs f0's stages): outliers
  removed (free space with cameras or scanners, the isolated-point rule),
  given normals checked, ``global_count`` surface
  constraints (denoised when the points are noisy), exterior constraints
  toward the cameras or along the normals, the bounding sphere, automatic
  parameters, the robust fit;
- tile t, as a task (Dask future, or this process), on the points inside
  its support, handed to it by a chunked pass (a per-tile file or array: no
  process needs all the points): outliers removed, normals facing away from
  their scanner flipped, up to ``surface_count_per_tile`` surface
  constraints (denoised likewise) and their exterior constraints (kept
  inside the support), parameters from its own spacing and noise, and the
  robust fit of the residual ``y - f0`` at those constraints.

The number of points kept counts each point in the one tile whose cell
holds it (the cells partition the root box).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace

import numpy as np

from o3drbf.constraints.core import EXTERIOR, Constraints
from o3drbf.options import TILE_DEFAULTS as OPTION_TILE_DEFAULTS
from o3drbf.options import ConstraintOptions, Options
from o3drbf.prep.normalize import Normalization
from o3drbf.rbf.kernels import make_kernel
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

__all__ = ["fit_tiled", "fit_tile", "point_source", "tile_count", "surface_tile_cap", "mesh_cell_box", "tile_options", "TILE_DEFAULTS"]

log = logging.getLogger("o3drbf")

#: Defaults of :func:`fit_tiled` (the table lives in :mod:`o3drbf.options`).
TILE_DEFAULTS = OPTION_TILE_DEFAULTS


def tile_count(n_points: int, tiles="auto", points_per_tile: int = TILE_DEFAULTS["points_per_tile"], surface_cap: int | None = None) -> int:
    """Number of tiles: ``ceil(n_points / points_per_tile)`` for "auto" (or None), else ``tiles``.

    Parameters
    ----------
    n_points : int
    tiles : "auto", None or int
    points_per_tile : int
    surface_cap : int, optional
        For "auto": at most this many tiles (:func:`surface_tile_cap`, the tiles
        the surface needs at the mesh's resolution), at least one.

    Raises
    ------
    ValueError
        ``tiles`` not "auto" nor an integer in [1, n_points / 10].

    Examples
    --------
    >>> tile_count(1_000_000), tile_count(10_000_000, surface_cap=20), tile_count(1000, tiles=3)
    (17, 20, 3)
    """
    if tiles is None or isinstance(tiles, str):
        if tiles not in (None, "auto"):
            raise ValueError(f"tiles must be 'auto' or a positive integer, got {shown(tiles)}")
        ppt = check_number("points_per_tile", points_per_tile, low=100, integer=True)
        count = max(1, math.ceil(n_points / ppt))
        return count if surface_cap is None else max(1, min(count, int(surface_cap)))
    return check_number("tiles", tiles, low=1, high=max(1, n_points // 10), integer=True)


def surface_tile_cap(sample_box: np.ndarray, cell_box: float, surface_count_per_tile: int | None) -> int | None:
    """The most tiles ``tiles="auto"`` uses: enough for one surface constraint per voxel the surface crosses.

    The voxels are ``constraint_cells`` (:data:`o3drbf.options.TILE_DEFAULTS`) marching-cubes cells
    wide; more tiles would put the constraints closer than the mesh shows, at a cost that grows with
    the number of points while the mesh does not change.

    Parameters
    ----------
    sample_box : (M, 3) array
        A uniform sample of the points (box coordinates), dense enough to cross every voxel.
    cell_box : float
        The marching-cubes cell (box units).
    surface_count_per_tile : int or None
        None (every point a constraint): no cap.

    Returns
    -------
    int or None
        ``ceil(occupied voxels / surface_count_per_tile)``.

    Examples
    --------
    >>> u = np.random.default_rng(0).uniform(-1, 1, (20000, 2))
    >>> plane = np.c_[u, np.zeros(len(u))]          # a 2 x 2 square: (2 / 0.075)**2 ~ 711 voxels of 0.1 * 0.75
    >>> surface_tile_cap(plane, 0.1, 100)
    8
    """
    if surface_count_per_tile is None or len(sample_box) == 0:
        return None
    size = TILE_DEFAULTS["constraint_cells"] * float(cell_box)
    keys = np.floor((sample_box - sample_box.min(axis=0)) / size).astype(np.int64)
    occupied = len(np.unique(keys[:, 0] + (keys[:, 1] << 21) + (keys[:, 2] << 42)))
    return max(1, math.ceil(occupied / int(surface_count_per_tile)))


def mesh_cell_box(options: Options, norm: Normalization, data_lo, data_hi) -> float:
    """The marching-cubes cell (box units) of :func:`o3drbf.tiles.extract.extract_tiled` with these options.

    ``resolution="auto"`` is taken at its finest (``AUTO_RESOLUTION["max_resolution"]``): the tiles'
    constraints decide it, and the cap on their number must not depend on it.
    """
    from o3drbf.extract import AUTO_RESOLUTION

    side = 1.1 * float((norm.forward(data_hi) - norm.forward(data_lo)).max())  # the extraction bounds: the data box padded by 5 %
    eo = options.extract
    if eo.voxel_size is not None:
        return float(eo.voxel_size) * float(norm.scale)
    res = AUTO_RESOLUTION["max_resolution"] if eo.resolution == "auto" else int(eo.resolution)
    return side / res


def tile_options(options: Options | None = None, **option_values) -> Options:
    """The validated :class:`~o3drbf.options.Options` of a tiled entry point: ``options`` with flat names over it.

    Raises
    ------
    ValueError
        An unknown name or a bad value; the kernel is not the multi-order one
        (the tiles' fits and the saved model take the multi-order basis);
        confidence or trimming asked for (not available on tiles).
    """
    opts = Options.create(options, **option_values).validate()
    kernel = opts.parameters.kernel
    if getattr(kernel, "name", kernel) != "multiorder":
        raise ValueError(f"tiled reconstruction takes the multiorder kernel, not {getattr(kernel, 'name', kernel)!r}; "
                         "drop --kernel (or kernel=)")
    if opts.confidence.wanted:
        raise ValueError("confidence and trimming are not available with tiles; drop --confidence/--trim or --tiles")
    return opts


def _single_thread():
    """One BLAS thread (threadpoolctl): the same bits in any process or scheduler."""
    import contextlib

    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # without it, BLAS threads may change the last bits between schedulers
        return contextlib.nullcontext()
    return threadpool_limits(limits=1)


def _stages(data, norm: Normalization, options: Options, surface_count, sphere_count: int, seed: int, support=None, occluders=None):
    """The untiled stages from outliers to parameters on ``data``, in the box ``norm``.

    ``occluders`` (box coordinates): points of the whole cloud that also block the cameras' view (those
    outside ``support`` are added to the kept points), so that a tile places no exterior constraint toward
    a camera hidden by a part of the surface outside it.

    Returns
    -------
    data : PointSet
        The kept points.
    outliers : OutlierReport
    cset : ConstraintSet
        Exterior constraints outside ``support`` ((centre, rho), box) dropped.
    params : Parameters
    """
    from o3drbf.pipeline import build_constraints, choose_parameters, remove_outliers

    data, outliers = remove_outliers(data, options.outliers, seed=seed)
    copts = replace(options.constraints, surface_count=surface_count, surface_radius=None, sphere_count=sphere_count)
    occluder = None
    if occluders is not None and data.cameras is not None and support is not None:
        outside = np.any(np.abs(occluders - support[0]) >= support[1], axis=1)
        occluder = np.concatenate([data.points, norm.inverse(occluders[outside])])
    try:
        cset = build_constraints(data, copts, seed=seed, normalization=norm, occluder=occluder)
    except ValueError as exc:  # a camera the rest of the cloud hides from this whole tile
        if occluder is None or "see no point" not in str(exc):
            raise
        data = _seen_cameras_only(data, occluder)
        cset = build_constraints(data, copts, seed=seed, normalization=norm, occluder=occluder)
    if support is not None:
        c = cset.constraints
        centre, rho = support
        keep = (c.kind != EXTERIOR) | np.all(np.abs(c.points - centre) < rho, axis=1)
        cset = replace(cset, constraints=Constraints(c.points[keep], c.values[keep], c.smoothing[keep], c.kind[keep]))
    params = choose_parameters(data, cset, options.parameters, seed=seed, confidence=outliers.confidence)
    return data, outliers, cset, params


def _seen_cameras_only(data, occluder):
    """``data`` with only the cameras that see at least one of its points past ``occluder`` (their indices remapped)."""
    from o3drbf.constraints.visibility import visibility

    seen = visibility(data.points, data.cameras, occluder=occluder, point_camera=data.point_camera, strict=False).any(axis=0)
    if seen.all() or not seen.any():
        return data
    new = np.where(seen, np.cumsum(seen) - 1, -1)
    pcam = None if data.point_camera is None else np.where(data.point_camera >= 0, new[np.maximum(data.point_camera, 0)], -1)
    log.info("tile: %d of %d cameras see none of its points past the rest of the cloud; left out here", int((~seen).sum()), len(seen))
    return replace(data, cameras=[c for c, k in zip(data.cameras, seen) if k], point_camera=pcam, _cache=data._cache)


def _fit(cset, params, options: Options, base: ImplicitSurface | None = None):
    """The robust fit of ``cset`` (of its residual to ``base`` when given), one BLAS thread."""
    from o3drbf.pipeline import fit_surface

    if base is not None:
        c = cset.constraints
        cset = replace(cset, constraints=Constraints(c.points, c.values - base.evaluate_box(c.points), c.smoothing, c.kind))
    with _single_thread():
        surface, sol, robust = fit_surface(cset, params, options.fit)
    return ImplicitSurface(params.kernel, surface.centres, surface.weights, surface.poly, Normalization.identity()), sol, robust, cset


def _tile_points(store, norm: Normalization, cameras, settings: dict, pick=None):
    """The PointSet of one tile store (data coordinates), with its normals as the whole cloud's check left them.

    ``pick``: a callable ``(box points) -> indices`` of the points to keep, or None for all of them.
    """
    from o3drbf.pointset import PointSet

    sub, nsub, pcam = read_tile_points(store)
    keep = None if pick is None else pick(sub)
    if keep is not None:
        sub, nsub, pcam = sub[keep], nsub[keep], pcam[keep]
    if not settings["normals"]:
        nsub = None
    elif settings["flip_normals"]:
        nsub = -nsub
    if cameras is None or pcam is None or (pcam < 0).all():
        pcam = None
    else:
        pcam = np.where(pcam >= 0, settings["camera_map"][np.maximum(pcam, 0).astype(np.int64)], -1)
        pcam = None if (pcam < 0).all() else pcam
    return PointSet.create(norm.inverse(sub), nsub, cameras=cameras, point_camera=pcam, min_count=0), sub


def fit_tile(t: int, store=None, base: ImplicitSurface | None = None, partition: Partition | None = None,
             settings: dict | None = None, cameras=None, occluders=None) -> tuple[ImplicitSurface, dict]:
    """Fit tile ``t``'s residual g_t (a Dask task; the surfaces in box coordinates).

    Parameters
    ----------
    t : int
        Tile index.
    store : str or tuple
        The points in the tile's support (box coordinates), their normals and
        scanner indices: a per-tile file or arrays (:func:`o3drbf.tiles.partition.spread_to_tiles`).
    base : ImplicitSurface
        f0 (identity normalization: box coordinates).
    partition : Partition
    settings : dict
        ``options``, ``normalization``, ``seed`` and how to read the store, from :func:`fit_tiled`.
    cameras : list of Camera, optional
        The cameras or scanners (data coordinates).
    occluders : (K, 3) array, optional
        With cameras: a sample of the whole cloud (box coordinates) that blocks their view too.

    Returns
    -------
    g : ImplicitSurface
        The residual fit (zero when the support holds fewer than 10 points after outlier removal).
    info : dict
        Counts (points, ``owned`` and ``owned_kept``: those in the tile's cell,
        outliers, constraints), spacing, parameters, solver record and seconds.
    """
    from o3drbf.pipeline import check_given_normals

    t0 = time.perf_counter()
    s = settings
    norm, options = s["normalization"], s["options"]
    lo, hi = partition.lo[t], partition.hi[t]
    seed = s["seed"] + 1 + t

    def owned(box_points):
        return int(np.all((box_points >= lo) & (box_points < hi), axis=1).sum())

    info = {"tile": t}
    limit = None if s["surface_count_per_tile"] is None else TILE_DEFAULTS["support_points_per_constraint"] * s["surface_count_per_tile"]

    def pick(box_points):  # denser than its constraints need: a seeded uniform subsample (None: every point)
        info["points"], info["owned"] = int(len(box_points)), owned(box_points)
        return None if limit is None or len(box_points) <= limit else sample_indices(len(box_points), limit, seed)

    data, box = _tile_points(store, norm, cameras, s, pick)
    info["used"], used_owned = int(len(data)), owned(box)
    if s.get("estimate_normals") and len(data) >= 10:
        data = replace(data, normals=oriented_normals(box, base), normals_estimated=True)
    del box
    g = None
    if len(data) >= 10:
        if data.normals is not None and data.point_camera is not None:  # local rule: each normal toward its own scanner
            data, _ = check_given_normals(data, seed=seed)
        try:
            data, outliers, cset, params = _stages(data, norm, options, s["surface_count_per_tile"], 0, seed,
                                                   (partition.centre[t], partition.rho[t]), occluders)
        except ValueError as exc:  # fewer than 10 points left: no residual in this tile
            if "at least 10" not in str(exc):
                raise
            log.info("tile %d: %s; its residual is zero", t, exc)
        else:
            g, sol, robust, cset = _fit(cset, params, options, base)
            counts = cset.constraints.counts()
            res = cset.constraints.values
            info.update(
                constraints=len(cset.constraints), surface=counts["surface"], exterior=counts["exterior"], spacing=cset.spacing,
                delta=params.kernel.params["delta"], tau=params.kernel.params["tau"], lambda_surface=params.lambda_surface,
                outliers=int(outliers.removed), denoised=int(cset.denoised), noise=float(cset.noise), method=sol.method,
                residual=float(sol.residual), robust_dropped=0 if robust is None else int(robust["dropped"]),
                max_abs_target=float(np.abs(res).max()) if len(res) else 0.0)
    kept = owned(norm.forward(data.points)) if g is not None else 0
    # Of the cell's points, those kept; from a subsample, the same fraction of all of them.
    info["owned_kept"] = kept if used_owned == info["owned"] else int(round(kept * info["owned"] / max(used_owned, 1)))
    if g is None:
        kernel = make_kernel("multiorder", delta=10.0, tau=0.01)
        g = ImplicitSurface(kernel, partition.centre[t][None], np.zeros(1), np.zeros(1), Normalization.identity())
        info.update(constraints=0, method="none", outliers=0, denoised=0)
    info["seconds"] = time.perf_counter() - t0
    return g, info


def oriented_normals(box_points: np.ndarray, base: ImplicitSurface, k: int = 30) -> np.ndarray:
    """Unit normals of points (box coordinates) from their ``k`` nearest neighbours, each turned outward along f0.

    Outward is ``-grad f0`` (f0 is -1 outside the surface and 0 on it): a tile needs no orientation of its
    own, and neighbouring tiles agree where f0 does.

    Examples
    --------
    >>> class Ball:  # f = 1 - |x|^2: -grad f = 2 x points outward
    ...     def evaluate_box(self, x, gradient=False):
    ...         return 1 - (x * x).sum(axis=1), -2 * x
    >>> x = np.random.default_rng(0).normal(size=(500, 3))
    >>> x /= np.linalg.norm(x, axis=1, keepdims=True)
    >>> n = oriented_normals(x, Ball())
    >>> bool(np.all(np.einsum("ij,ij->i", n, x) > 0.9))
    True
    """
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(box_points, dtype=float)))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(int(min(k, len(box_points) - 1))))
    n = np.asarray(pcd.normals).copy()
    _, g = base.evaluate_box(box_points, gradient=True)
    flip = np.einsum("ij,ij->i", n, -np.asarray(g)) < 0
    n[flip] *= -1
    return n


def point_source(points, normals=None, *, cameras=None, point_camera=None, seed: int = 0):
    """The points of :func:`fit_tiled` as a chunked source, and their cameras.

    A :class:`o3drbf.io.files.PlyVertices` (a memory-mapped binary PLY with
    normals) is used as it is, never loaded whole; arrays, an Open3D cloud or
    a :class:`o3drbf.pointset.PointSet` are checked and wrapped.  Without
    normals and without cameras, normals are estimated and oriented with
    Open3D over the whole cloud (:func:`o3drbf.pipeline.estimate_normals`).

    Returns
    -------
    source : PlyVertices or ArrayPoints
    cameras : list of Camera or None
    """
    from o3drbf.io.files import PlyVertices
    from o3drbf.pointset import PointSet

    if isinstance(points, ArrayPoints) and normals is None and point_camera is None:
        return points, _camera_list(cameras)
    from o3drbf.cameras.lidar import LidarPoints

    if isinstance(points, LidarPoints):  # read chunk by chunk; normals, if none and no scanners, per tile
        if normals is not None or point_camera is not None:
            raise ValueError("a lidar file source carries its own scans; pass normals=None and no point_camera")
        if cameras is not None and cameras is not points.cameras:
            raise ValueError(f"{points.path}: the scanners come from the file (E57 poses); give no cameras with a lidar file source")
        if points.count < 10:
            raise ValueError(f"{points.path}: {points.count} points, at least 10 needed")
        return points, points.cameras
    if isinstance(points, PlyVertices):
        if normals is not None or point_camera is not None:
            raise ValueError("normals come from the PLY file's nx, ny, nz; pass normals=None and no point_camera with a PlyVertices source")
        if not points.has_normals and cameras is None:
            raise ValueError(f"{points.path} has no normals (nx, ny, nz): the memory-mapped tiled path needs them (or cameras); "
                             "read the file into memory instead (normals are then estimated) or add normals")
        if points.count < 10:
            raise ValueError(f"{points.path}: {points.count} points, at least 10 needed")
        return points, _camera_list(cameras)
    if isinstance(points, PointSet):
        if normals is not None or cameras is not None or point_camera is not None:
            raise ValueError("a PointSet carries its own normals, cameras and point_camera; pass them to PointSet.create")
        data = points
    else:
        data = PointSet.create(points, normals, cameras=cameras, point_camera=point_camera)
    nrm = data.normals
    if nrm is None and data.cameras is None:
        from o3drbf.pipeline import estimate_normals

        log.info("no normals given: estimating and orienting normals with Open3D (30 neighbours)")
        nrm = estimate_normals(data.points, seed=seed)
    return ArrayPoints(data.points, nrm, data.point_camera), data.cameras


def _camera_list(cameras):
    """The cameras as a list (read from a file when a path), or None."""
    if cameras is None:
        return None
    if isinstance(cameras, (str, bytes)) or hasattr(cameras, "__fspath__"):
        from o3drbf.cameras.model import load_cameras

        cameras = load_cameras(cameras)
    cams = list(cameras)
    if not cams:
        raise ValueError("cameras is empty; give at least one camera (or None to use normals)")
    return cams


def _sample_points(source, cameras, norm: Normalization, options: Options, seed: int):
    """The PointSet of f0's sample (data coordinates) and the cameras kept (those inside the data dropped)."""
    from o3drbf.pipeline import drop_cameras_within_data
    from o3drbf.pointset import PointSet

    n = source.count
    index = sample_indices(n, options.tiles.partition_sample, seed)
    pts, nrm = source.gather(index)
    pcam = source.point_camera[index] if getattr(source, "point_camera", None) is not None else None
    data = PointSet.create(pts, nrm if source.has_normals else None, cameras=cameras, point_camera=pcam)
    if cameras is None:
        return data, None, None
    given = data.cameras
    data, _ = drop_cameras_within_data(data)
    camera_map = np.full(len(given), -1)  # index among the given cameras -> among those kept (-1: dropped)
    for new, camera in enumerate(data.cameras):
        camera_map[next(k for k, c in enumerate(given) if c is camera)] = new
    return data, data.cameras, camera_map


def _root_box(norm: Normalization, data_lo, data_hi) -> np.ndarray:
    """The k-d root box (box coordinates): the points' box padded by ``root_pad`` of its longest side."""
    box_lo, box_hi = norm.forward(data_lo), norm.forward(data_hi)  # = the min / max of all points in the box
    pad = TILE_DEFAULTS["root_pad"] * float((box_hi - box_lo).max())
    return np.array([box_lo - pad, box_hi + pad])


def fit_tiled(points, normals=None, *, cameras=None, point_camera=None, options: Options | None = None, client=None,
              seed: int = 0, progress: bool = False, **option_values) -> TiledSurface:
    """Fit f = f0 + sum_t W_t g_t tile by tile, with the untiled path's stages on every fit.

    Parameters
    ----------
    points : (N, 3) array_like, open3d.geometry.PointCloud, PointSet or o3drbf.io.files.PlyVertices
        Surface samples (data coordinates), N >= 10.  A ``PlyVertices``
        (:func:`o3drbf.io.files.open_ply_vertices`, a memory-mapped binary PLY)
        is read in chunks of ``chunk_points``: this process never holds all
        the points, and each tile's points go to a file in ``tile_dir`` that
        its worker reads.
    normals : (N, 3) array_like, optional
        Outward normals; None: from the cloud or file; without them and
        without cameras, estimated with Open3D (o3drbf.pipeline.estimate_normals).
    cameras : sequence of Camera, CameraSet or path, optional
        The cameras or scanners that saw the points: exterior constraints
        toward them and the free-space outlier test, in every tile and in f0.
    point_camera : (N,) int array_like, optional
        The camera of each point (-1 unknown).
    options : Options, optional
        All options (:class:`o3drbf.options.Options`); the ``tiles`` group
        (:class:`o3drbf.options.TileOptions`) sizes the tiles and says where
        they run, the others act on f0 and on every tile as on the untiled path.
    client : None, "synchronous", scheduler address or distributed.Client, optional
        Where tile fits run (:mod:`o3drbf.tiles.cluster`); default the
        ``scheduler`` option (None: a LocalCluster of ``workers`` processes
        when there is more than one tile).
    seed : int
        Seeds every random choice (tile t uses ``seed + 1 + t``).
    progress : bool
        One bar tick per finished tile.
    **option_values
        Any key of :data:`o3drbf.options.DEFAULTS` over ``options``
        (``tiles=8``, ``surface_count_per_tile=2000``, ``outliers="none"``, ...).

    The result depends only on the points (not on ``chunk_points``, the
    scheduler or whether they came from a file or an array): bit-identical.

    Returns
    -------
    TiledSurface
        ``metadata`` holds the per-tile records (``tiles``), per-worker task
        time and peak memory (``workers``), the points read and kept
        (``points``, ``kept``, ``outliers``), the extraction ``bounds`` (data
        box padded by 5 %), parameters, timings and CPU seconds per stage (``cpu``).

    Raises
    ------
    ValueError
        Bad points, normals, cameras or options (one line, before any costly step).

    Examples
    --------
    >>> from o3drbf.synthetic.shapes import Torus
    >>> from o3drbf.tiles.fit import fit_tiled
    >>> pts, nrm = Torus(0.7, 0.25).sample(2000, seed=1)
    >>> surface = fit_tiled(pts, nrm, tiles=2, scheduler="synchronous", global_count=300, surface_count_per_tile=500)
    >>> len(surface.tiles), bool(abs(surface(pts)).max() < 0.01)
    (2, True)
    """
    opts = tile_options(options, **option_values)
    seed = check_number("seed", seed, low=0, integer=True)
    to = opts.tiles
    t_start, cpu = time.perf_counter(), {"start": time.process_time()}
    source, camera_list = point_source(points, normals, cameras=cameras, point_camera=point_camera, seed=seed)
    n = source.count

    # One pass for the bounding box, one gather for the sample: never all the points at once.
    data_lo, data_hi = scan_bounds(source, to.chunk_points)
    norm = Normalization.from_points(np.array([data_lo, data_hi]))
    sample, camera_list, camera_map = _sample_points(source, camera_list, norm, opts, seed)
    sample_box = norm.forward(sample.points)
    cap = surface_tile_cap(sample_box, mesh_cell_box(opts, norm, data_lo, data_hi), to.surface_count_per_tile)
    by_points = tile_count(n, to.tiles, to.points_per_tile)
    count = tile_count(n, to.tiles, to.points_per_tile, surface_cap=cap)
    if count < by_points:
        log.info("tiles: %d tiles (not %d): more would put the surface constraints closer than the mesh shows; "
                 "each tile fits from a uniform subsample of its points", count, by_points)
    cells_lo, cells_hi = kd_split(sample_box, count, _root_box(norm, data_lo, data_hi))
    occluders = sample_box if camera_list is not None else None  # what hides a camera from a tile, outside the tile
    del sample_box
    # f0 is coarse: its stages run on a seeded subsample of the sample (outlier rules and noise are relative to the spacing).
    sample = sample.subset(sample_indices(len(sample), TILE_DEFAULTS["base_points_per_constraint"] * to.global_count, seed + 1))
    cpu["prepare"] = time.process_time() - cpu.pop("start")

    # f0: the untiled stages on the sample, fitted here.
    from o3drbf.pipeline import check_given_normals

    t0, u0 = time.perf_counter(), time.process_time()
    estimate = not source.has_normals and camera_list is None  # normals from the points: f0's sample here, each tile's in its task
    if estimate:
        from o3drbf.pipeline import estimate_normals

        log.info("tiles: no normals and no scanners: normals estimated on f0's sample, and in each tile oriented along f0")
        sample = replace(sample, normals=estimate_normals(sample.points, seed=seed), normals_estimated=True)
    sample, normal_check = check_given_normals(sample, seed=seed)
    flip = normal_check is not None and normal_check.changed and "flipped" in normal_check.action.split(" + ")
    if normal_check is not None and normal_check.changed and "re-oriented" in normal_check.action:
        log.warning("tiles: the given normals disagree between neighbours (%s); f0 uses them re-oriented, the tiles as given",
                    normal_check.reason)
    sample, outliers0, cset0, params0 = _stages(sample, norm, opts, to.global_count, opts.constraints.sphere_count, seed)
    base, sol0, robust0, cset0 = _fit(cset0, params0, opts)
    t_base, cpu["base"] = time.perf_counter() - t0, time.process_time() - u0
    log.info("tiles: global fit f0 on %d constraints (%s, %r) in %.1f s", len(cset0.constraints), sol0.method, params0.kernel, t_base)

    partition = Partition.from_cells(cells_lo, cells_hi, overlap=to.overlap, min_overlap=to.min_overlap)
    del sample
    task_options = replace(opts, tiles=replace(to, scheduler=None))  # a client object does not travel to the workers
    settings = {"seed": seed, "surface_count_per_tile": to.surface_count_per_tile, "options": task_options, "normalization": norm,
                "normals": bool(source.has_normals), "flip_normals": bool(flip), "camera_map": camera_map,
                "estimate_normals": bool(estimate)}
    from o3drbf.io.files import PlyVertices

    tile_dir = to.tile_dir
    made_dir = None
    from o3drbf.cameras.lidar import LidarPoints

    if tile_dir is None and isinstance(source, (PlyVertices, LidarPoints)):  # a file: its tiles' points to files too
        import tempfile

        tile_dir = made_dir = tempfile.mkdtemp(prefix="o3drbf-tiles-")
    t0, u0 = time.perf_counter(), time.process_time()
    records: list = []
    run_on = client if client is not None else to.scheduler
    try:
        stores, _ = spread_to_tiles(source, norm, partition, to.chunk_points, folder=tile_dir)
        t_spread, cpu["spread"] = time.perf_counter() - t0, time.process_time() - u0
        u0 = time.process_time()
        log.info("tiles: %d points spread over %d tiles in %.1f s (%s)", n, count, t_spread,
                 "per-tile arrays" if tile_dir is None else f"files in {tile_dir}")
        with tile_client(run_on, tasks=count, workers=to.workers, memory_limit=to.memory_limit) as c:
            results = run_tasks(c, fit_tile, count, {"base": base, "partition": partition, "settings": settings, "cameras": camera_list,
                                                     "occluders": occluders},
                                per_task=[{"store": st} for st in stores], records=records,
                                progress=progress, desc="fitting tiles")
        del stores
    finally:
        if made_dir is not None:
            import shutil

            shutil.rmtree(made_dir, ignore_errors=True)
    t_tiles, cpu["tiles_client"] = time.perf_counter() - t0, time.process_time() - u0
    cpu["tiles_tasks"] = float(sum(r["cpu"] for r in records))
    infos = [info for _, info in results]
    for info in infos:
        log.info("tile %d: %d points (%d outliers), %d constraints, %.1f s", info["tile"], info["points"], info["outliers"],
                 info["constraints"], info["seconds"])
    kept = int(sum(i["owned_kept"] for i in infos))
    owned = int(sum(i["owned"] for i in infos))
    dpad = 0.05 * float((data_hi - data_lo).max())
    c0 = cset0.constraints
    metadata = {
        "points": n,
        "subsampled_tiles": int(sum(1 for i in infos if i["used"] < i["points"])),
        "kept": kept,
        "outliers": owned - kept,
        "denoised_tiles": int(sum(1 for i in infos if i.get("denoised"))),
        "cameras": 0 if camera_list is None else len(camera_list),
        "normals_flipped": bool(flip),
        "tile_count": count,
        "tiles": infos,
        "base": {"constraints": len(c0), "counts": c0.counts(), "spacing": cset0.spacing, "delta": params0.kernel.params["delta"],
                 "tau": params0.kernel.params["tau"], "lambda_surface": params0.lambda_surface, "method": sol0.method,
                 "outliers": int(outliers0.removed), "outlier_reason": outliers0.reason, "denoised": int(cset0.denoised),
                 "seconds": t_base},
        "noise": float(cset0.noise) if np.isfinite(cset0.noise) else None,
        "lambda_exterior": params0.lambda_exterior,
        "exterior_offset": opts.constraints.exterior_offset,
        "seed": seed,
        "bounds": [(data_lo - dpad).tolist(), (data_hi + dpad).tolist()],
        "overlap": to.overlap,
        "min_overlap": to.min_overlap,
        "partition_sample": int(min(n, to.partition_sample)),
        "workers": worker_summary(records),
        "spread_seconds": t_spread,
        "tiles_seconds": t_tiles,
        "cpu": cpu,
        "total_seconds": time.perf_counter() - t_start,
    }
    return TiledSurface(base, [g for g, _ in results], partition, norm, metadata)
