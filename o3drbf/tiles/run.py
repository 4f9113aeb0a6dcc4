"""One call for the command line: fit and mesh tile by tile on one Dask client.

``o3drbf reconstruct --tiles auto|N --scheduler ADDR --workers N`` maps onto
:func:`reconstruct_tiled` (see :func:`tiles_argument` for ``--tiles``).
"""

from __future__ import annotations

import time

from o3drbf.tiles.cluster import tile_client
from o3drbf.tiles.extract import extract_tiled
from o3drbf.tiles.fit import fit_tiled, tile_count
from o3drbf.tiles.surface import TiledSurface
from o3drbf.validation import as_points

__all__ = ["reconstruct_tiled", "tiles_argument"]


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
    points : (N, 3) array_like
    normals : (N, 3) array_like, optional
    tiles : "auto" or int
    scheduler : None, "synchronous" or a Dask scheduler address
        None: a LocalCluster of ``workers`` processes when there is more than one tile.
    workers : int
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
        ``tiles``, ``fit_seconds``, ``extract_seconds`` and the extraction record.
    """
    n = len(as_points(points, min_count=10))
    count = tile_count(n, tiles, fit_options.get("points_per_tile", 60_000))
    with tile_client(scheduler, tasks=count, workers=workers) as client:
        run_on = "synchronous" if client is None else client
        t0 = time.perf_counter()
        surface = fit_tiled(points, normals, tiles=count, client=run_on, seed=seed, progress=progress, **fit_options)
        t1 = time.perf_counter()
        extraction = {}
        mesh = extract_tiled(surface, resolution=resolution, voxel_size=voxel_size, bounds=bounds, client=run_on,
                             progress=progress, stats=extraction)
        t2 = time.perf_counter()
    stats = {"tiles": count, "fit_seconds": t1 - t0, "extract_seconds": t2 - t1, "extraction": extraction,
             "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}
    return surface, mesh, stats
