"""Open3D's reconstructions, run the way a user would, for comparison."""

from __future__ import annotations

import numpy as np

from o3drbf.progress import native_output_logged
from o3drbf.validation import as_points, as_vectors, check_number

__all__ = ["poisson"]


def poisson(points, normals, depth: int = 8, density_quantile: float = 0.0, threads: int | None = None):
    """Open3D screened Poisson reconstruction.

    Parameters
    ----------
    points, normals : (N, 3) array_like
    depth : int
        Octree depth, 1..12.
    density_quantile : float
        Remove vertices whose density is below this quantile (0: keep all,
        closed surface; Open3D's usual trimming uses ~0.01-0.05).
    threads : int, optional
        Open3D's ``n_threads`` (-1: all cores).  Default: one thread on a busy machine
        (:func:`o3drbf.solvers.base.busy_machine`), else all cores.  Open3D's threaded
        Poisson crashes the process at random when more work than cores is waiting
        (isl-org/Open3D#6828, #7229), and on a busy machine one thread is as fast.

    Returns
    -------
    open3d.geometry.TriangleMesh
    """
    import open3d as o3d

    pts = as_points(points, min_count=4)
    nrm = as_vectors(normals, len(pts))
    depth = check_number("depth", depth, low=1, high=12, integer=True)
    q = check_number("density_quantile", density_quantile, low=0.0, high=1.0)
    if threads is None:
        from o3drbf.solvers.base import busy_machine

        threads = 1 if busy_machine() else -1
    threads = check_number("threads", threads, low=-1, integer=True)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pcd.normals = o3d.utility.Vector3dVector(nrm)
    # PoissonRecon prints its warnings ("bad average roots") past Open3D's verbosity: one log line at -v instead
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error), native_output_logged("Open3D Poisson"):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, n_threads=int(threads or -1))
    if q > 0:
        dens = np.asarray(dens)
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, q))
    mesh.compute_vertex_normals()
    return mesh
