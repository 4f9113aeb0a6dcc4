"""E57 scans with their scanner poses: points in world coordinates and one scanner camera per scan.

An E57 scan stores its points in its own frame and, optionally, a pose
(rotation quaternion ``q`` and translation ``t``) that takes them to the
file's world frame: ``X = R(q) @ p_scan + t``.  A terrestrial scanner sits
at the origin of its scan frame and sees all around, so each posed scan
becomes a ``"center"`` :class:`~o3drbf.cameras.model.Camera` at ``t`` with
the scan's frame (:meth:`~o3drbf.cameras.model.Camera.from_pose`), as a
Stanford ``.conf`` pose becomes a direction sensor.  Exterior constraints
then go toward the scanner and the free-space outlier check uses its
spherical z-buffer.

A scan without a pose is read in the file's frame (the E57 standard's
identity default) but gives no scanner: its position is unknown, and a
scanner guessed at the origin would carve free space through the object.
One log line says so.  A pose with NaN or infinite values is refused,
naming the scan.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from o3drbf.cameras.model import Camera, CameraSet, quaternion_to_matrix, unit_quaternion
from o3drbf.io.lidar import CHUNK_POINTS, e57_chunks, e57_scans

__all__ = ["load_e57", "scan_camera"]

log = logging.getLogger("o3drbf")


def scan_camera(path, scan) -> Camera:
    """The scanner camera of one E57 scan (:class:`o3drbf.io.lidar.E57Scan` with a pose).

    Raises
    ------
    ValueError
        The pose has NaN or infinite values, or a quaternion that is not of
        unit length; the message names the file and the scan.
    """
    where = f"{path}, scan {scan.index} {scan.name!r}"
    q, t = np.asarray(scan.rotation, dtype=float), np.asarray(scan.translation, dtype=float)
    values = np.concatenate([q, t])
    # libe57 reads a number too large for a double as +-DBL_MAX: an overflow, not a position
    if not (np.isfinite(values) & (np.abs(values) < np.finfo(float).max)).all():
        raise ValueError(f"{where}: the pose has NaN or infinite values (rotation w x y z {q.tolist()}, translation {t.tolist()}); "
                         "fix the pose or remove the scan (nothing was written)")
    try:
        w, x, y, z = q
        R = quaternion_to_matrix(*unit_quaternion([x, y, z, w]))
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    return Camera.from_pose(R, t, name=scan.name)


def load_e57(path: str | os.PathLike, chunk_size: int = CHUNK_POINTS) -> CameraSet:
    """Read every scan of an E57 file in world coordinates, with a scanner camera per posed scan.

    Every pose is checked before any point is read; the points are then
    read scan by scan, in chunks, into one array.

    Parameters
    ----------
    path : path-like
    chunk_size : int
        Point records decoded at a time.

    Returns
    -------
    CameraSet
        ``cameras``: one ``"center"`` scanner per scan with a pose, in file
        order (empty when no scan has one); ``points`` (N, 3) in world
        coordinates; ``point_camera`` (N,): the camera of each point's scan
        (its scan index when every scan has a pose), -1 for scans without a
        pose, or None when no scan has one.

    Raises
    ------
    ImportError
        pye57 is missing; the message names the install.
    FileNotFoundError, ValueError
        Missing, truncated or corrupt files, NaN poses, no valid point.
    """
    path = Path(path)
    scans = e57_scans(path)
    cameras, owner_of = [], []
    for scan in scans:
        if scan.has_pose:
            owner_of.append(len(cameras))
            cameras.append(scan_camera(path, scan))
        else:
            owner_of.append(-1)
    total = sum(s.count for s in scans)
    points = np.empty((total, 3))
    owner = np.empty(total, dtype=np.int64)
    k = 0
    for scan, j in zip(scans, owner_of):
        if j >= 0:
            cam = cameras[j]
            R, t = cam.R.T, cam.center  # scan -> world
        for local in e57_chunks(path, scan, chunk_size):
            m = len(local)
            points[k:k + m] = local if j < 0 else np.einsum("ij,kj->ki", R, local) + t
            owner[k:k + m] = j
            k += m
    if k == 0:
        raise ValueError(f"{path}: no points (every record is marked invalid, or the scans are empty)")
    points, owner = points[:k], owner[:k]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise ValueError(f"{path}: {int(bad.sum())} point(s) with NaN or infinite coordinates (first at index {int(np.argmax(bad))})")
    missing = [s for s in scans if not s.has_pose]
    if missing:
        shown = ", ".join(f"{s.index} {s.name!r}" for s in missing[:3]) + (", ..." if len(missing) > 3 else "")
        log.warning("%s: %d of %d scan(s) have no pose (%s): their points are read in the file's frame, without a scanner "
                    "position, so no free-space constraints nor free-space outlier check come from them", path, len(missing),
                    len(scans), shown)
    point_camera = owner if cameras else None
    return CameraSet(cameras, points, None, point_camera, None, str(path), "e57")
