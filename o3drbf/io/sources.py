"""Surface data in the forms vision pipelines produce, turned into points.

- :func:`points_from_depth`: a depth (range) image and its pinhole camera.
- :func:`points_from_voxels`: an occupancy grid (space carving, voxel
  colouring) with its origin and voxel size, or an Open3D ``VoxelGrid``.

Both return points in world coordinates (plus the camera index of each
depth point, or the colours of voxels), ready for :func:`o3drbf.reconstruct`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from o3drbf.validation import check_number

__all__ = ["points_from_depth", "points_from_voxels", "read_voxel_grid"]


def points_from_depth(depth, camera, depth_scale: float = 1.0, max_depth: float | None = None, camera_index: int = 0):
    """Back-project a depth image through its pinhole camera.

    Parameters
    ----------
    depth : (H, W) array_like
        Depth along the camera's z axis per pixel (``x_cam = R X + t``);
        0, negative or NaN means no measurement.
    camera : o3drbf.cameras.model.Camera
        A pinhole camera whose image is ``W x H``.
    depth_scale : float
        Divide raw values by this (e.g. 1000 for millimetre PNGs).
    max_depth : float, optional
        Ignore measurements farther than this.
    camera_index : int
        Written into the returned ``point_camera``.

    Returns
    -------
    points : (N, 3) array
        World coordinates of the valid pixels.
    point_camera : (N,) int array
        ``camera_index`` for every point (it saw them, by definition).

    Raises
    ------
    ValueError
        A depth that is not 2-D, does not match the camera's image size, has
        no valid pixel, or a camera that is not a pinhole.
    """
    d = np.asarray(depth, dtype=float)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D image, got shape {d.shape}")
    if getattr(camera, "kind", "pinhole") != "pinhole" or camera.K is None:
        raise ValueError("points_from_depth needs a pinhole camera (K, R, t)")
    if camera.width is not None and camera.height is not None and d.shape != (camera.height, camera.width):
        raise ValueError(f"depth image is {d.shape[1]}x{d.shape[0]} but the camera's image is {camera.width}x{camera.height}")
    depth_scale = check_number("depth_scale", depth_scale, low=0.0, low_open=True)
    d = d / depth_scale
    valid = np.isfinite(d) & (d > 0)
    if max_depth is not None:
        valid &= d <= check_number("max_depth", max_depth, low=0.0, low_open=True)
    if not valid.any():
        raise ValueError("depth image has no valid pixel (all zero, negative, NaN or beyond max_depth)")
    v, u = np.nonzero(valid)
    z = d[v, u]
    K = np.asarray(camera.K, dtype=float)
    # pixel = K x_cam / z, with pixel (u, v) at the pixel's index
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    cam = np.column_stack([x * z, y * z, z])
    R = np.asarray(camera.R, dtype=float)
    t = np.asarray(camera.t, dtype=float)
    world = (cam - t) @ R  # R^T (x_cam - t), row-wise
    return world, np.full(len(world), int(camera_index), dtype=np.int64)


def points_from_voxels(occupancy, origin=(0.0, 0.0, 0.0), voxel_size: float = 1.0, colors=None, keep_components: int | None = 1):
    """Centres of occupied voxels, optionally keeping the largest 26-connected parts.

    Parameters
    ----------
    occupancy : (X, Y, Z) bool array_like, or (V, 3) int array of voxel indices
    origin : (3,) array_like
        World position of voxel (0, 0, 0)'s centre.
    voxel_size : float
    colors : (X, Y, Z, 3) or (V, 3) array_like, optional
        Per-voxel colours in [0, 1].
    keep_components : int or None
        Keep this many largest 26-connected components (stray voxels are
        removed); None keeps everything.

    Returns
    -------
    points : (N, 3) array
    colors : (N, 3) array or None
    report : o3drbf.prep.outliers.OutlierReport or None

    Raises
    ------
    ValueError
        No occupied voxel, wrong shapes, a non-positive voxel size.
    """
    from o3drbf.prep.outliers import voxel_components

    voxel_size = check_number("voxel_size", voxel_size, low=0.0, low_open=True)
    origin = np.asarray(origin, dtype=float)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"origin must be 3 finite numbers, got {origin.tolist()}")
    occ = np.asarray(occupancy)
    cols = None if colors is None else np.asarray(colors, dtype=float)
    if occ.ndim == 3:
        idx = np.argwhere(occ.astype(bool))
        if cols is not None:
            if cols.shape != occ.shape + (3,):
                raise ValueError(f"colors must have shape {occ.shape + (3,)}, got {cols.shape}")
            cols = cols[occ.astype(bool)]
    elif occ.ndim == 2 and occ.shape[1] == 3:
        idx = occ.astype(np.int64)
        if cols is not None and cols.shape != (len(idx), 3):
            raise ValueError(f"colors must have shape ({len(idx)}, 3), got {cols.shape}")
    else:
        raise ValueError(f"occupancy must be an (X, Y, Z) boolean grid or (V, 3) voxel indices, got shape {occ.shape}")
    if len(idx) == 0:
        raise ValueError("the voxel grid has no occupied voxel")
    report = None
    if keep_components is not None:
        kept, report = voxel_components(idx, keep=keep_components)
        idx = idx[kept]
        cols = None if cols is None else cols[kept]
    return origin + idx * voxel_size, cols, report


def read_voxel_grid(path: str | os.PathLike):
    """Read an Open3D voxel grid file: ``(indices (V, 3), origin (3,), voxel_size, colors (V, 3) or None)``.

    ``origin`` is the centre of voxel (0, 0, 0), as :func:`points_from_voxels` expects.
    """
    import open3d as o3d

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"voxel grid file not found: {path}")
    grid = o3d.io.read_voxel_grid(str(path))
    voxels = grid.get_voxels()
    if not voxels:
        raise ValueError(f"{path} holds no voxels (empty, or not an Open3D voxel grid file)")
    idx = np.array([v.grid_index for v in voxels], dtype=np.int64)
    cols = np.array([v.color for v in voxels], dtype=float)
    size = float(grid.voxel_size)
    origin = np.asarray(grid.origin, dtype=float) + 0.5 * size
    return idx, origin, size, (cols if cols.any() else None)
