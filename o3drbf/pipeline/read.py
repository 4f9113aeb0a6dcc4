"""Read: the input made consistent before any costly step (repeated points merged, cameras inside the data dropped)."""

from __future__ import annotations

import logging

import numpy as np

from o3drbf.pointset import PointSet

__all__ = ["MIN_DISTINCT_POINTS", "merge_repeated", "drop_cameras_within_data"]

log = logging.getLogger("o3drbf")


#: Fewest distinct points a reconstruction takes (``PointSet.create``'s ``min_count``).
MIN_DISTINCT_POINTS = 10


def merge_repeated(data: PointSet) -> tuple[PointSet, int]:
    """Merge exactly repeated points (real pipelines produce them), averaging their normals and colours.

    Returns the PointSet and how many rows were merged (logged when any).
    """
    from o3drbf.prep.duplicates import merge_duplicates

    points, normals, colors, point_camera, merged = merge_duplicates(data.points, data.normals, data.colors, data.point_camera)
    if not merged:
        return data, 0
    if len(points) < MIN_DISTINCT_POINTS:
        n = len(points) + merged
        what = "copies of one point" if len(points) == 1 else f"copies of {len(points)} points"
        raise ValueError(f"all {n:,} points are {what}: {merged:,} repeats removed, {len(points)} distinct left; at least "
                         f"{MIN_DISTINCT_POINTS} distinct points are needed (check how the file was exported)")
    log.warning("%d repeated point(s) merged", merged)
    kept = PointSet.create(points, normals, cameras=data.cameras, point_camera=point_camera, colors=colors, source=data.source)
    return kept, merged


def drop_cameras_within_data(data: PointSet) -> tuple[PointSet, list[str]]:
    """Drop the cameras whose centre lies within the data: at a point, or closer to one than the visibility test can resolve.

    A camera that close (within the ray margin of
    :mod:`o3drbf.constraints.visibility`, ``VOXEL_SPACINGS * MARGIN_VOXELS``
    mean point spacings) would be taken to see every point near it with
    nothing tested in between, and would place exterior (free-space)
    constraints along the surface or inside the object; a camera exactly at
    a point has no direction toward it at all.  Such a camera is a wrong
    pose (or a sensor position that is not a viewpoint): it is dropped, its
    points are kept as points of unknown camera, and a warning names it.

    Parameters
    ----------
    data : PointSet

    Returns
    -------
    PointSet
        Without those cameras (the same object when none is dropped).
    list of str
        The dropped cameras, e.g. ``"camera 3 (img03.png)"``.

    Raises
    ------
    ValueError
        Every camera lies within the data.
    """
    if data.cameras is None:
        return data, []
    from dataclasses import replace

    from o3drbf.constraints.visibility import MARGIN_VOXELS, VOXEL_SPACINGS

    clearance = VOXEL_SPACINGS * MARGIN_VOXELS * data.spacing
    with_centre = [k for k, cam in enumerate(data.cameras) if cam.kind != "direction"]
    if not with_centre:
        return data, []
    distance, _ = data.kdtree.query(np.array([data.cameras[k].center for k in with_centre]))
    inside = {k: float(d) for k, d in zip(with_centre, distance) if d <= clearance}
    if not inside:
        return data, []
    labels = [f"camera {k}" + (f" ({data.cameras[k].name})" if data.cameras[k].name else "") for k in inside]
    spacings = max(inside.values()) / data.spacing
    limit = clearance / data.spacing
    if len(inside) == len(data.cameras):
        raise ValueError(f"every camera lies within the data (at most {spacings:.2g} point spacings from a point, closer than the "
                         f"{limit:.3g} the visibility test resolves): no free space can be proved; check the camera poses "
                         "(x_cam = R X + t, looking along +z), or give normals and leave --cameras out")
    one = len(labels) == 1
    log.warning("%s %s %.2g point spacings from a data point, closer than the %.3g the visibility test resolves (inside the data): "
                "%s free-space constraints dropped, %s points kept; check %s pose", ", ".join(labels), "lies" if one else "lie (at most)",
                spacings, limit, "its" if one else "their", "its" if one else "their", "its" if one else "their")
    kept = [k for k in range(len(data.cameras)) if k not in inside]
    point_camera = None
    if data.point_camera is not None:
        new = np.full(len(data.cameras), -1, dtype=np.int64)
        new[kept] = np.arange(len(kept))
        point_camera = np.where(data.point_camera >= 0, new[np.maximum(data.point_camera, 0)], -1)
        point_camera = None if (point_camera < 0).all() else point_camera
    return replace(data, cameras=[data.cameras[k] for k in kept], point_camera=point_camera, _cache=data._cache), labels
