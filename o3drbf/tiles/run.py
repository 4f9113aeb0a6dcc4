"""One call for the command line: fit and mesh tile by tile on one Dask client.

``o3drbf reconstruct --tiles auto|N --scheduler ADDR --workers N`` maps onto
:func:`reconstruct_tiled` (``--tiles`` takes :func:`o3drbf.options.count_or_auto`).
"""

from __future__ import annotations

import time

import numpy as np

from o3drbf.tiles.cluster import tile_client
from o3drbf.tiles.extract import extract_tiled
from o3drbf.tiles.fit import fit_tiled, point_source, tile_count
from o3drbf.tiles.surface import TiledSurface

__all__ = ["reconstruct_tiled", "merge_workers"]


def merge_workers(*summaries: dict) -> dict:
    """One per-worker table from several :func:`o3drbf.tiles.cluster.worker_summary` tables (tasks and seconds add, peaks max)."""
    out: dict = {}
    for summary in summaries:
        for name, w in summary.items():
            m = out.setdefault(name, {"tasks": 0, "seconds": 0.0, "peak_rss": 0})
            m["tasks"] += int(w["tasks"])
            m["seconds"] += float(w["seconds"])
            m["peak_rss"] = max(m["peak_rss"], int(w["peak_rss"]))
    return dict(sorted(out.items()))


def reconstruct_tiled(points, normals=None, *, cameras=None, point_camera=None, options=None, seed: int = 0, progress: bool = False,
                      **option_values) -> tuple[TiledSurface, object, dict]:
    """Tiled fit and tiled marching cubes on the same client, with the untiled path's stages in every fit.

    Parameters
    ----------
    points : (N, 3) array_like, PointSet or o3drbf.io.files.PlyVertices
        A memory-mapped binary PLY (with normals) is read in chunks, never whole.
    normals : (N, 3) array_like, optional
    cameras : sequence of Camera, CameraSet or path, optional
        Cameras or scanners: free space (exterior constraints, outliers) as on the untiled path.
    point_camera : (N,) int array_like, optional
    options : Options, optional
        All options (:class:`o3drbf.options.Options`): the ``tiles`` group
        sizes the tiles and says where they run (``scheduler``: None a
        LocalCluster of ``workers`` processes when there is more than one
        tile, "synchronous", or an address), ``extract`` the lattice, the
        others each fit (:func:`o3drbf.tiles.fit.fit_tiled`).
    seed : int
    progress : bool
    **option_values
        Keys of :data:`o3drbf.options.DEFAULTS` over ``options`` (``tiles=8``, ``resolution=256``, ...).

    Returns
    -------
    surface : TiledSurface
    mesh : open3d.geometry.TriangleMesh
    stats : dict
        ``tiles``, ``points`` (read), ``kept`` and ``outliers`` (each point
        counted in the tile whose cell holds it), ``constraints`` (per tile:
        ``min``, ``median``, ``max``), ``denoised_tiles``, ``cameras``,
        ``overlap`` and ``min_overlap``, ``fit_seconds``, ``extract_seconds``,
        ``workers`` (per worker: ``tasks``, ``seconds`` of task time and
        ``peak_rss`` bytes, the worker process's peak during the fit and the
        meshing), the extraction record, ``vertices``, ``triangles``.

    Examples
    --------
    >>> from o3drbf.synthetic.shapes import Torus
    >>> from o3drbf.tiles.run import reconstruct_tiled
    >>> pts, nrm = Torus(0.7, 0.25).sample(2000, seed=1)
    >>> surface, mesh, stats = reconstruct_tiled(pts, nrm, tiles=2, scheduler="synchronous", resolution=32, global_count=300)
    >>> stats["tiles"], stats["kept"], mesh.is_watertight()
    (2, 2000, True)
    """
    from o3drbf.tiles.fit import tile_options

    opts = tile_options(options, **option_values)
    source, camera_list = point_source(points, normals, cameras=cameras, point_camera=point_camera, seed=seed)
    count = tile_count(source.count, opts.tiles.tiles, opts.tiles.points_per_tile)  # at most; fit_tiled may need fewer
    with tile_client(opts.tiles.scheduler, tasks=count, workers=opts.tiles.workers, memory_limit=opts.tiles.memory_limit) as client:
        run_on = "synchronous" if client is None else client
        t0 = time.perf_counter()
        surface = fit_tiled(source, cameras=camera_list, options=opts, client=run_on, seed=seed, progress=progress)
        t1 = time.perf_counter()
        extraction = {}
        mesh = extract_tiled(surface, opts, client=run_on, progress=progress, stats=extraction)
        t2 = time.perf_counter()
    meta = surface.metadata
    cons = np.array([t["constraints"] for t in meta["tiles"]])
    stats = {"tiles": int(meta["tile_count"]), "points": int(source.count), "kept": int(meta["kept"]), "outliers": int(meta["outliers"]),
             "subsampled_tiles": int(meta["subsampled_tiles"]),
             "denoised_tiles": int(meta["denoised_tiles"]), "cameras": int(meta["cameras"]),
             "constraints": {"min": int(cons.min()), "median": float(np.median(cons)), "max": int(cons.max())},
             "overlap": float(meta["overlap"]), "min_overlap": float(meta["min_overlap"]),
             "fit_seconds": t1 - t0, "extract_seconds": t2 - t1, "extraction": extraction,
             "workers": merge_workers(meta["workers"], extraction["workers"]),
             "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}
    return surface, mesh, stats
