"""One call for the command line: fit and mesh tile by tile on one Dask client.

``o3drbf reconstruct --tiles auto|N --scheduler ADDR --workers N`` maps onto
:func:`reconstruct_tiled` (see :func:`tiles_argument` for ``--tiles``).
"""

from __future__ import annotations

import time

import numpy as np

from o3drbf.tiles.cluster import tile_client
from o3drbf.tiles.extract import extract_tiled
from o3drbf.tiles.fit import fit_tiled, point_source, tile_count
from o3drbf.tiles.surface import TiledSurface

__all__ = ["reconstruct_tiled", "tiles_argument", "merge_workers"]


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


def tiles_argument(text: str):
    """argparse ``type=`` for ``--tiles``: "auto" or a whole number >= 1."""
    from o3drbf.options import count_or_auto

    return count_or_auto(text)


def reconstruct_tiled(
    points,
    normals=None,
    *,
    tiles="auto",
    scheduler=None,
    workers: int = 2,
    memory_limit=None,
    resolution: int | None = 128,
    voxel_size: float | None = None,
    bounds=None,
    seed: int = 0,
    progress: bool = False,
    **fit_options,
) -> tuple[TiledSurface, object, dict]:
    """Tiled fit and tiled marching cubes on the same client.

    Parameters
    ----------
    points : (N, 3) array_like or o3drbf.io.files.PlyVertices
        A memory-mapped binary PLY (with normals) is read in chunks, never whole.
    normals : (N, 3) array_like, optional
    tiles : "auto" or int
    scheduler : None, "synchronous" or a Dask scheduler address
        None: a LocalCluster of ``workers`` processes when there is more than one tile.
    workers : int
    memory_limit : int or str, optional
        Per-worker memory limit of a LocalCluster started here (default 80 % of
        the available memory divided among the workers).
    resolution, voxel_size, bounds
        As in :func:`o3drbf.tiles.extract.extract_tiled`.
    seed, progress
    **fit_options
        Passed to :func:`o3drbf.tiles.fit.fit_tiled`.

    Returns
    -------
    surface : TiledSurface
    mesh : open3d.geometry.TriangleMesh
    stats : dict
        ``tiles``, ``points``, ``constraints`` (per tile: ``min``, ``median``,
        ``max``), ``overlap`` and ``min_overlap`` (the blend margin: a fraction
        of each cell's half-size, at least ``min_overlap`` box units),
        ``fit_seconds``, ``extract_seconds``, ``workers`` (per worker: ``tasks``,
        ``seconds`` of task time and ``peak_rss`` bytes, measured on the worker
        during the fit and the meshing), the extraction record, ``vertices``, ``triangles``.
    """
    from o3drbf.options import TILE_DEFAULTS

    source = point_source(points, normals, seed=seed)
    count = tile_count(source.count, tiles, fit_options.get("points_per_tile", TILE_DEFAULTS["points_per_tile"]))
    with tile_client(scheduler, tasks=count, workers=workers, memory_limit=memory_limit) as client:
        run_on = "synchronous" if client is None else client
        t0 = time.perf_counter()
        surface = fit_tiled(source, tiles=count, client=run_on, seed=seed, progress=progress, **fit_options)
        t1 = time.perf_counter()
        extraction = {}
        mesh = extract_tiled(surface, resolution=resolution, voxel_size=voxel_size, bounds=bounds, client=run_on,
                             progress=progress, stats=extraction)
        t2 = time.perf_counter()
    meta = surface.metadata
    cons = np.array([t["constraints"] for t in meta["tiles"]])
    stats = {"tiles": count, "points": int(source.count),
             "constraints": {"min": int(cons.min()), "median": float(np.median(cons)), "max": int(cons.max())},
             "overlap": float(meta["overlap"]), "min_overlap": float(meta["min_overlap"]),
             "fit_seconds": t1 - t0, "extract_seconds": t2 - t1, "extraction": extraction,
             "workers": merge_workers(meta["workers"], extraction["workers"]),
             "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}
    return surface, mesh, stats
